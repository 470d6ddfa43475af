"""Warp helpers shared by the package: device choice and CPU chunked launches.

The package leaves Warp's global configuration alone (kernels set their own module options);
the CLI quiets Warp's console output.
"""

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

_pool = None
_pool_lock = threading.Lock()


def resolve_device(device=None):
    """Warp device for ``device`` (``None`` → CUDA when present, else CPU); ValueError if there
    is no such device."""
    wp.init()
    if device is None:
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    try:
        return wp.get_device(device)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"device {device!r}: {exc}") from None


def cpu_threads():
    """Threads used for CPU launches (``DQSKIN_THREADS`` or the core count)."""
    return max(1, int(os.environ.get("DQSKIN_THREADS", os.cpu_count() or 1)))


FRAME_BLOCK = 16
"""Frames one skinning thread handles: the joints of 16 frames stay in L1 while every vertex of
the block is skinned, and influences are read once per block."""


def _pool_map(tasks):
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=cpu_threads(), thread_name_prefix="dqskin")
    for fut in [_pool.submit(*t) for t in tasks]:
        fut.result()


def launch_blocks(launch, rows, frames, device, min_work=32768):
    """Call ``launch(block_offset, block_count, row_offset, row_count)`` over a grid of
    ``ceil(frames / FRAME_BLOCK)`` frame blocks × ``rows``.

    On CUDA one call covers the grid. On the CPU the grid is split along its longer axis into one
    piece per core, launched from a thread pool (Warp releases the GIL during CPU launches).
    """
    blocks = -(-frames // FRAME_BLOCK)
    threads = cpu_threads() if device.is_cpu else 1
    chunks = min(threads, max(1, rows * frames // min_work))
    if chunks <= 1:
        launch(0, blocks, 0, rows)
        return
    if blocks >= chunks and blocks * FRAME_BLOCK >= rows:
        cut = [blocks * c // chunks for c in range(chunks + 1)]
        _pool_map([(launch, cut[c], cut[c + 1] - cut[c], 0, rows) for c in range(chunks)])
    else:
        cut = [rows * c // chunks for c in range(chunks + 1)]
        _pool_map([(launch, 0, blocks, cut[c], cut[c + 1] - cut[c]) for c in range(chunks)])


def launch_rows(launch, count, device, min_chunk=4096):
    """Call ``launch(offset, n)`` over ``range(count)`` split in chunks.

    On CUDA one call covers everything. On the CPU, Warp runs a launch on one thread but releases
    the GIL, so chunks launched from a thread pool use every core.
    """
    threads = cpu_threads() if device.is_cpu else 1
    chunks = min(threads, max(1, count // min_chunk))
    if chunks <= 1:
        launch(0, count)
        return
    bounds = [count * c // chunks for c in range(chunks + 1)]
    _pool_map([(launch, bounds[c], bounds[c + 1] - bounds[c]) for c in range(chunks)])
