"""Device choice for the package. Launching (and CPU chunking) lives beside the kernels, in
:mod:`dqskin.kernels.grid`; the package leaves Warp's global configuration alone (kernel modules
set their own options; the CLI quiets Warp's console output)."""

import threading

import warp as wp

from .errors import InputError, Param

Device = str | wp.Device | None
"""A Warp device or its name (``"cpu"``, ``"cuda:0"``); None picks CUDA when present."""


_init_lock = threading.Lock()
_initialized = False


def init_warp() -> None:
    """``wp.init()``, once per process and under a lock. Warp's own is not thread-safe: two
    threads making their first dqskin call at once (a pipeline's worker threads, the concurrent
    tasks of a ``dask worker --nthreads N``) would each create a runtime, and the second would
    clear the module hashes the first is loading a kernel module with (``KeyError`` in
    ``Module.load``)."""
    global _initialized
    if not _initialized:
        with _init_lock:
            if not _initialized:
                wp.init()
                _initialized = True


def resolve_device(device: Device = None) -> wp.Device:
    """Warp device for ``device`` (``None`` → CUDA when present, else CPU); InputError (a
    ValueError) naming the ``device`` parameter if there is no such device."""
    init_warp()
    if device is None:
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    try:
        return wp.get_device(device)
    except (RuntimeError, ValueError) as exc:
        raise InputError(Param("device", device), f": {exc}") from None
