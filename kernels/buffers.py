"""Output buffers of the launchers: on the CPU, large ones are mappings of their own, backed by
transparent huge pages.

A skinning result is fresh memory that the kernel writes once: with 4 KiB pages, the page faults
of first touch cost as much as the skinning itself (a 100 MB chunk of frames: 24,500 faults,
80-95 ms, against 22-24 ms with 2 MiB pages; freeing it 14 ms against 1-2 ms). NumPy asks the
kernel for huge pages for its own large arrays (``madvise(MADV_HUGEPAGE)``, Linux); Warp's CPU
allocator does not, so :func:`empty` does the same for the Warp arrays the launchers fill. Where
transparent huge pages are off (the kernel's ``transparent_hugepage/enabled`` is ``never``), or not
on Linux, it is a plain ``wp.empty``; NumPy's switch, ``NUMPY_MADVISE_HUGEPAGE=0`` in the
environment, turns it off here too (a first touch of huge pages can stall on memory compaction
when free memory is fragmented: rare, but a latency spike).

With huge pages on, such a buffer is mapped apart rather than taken from malloc's heap, and
unmapped when freed: a bake skins piece after piece of unequal sizes, and in the heap the holes
the pieces left filled with small allocations until the heap had grown by 45-60 MB of free
memory (:func:`empty`). Each piece is then faulted in afresh, 2 MiB at a time: a one-thread
worker baking CesiumMan × 10,000 as 12 clips took 46,000-55,000 page faults instead of 35,000,
in the same CPU time (0.71-0.94 against 0.67-0.88 s).
"""

import ctypes
import mmap
import os
import sys

import numpy as np
import warp as wp

HUGE_PAGE = 1 << 21
"""Transparent huge page size on x86-64 and most arm64 kernels (2 MiB)."""

MIN_BYTES = 2 * HUGE_PAGE
"""Smaller CPU buffers keep plain pages (they hold at most one aligned huge page)."""

_MADV_HUGEPAGE = 14


def _libc():
    """libc's ``(madvise, mmap, munmap)`` (Linux, unless ``NUMPY_MADVISE_HUGEPAGE=0``), else
    None."""
    if not sys.platform.startswith("linux") or os.environ.get("NUMPY_MADVISE_HUGEPAGE") == "0":
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        madvise, map_, unmap = libc.madvise, libc.mmap, libc.munmap
    except (OSError, AttributeError):
        return None
    madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    madvise.restype = ctypes.c_int
    map_.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                     ctypes.c_long]
    map_.restype = ctypes.c_void_p
    unmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    unmap.restype = ctypes.c_int
    return madvise, map_, unmap


def _huge_pages_on(path="/sys/kernel/mm/transparent_hugepage/enabled"):
    """Whether the kernel gives transparent huge pages to a mapping that asks (``[always]`` or
    ``[madvise]``)."""
    try:
        with open(path) as fh:
            mode = fh.read()
    except OSError:
        return False
    return "[always]" in mode or "[madvise]" in mode


_LIBC = _libc()
_MADVISE = None if _LIBC is None else _LIBC[0]
_MAPPER = None if _LIBC is None or not _huge_pages_on() else _LIBC[1:]
"""``(mmap, munmap)`` where large buffers are mappings of their own: with huge pages on, as
fresh 4 KiB pages would be faulted in again for each piece of a bake."""
_MAP_FAILED = ctypes.c_void_p(-1).value


def _unmap(ptr, size):
    _MAPPER[1](ptr, size)


def empty(shape, dtype, device) -> wp.array:
    """``wp.empty(shape, dtype, device)``; on the CPU, where huge pages are on, a buffer of
    :data:`MIN_BYTES` or more is a mapping of its own, unmapped when the array is freed, that
    asks for huge pages before anything touches it (a hint: a refusal is ignored). Not from the
    heap: a process skinning piece after piece (a bake), pieces of unequal sizes (a clip's last
    one is shorter) and small allocations settling in the holes they left had grown the heap by
    45-60 MB over a clip bake's first chunks, all of it free (CesiumMan × 10,000, 854-frame
    clips)."""
    device = wp.get_device(device)
    nbytes = int(np.prod(shape, dtype=np.int64)) * wp.types.type_size_in_bytes(dtype)
    if _MAPPER is None or not device.is_cpu or nbytes < MIN_BYTES:
        return wp.empty(shape, dtype=dtype, device=device)
    size = -(-nbytes // mmap.PAGESIZE) * mmap.PAGESIZE
    ptr = _MAPPER[0](None, size, mmap.PROT_READ | mmap.PROT_WRITE,
                     mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, -1, 0)
    if ptr is None or ptr == _MAP_FAILED:
        return wp.empty(shape, dtype=dtype, device=device)
    lo = (ptr + HUGE_PAGE - 1) & ~(HUGE_PAGE - 1)
    hi = (ptr + size) & ~(HUGE_PAGE - 1)
    if hi > lo:
        _MADVISE(lo, hi - lo, _MADV_HUGEPAGE)
    return wp.array(ptr=ptr, dtype=dtype, shape=shape, device=device, capacity=size,
                    deleter=_unmap)
