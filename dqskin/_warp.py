"""Warp set-up shared by the package: configuration, device choice, CPU chunked launches."""

import os
from concurrent.futures import ThreadPoolExecutor

import warp as wp

wp.config.enable_backward = False
wp.config.quiet = True
wp.config.log_level = wp.LOG_ERROR  # no init banner or per-module load timings on stdout

_pool = None


def resolve_device(device=None):
    """Warp device for ``device`` (``None`` → CUDA when present, else CPU)."""
    if device is None:
        wp.init()
        return wp.get_device("cuda:0" if wp.get_cuda_device_count() > 0 else "cpu")
    return wp.get_device(device)


def cpu_threads():
    """Threads used for CPU launches (``DQSKIN_THREADS`` or the core count)."""
    return max(1, int(os.environ.get("DQSKIN_THREADS", os.cpu_count() or 1)))


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
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="dqskin")
    bounds = [count * c // chunks for c in range(chunks + 1)]
    futures = [_pool.submit(launch, bounds[c], bounds[c + 1] - bounds[c]) for c in range(chunks)]
    for fut in futures:
        fut.result()
