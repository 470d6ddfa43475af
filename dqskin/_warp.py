"""Device choice for the package. Launching (and CPU chunking) lives beside the kernels, in
:mod:`dqskin.kernels.grid`; the package leaves Warp's global configuration alone (kernel modules
set their own options; the CLI quiets Warp's console output)."""

import warp as wp

Device = str | wp.Device | None
"""A Warp device or its name (``"cpu"``, ``"cuda:0"``); None picks CUDA when present."""


def resolve_device(device: Device = None) -> wp.Device:
    """Warp device for ``device`` (``None`` → CUDA when present, else CPU); ValueError if there
    is no such device."""
    wp.init()
    if device is None:
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    try:
        return wp.get_device(device)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"device {device!r}: {exc}") from None
