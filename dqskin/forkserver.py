"""The forkserver that a LocalCluster bake's worker processes (``workers=N``) are forked from.

Dask spawns each worker process afresh by default, and each then imports Dask, NumPy, USD, Warp
and dqskin itself. A bake instead starts them from multiprocessing's forkserver that has imported
those once (:data:`PRELOAD`); :func:`prestart_workers` starts it early so that its imports
overlap the caller's own work: a ``workers=N`` bake calls it while it bakes the clip that
decides whether the workers pay (:mod:`dqskin.distributed`). :func:`stop_workers` stops it
when the bake ends.

Importing this module imports nothing heavy; :func:`prestart_workers` imports Dask, not
``distributed`` (slower to import): Dask's settings for worker processes come from Dask's config
with ``distributed``'s defaults read from its own YAML file, as ``distributed.config`` does.
"""

import contextlib
import os
import signal
import sys
from collections.abc import Iterator

__all__ = ["MAX_WORKERS_PER_CORE", "PRELOAD", "dask_config", "freeze_heap", "keep_freed_memory",
           "max_workers", "prestart_workers", "stop_workers"]

PRELOAD = ["distributed", "numpy", "dqskin.distributed", "dqskin.readers.usd"]
"""Modules the forkserver imports once; every worker process forked from it starts with them
(instead of each worker importing them itself)."""

_CONFIG = {"distributed.worker.multiprocessing-method": "forkserver",
           "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
           "distributed.worker.profile.enabled": False}
"""Dask settings of a LocalCluster bake: workers from the forkserver, and without Dask's
``MALLOC_TRIM_THRESHOLD_=65536``: glibc reads it once, when the forkserver starts, and with it
every worker hands each chunk's freed memory back to the system and faults it in again for the
next, doubling the workers' system time; and without Dask's statistical profiler, which samples
every thread's stack (it competes for the GIL with each chunk's short-lived threads)."""


MAX_WORKERS_PER_CORE = 4
"""Local Dask worker processes allowed per CPU core (:func:`max_workers`)."""


def max_workers() -> int:
    """Most local worker processes a bake starts (``workers``): :data:`MAX_WORKERS_PER_CORE`
    per CPU core (each worker is a process holding the asset, some 360 MB for a small one), or
    the whole number in the environment variable ``DQSKIN_MAX_WORKERS``."""
    given = os.environ.get("DQSKIN_MAX_WORKERS", "").strip()
    if given.isdigit() and int(given) >= 1:
        return int(given)
    return MAX_WORKERS_PER_CORE * (os.cpu_count() or 1)


def _distributed_defaults() -> None:
    """Add ``distributed``'s default settings to Dask's config without importing it (what
    ``distributed.config`` does on import; it is then imported all the same, for the cluster);
    no-op when it is imported or its YAML file is not where it keeps it."""
    if "distributed.config" in sys.modules:
        return
    import importlib.util

    import dask
    import yaml
    spec = importlib.util.find_spec("distributed")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = os.path.join(folder, "distributed.yaml")
        if os.path.isfile(path):
            with open(path) as fh:
                dask.config.update_defaults(yaml.safe_load(fh))
            return


RETAIN_BYTES = 256 << 20
"""Freed memory at the top of a bake process's heap that glibc keeps for reuse
(:func:`keep_freed_memory`)."""

HEAP_BELOW_BYTES = 8 << 20
"""Allocations below this size come from the heap (reused); larger ones that the heap has no
free room for are mapped apart and handed back when freed. Chunks of skinned frames (at least
256 frames: 10 MB of CesiumMan's points; on huge pages, :mod:`dqskin.kernels.buffers` and
NumPy's own) are such blocks: in the heap, chunks of unequal sizes (a clip's last chunk is
shorter) would leave holes that small allocations fill, and a worker's heap would grow with free
memory over its first tasks. (In a library call's process, NumPy and glibc's defaults stand:
mapping each large output afresh there would cost the kernel's zeroing of its pages on every
call.)"""


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for reuse in this process: each chunk of a bake
    frees its samples (a clip layer's ``Vt`` arrays, tens of MB) and the next one allocates as
    much again. With glibc's defaults the heap is trimmed after every chunk and the next one
    faults its memory in again, 4 KiB at a time. Pieces of frames are mapped apart
    (:data:`HEAP_BELOW_BYTES`). Peak memory still follows the chunk size, not the clip length;
    freed memory stays with the process until it exits.

    Called only on the workers of the LocalCluster a bake starts (dqskin's own processes): never
    by a library call nor on the workers of a cluster given as ``--scheduler``, whose processes
    are the caller's. The ``dqskin`` program leaves its own malloc alone (its pipelined
    in-process bake gains nothing from this).
    Returns whether it applied: glibc on Linux only (the mmap threshold first; the trim threshold,
    which turns glibc's adaptive thresholds off, only when that was accepted)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):  # None: unknown
            return False
        import ctypes
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, ValueError, AttributeError, TypeError):
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3
    return bool(mallopt(m_mmap_threshold, HEAP_BELOW_BYTES)
                and mallopt(m_trim_threshold, RETAIN_BYTES))


def freeze_heap() -> None:
    """Move every object this process holds now (the modules it imported: Dask, NumPy, USD,
    Warp, dqskin; in the program, its loaded input) out of reach of Python's cyclic garbage
    collector
    (:func:`gc.freeze`): they live until the process exits, and each full collection walked all
    of them again. Garbage made afterwards is collected as before.
    What is frozen is never freed, so garbage not yet collected stays too, without a full
    collection first (which would cost what this saves); and a cycle of
    frozen objects that becomes garbage later (nothing dqskin drops: its processes end with the
    bake).

    Called only in dqskin's own processes (the workers of the LocalCluster a bake starts, also
    for a ``bake(..., workers=N)`` from Python; the ``dqskin`` program once it has loaded its
    input), never in the caller's process of a library call."""
    import gc
    gc.freeze()


def dask_config() -> dict[str, object]:
    """The Dask settings a LocalCluster bake runs under (:data:`_CONFIG`), with the forkserver's
    preload made :data:`PRELOAD` (Dask sets its own list once per process, on first use; this
    call makes that happen first, then replaces it). Imports ``distributed``."""
    import multiprocessing

    import dask
    from distributed.utils import get_mp_context

    with dask.config.set(_CONFIG):
        get_mp_context()
    multiprocessing.get_context("forkserver").set_forkserver_preload(PRELOAD)
    return dict(_CONFIG)


def prestart_workers() -> None:
    """Start the forkserver now, in the background, so that its imports (:data:`PRELOAD`)
    overlap the caller's own work (a ``workers=N`` bake calls it while it bakes the clip that
    decides whether the workers pay). The bake stops it (:func:`stop_workers`);
    else it ends with this process. One already running is used as it is (one started before
    dqskin touched it is then left running, never stopped).

    Like each Dask nanny before it starts a worker, it gives the forkserver the variables of
    ``distributed.nanny.pre-spawn-environ`` (one BLAS/OpenMP thread) that are not set in this
    process's environment; this process's own environment is left as it was (its NumPy, often
    imported just after, keeps its BLAS threads)."""
    import multiprocessing
    import multiprocessing.forkserver

    import dask
    _distributed_defaults()
    with dask.config.set(_CONFIG):
        env = dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {}
    added = {k: str(v) for k, v in env.items() if v is not None and k not in os.environ}
    multiprocessing.get_context("forkserver").set_forkserver_preload(PRELOAD)
    os.environ.update(added)
    try:
        with owning_forkserver():
            multiprocessing.forkserver.ensure_running()
    finally:
        for k in added:
            os.environ.pop(k, None)


_own_forkservers: set[int] = set()
"""Pids of the forkservers dqskin started (:func:`prestart_workers`, a LocalCluster bake): the
only ones :func:`stop_workers` stops. multiprocessing has one forkserver per process, shared with
whatever else in it uses the ``forkserver`` start method."""


def _forkserver_pid() -> int | None:
    fs = sys.modules.get("multiprocessing.forkserver")
    return getattr(getattr(fs, "_forkserver", None), "_forkserver_pid", None)


@contextlib.contextmanager
def owning_forkserver() -> Iterator[None]:
    """Count a forkserver started inside the block as dqskin's (not one running before it)."""
    before = _forkserver_pid()
    try:
        yield
    finally:
        pid = _forkserver_pid()
        if pid is not None and pid != before:
            _own_forkservers.add(pid)


def stop_workers() -> None:
    """Stop the forkserver dqskin started (:func:`prestart_workers`, a LocalCluster bake), once
    its workers are gone, so that no process outlives the bake (and its CPU time, its workers'
    included, is reaped into this process's); one started by anything else is left running.
    It is killed first: it holds nothing to save, and its orderly exit (tearing down USD, Warp and
    Dask) is slow. ``_stop`` is multiprocessing's own (Python 3.10+),
    skipped when absent."""
    fs = sys.modules.get("multiprocessing.forkserver")
    server = getattr(fs, "_forkserver", None)
    stop = getattr(server, "_stop", None)
    pid = _forkserver_pid()
    if stop is None or pid not in _own_forkservers:
        return
    _own_forkservers.discard(pid)
    with contextlib.suppress(OSError):
        os.kill(pid, signal.SIGKILL)
    stop()  # closes its pipe and reaps it
