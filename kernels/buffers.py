"""Output buffers of the launchers: on the CPU, large ones are backed by transparent huge pages.

A skinning result is fresh memory that the kernel writes once: with 4 KiB pages, the page faults
of first touch cost as much as the skinning itself, and several times what they cost with 2 MiB
pages (freeing too). NumPy asks the
kernel for huge pages for its own large arrays (``madvise(MADV_HUGEPAGE)``, Linux); Warp's CPU
allocator does not, so :func:`empty` does the same for the Warp arrays the launchers fill. Where
transparent huge pages are off, or not on Linux, it is a plain ``wp.empty``; NumPy's switch,
``NUMPY_MADVISE_HUGEPAGE=0`` in the environment, turns it off here too (a first touch of huge pages
can stall on memory compaction when free memory is fragmented: rare, but a latency spike).

Inside :func:`reusing` (what :meth:`dqskin.Scene.skin_chunks` does around each chunk), a large
CPU buffer whose array has been dropped is handed out again (:class:`BufferPool`: to the next
request it fits, down to half its size): a stream of chunks of frames then runs on the same few
buffers instead of fresh memory for each chunk (faulted in and zeroed by the kernel each time,
or taken from a heap that the other allocations of a bake fragment until it grows by chunks).
"""

import contextlib
import contextvars
import ctypes
import os
import sys
import threading
import weakref
from collections.abc import Iterator
from typing import Any

import warp as wp

from .._warp import Device

HUGE_PAGE = 1 << 21
"""Transparent huge page size on x86-64 and most arm64 kernels (2 MiB)."""

MIN_BYTES = 2 * HUGE_PAGE
"""Smaller CPU buffers keep plain pages (they hold at most one aligned huge page)."""

_MADV_HUGEPAGE = 14


def _madvise():
    """libc's ``madvise`` (Linux, unless ``NUMPY_MADVISE_HUGEPAGE=0``), else None."""
    if not sys.platform.startswith("linux") or os.environ.get("NUMPY_MADVISE_HUGEPAGE") == "0":
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    fn.restype = ctypes.c_int
    return fn


_MADVISE = _madvise()


class BufferPool:
    """Large CPU buffers that :func:`empty` hands out again inside :func:`reusing`: each one
    once nothing references the array it was given as (nor a NumPy view of it), to the next
    request it is the smallest fit for, at most twice its size (a shorter last chunk of frames
    takes a buffer of the longer ones). What the pool holds is freed with it; a buffer still
    in use, when its array goes."""

    def __init__(self) -> None:
        self._free: list[wp.array] = []  # buffers (wp.array) nothing else references
        # reentrant: a collection inside take() may run a finalizer, which gives a buffer back
        self._lock = threading.RLock()

    def take(self, nbytes: int, device: wp.Device) -> "wp.array | None":
        """The smallest free buffer of ``nbytes`` to twice that on ``device``, or None (a small
        request does not take, and keep, a much larger buffer: an array cached by its caller
        keeps its buffer for good)."""
        with self._lock:
            fits = [(b.capacity, i) for i, b in enumerate(self._free)
                    if nbytes <= b.capacity <= 2 * nbytes and b.device == device]
            return self._free.pop(min(fits)[1]) if fits else None

    def give(self, base: wp.array) -> None:
        with self._lock:
            self._free.append(base)

    def __len__(self) -> int:
        """Free buffers."""
        return len(self._free)


_POOL: contextvars.ContextVar[BufferPool | None] = contextvars.ContextVar("dqskin_buffer_pool",
                                                                          default=None)


@contextlib.contextmanager
def reusing(pool: BufferPool) -> Iterator[None]:
    """Within the block (this thread or task: a context variable), :func:`empty` takes its CPU
    buffers of :data:`MIN_BYTES` or more from ``pool`` (kept by the caller across blocks), and
    they go back to it when their arrays go."""
    token = _POOL.set(pool)
    try:
        yield
    finally:
        _POOL.reset(token)


def empty(shape: int | tuple[int, ...] | list[int], dtype: Any, device: Device) -> wp.array:
    """``wp.empty(shape, dtype, device)`` (uninitialized); on the CPU, a buffer of
    :data:`MIN_BYTES` or more asks for huge pages over its aligned interior before anything
    touches it (a hint: a refusal is ignored), and inside :func:`reusing` is a free one of the
    pool's when it has one large enough."""
    pool = _POOL.get()
    dev = wp.get_device(device)
    if pool is None or not dev.is_cpu:
        return _new(shape, dtype, dev)
    dims = tuple(shape) if isinstance(shape, (tuple, list)) else (int(shape),)
    nbytes = wp.types.type_size_in_bytes(dtype)
    for n in dims:
        nbytes *= n
    if nbytes < MIN_BYTES:
        return _new(dims, dtype, dev)
    base = pool.take(nbytes, dev)
    if base is None:
        base = _new(dims, dtype, dev)
    # the caller gets an alias of the pool's buffer; when the alias goes, the buffer goes back
    # (the finalizer holds it, so it lives as long as the alias whatever becomes of the pool)
    alias: wp.array = wp.array(ptr=base.ptr, dtype=dtype, shape=dims, capacity=base.capacity,
                     device=dev)
    weakref.finalize(alias, pool.give, base).atexit = False
    return alias


def _new(shape: int | tuple[int, ...] | list[int], dtype: Any, device: Device) -> wp.array:
    a = wp.empty(shape, dtype=dtype, device=device)
    if (_MADVISE is not None and a.device is not None and a.device.is_cpu
            and a.capacity >= MIN_BYTES):
        lo = (a.ptr + HUGE_PAGE - 1) & ~(HUGE_PAGE - 1)
        hi = (a.ptr + a.capacity) & ~(HUGE_PAGE - 1)
        if hi > lo:
            _MADVISE(lo, hi - lo, _MADV_HUGEPAGE)
    return a
