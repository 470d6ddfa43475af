"""Output buffers of the launchers: on the CPU, large ones are backed by transparent huge pages.

A skinning result is fresh memory that the kernel writes once: with 4 KiB pages, the page faults
of first touch cost as much as the skinning itself (a 100 MB chunk of frames: 24,500 faults,
80-95 ms, against 22-24 ms with 2 MiB pages; freeing it 14 ms against 1-2 ms). NumPy asks the
kernel for huge pages for its own large arrays (``madvise(MADV_HUGEPAGE)``, Linux); Warp's CPU
allocator does not, so :func:`empty` does the same for the Warp arrays the launchers fill. Where
transparent huge pages are off, or not on Linux, it is a plain ``wp.empty``; NumPy's switch,
``NUMPY_MADVISE_HUGEPAGE=0`` in the environment, turns it off here too (a first touch of huge pages
can stall on memory compaction when free memory is fragmented: rare, but a latency spike).
"""

import ctypes
import os
import sys

import warp as wp

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


def empty(shape, dtype, device) -> wp.array:
    """``wp.empty(shape, dtype, device)``; on the CPU, a buffer of :data:`MIN_BYTES` or more
    asks for huge pages over its aligned interior before anything touches it (a hint: a
    refusal is ignored)."""
    a = wp.empty(shape, dtype=dtype, device=device)
    if _MADVISE is not None and a.device.is_cpu and a.capacity >= MIN_BYTES:
        lo = (a.ptr + HUGE_PAGE - 1) & ~(HUGE_PAGE - 1)
        hi = (a.ptr + a.capacity) & ~(HUGE_PAGE - 1)
        if hi > lo:
            _MADVISE(lo, hi - lo, _MADV_HUGEPAGE)
    return a
