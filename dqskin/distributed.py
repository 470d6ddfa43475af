"""Clip bakes clip by clip, in this process or as tasks on Dask (:mod:`dqskin.writers.usd_clips`).

Every clip (the frames of one clip layer) is one independent task, :func:`run_clip`: it skins
its frames chunk by chunk with :meth:`dqskin.Scene.skin_chunks` and writes its own clip layer
(:func:`~.writers.usd_clips.write_clip`: complete, checksummed, then renamed into place). A task
carries only the source's path, its times, where each value goes
(:class:`~.writers.usd_cache.Target`) and the :class:`~dqskin.options.SkinOptions`; each worker
process loads the asset once and keeps it for its later clips, and returns a few numbers, so
point data never travels through the scheduler. Workers need the source and the output folder at
the same paths (one machine, or a shared file system).

* ``workers=None`` and no ``scheduler``: the clips run here, one after another, pipelined
  across clips (:func:`run_here`).
* ``workers=N``: a :class:`distributed.LocalCluster` of ``N`` worker processes (one task at a
  time each; USD's and dqskin's CPU threads limited to cores / ``N`` per process, or to
  ``threads``) on 127.0.0.1, started and closed by the bake, forked from a forkserver that has
  imported dqskin once (:mod:`dqskin.forkserver`), when they pay: the first two clips are baked
  here, the second one timed, and the cluster starts only if it would save at least
  :func:`workers_pay_seconds` (what starting workers, loading the asset in each and their
  first tasks cost) on the rest; else the rest is baked here too (:func:`workers_choice` says
  which, in one line). The workers' forkserver starts importing during the second clip when
  the first one's cost says they may pay.
* ``scheduler="tcp://HOST:PORT"``: an existing cluster (``dask scheduler`` and ``dask worker``).
  Each worker process's thread budget is its ``--nthreads`` (:func:`worker_threads`), unless
  ``DQSKIN_THREADS`` / ``PXR_WORK_THREAD_LIMIT`` are set in its environment.

A worker process that dies mid-clip leaves no layer under the clip's name; Dask runs the task
again on another worker (up to its ``allowed-failures``, 3 by default).
"""

import contextlib
import os
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import forkserver
from .errors import DqskinError, InputError, Param
from .files import atomic
from .files.direct import pays as direct_pays
from .kernels import buffers as KB
from .options import SkinOptions
from .progress import progress_bar
from .scene import Scene
from .validation import check_skinned
from .writers import clip_lock, usd_clips
from .writers.usd_cache import SampleWriter, chunk_frames, frame_bytes

if TYPE_CHECKING:
    from distributed import WorkerPlugin

    from .baking import BakeSettings

__all__ = ["WORKERS_PAY_SECONDS", "ClipJob", "bake_clips", "free_cores", "run_clip", "run_here",
           "worker_threads", "workers_choice", "workers_pay_seconds"]

WORKERS_PAY_SECONDS = 2.0
"""Seconds a ``workers=N`` bake must save for its LocalCluster to start: about what starting
it, each worker's load of the asset and first task cost on a small, busy machine (measured on
2 cores: a second quiet, two under load)."""


def workers_pay_seconds() -> float:
    """:data:`WORKERS_PAY_SECONDS`, or the seconds in the environment variable
    ``DQSKIN_WORKERS_PAY_SECONDS`` (0: always start the workers)."""
    given = os.environ.get("DQSKIN_WORKERS_PAY_SECONDS", "").strip()
    try:
        value = float(given)
    except ValueError:
        return WORKERS_PAY_SECONDS
    return value if value >= 0 and value == value else WORKERS_PAY_SECONDS


def free_cores(cores_used: float = 1.0) -> tuple[float, float]:
    """``(used, free)``: the cores a bake here uses (``cores_used``, at least one, at most this
    process's cores) and those not busy with other work (this process's cores less the system's
    load average beyond ``used``; at least ``used``)."""
    cores = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                else os.cpu_count() or 1)
    used = min(max(1.0, cores_used), cores)
    try:
        others = max(0.0, os.getloadavg()[0] - used)
    except OSError:  # (no load average on this system)
        others = 0.0
    return used, max(used, cores - others)


def workers_choice(workers: int, seconds_per_frame: float, frames_left: int,
                   cores_used: float = 1.0) -> tuple[bool, str]:
    """Whether ``workers`` worker processes pay for the ``frames_left`` frames of a bake whose
    clips take ``seconds_per_frame`` a frame here using ``cores_used`` cores (its CPU seconds
    over its wall seconds), and a line saying what was chosen: they pay when they would save at
    least :func:`workers_pay_seconds`, the work taking ``cores_used / min(workers, free)`` of
    its time here on them, ``free`` the cores not busy with other work (this process's cores
    less the system's load average beyond what this process uses)."""
    left = seconds_per_frame * frames_left
    limit = workers_pay_seconds()
    used, free = free_cores(cores_used)
    saved = max(0.0, left * (1 - used / min(workers, free)))
    pays = frames_left > 0 and saved >= limit
    n = f"{workers} worker process{'es' if workers != 1 else ''}"
    estimate = (f"{frames_left} frames left at {1e3 * seconds_per_frame:.2g} ms a frame on "
                f"{used:.1f} of {free:.1f} free cores: {left:.1f} s here, about {saved:.1f} s "
                "less on the workers")
    return pays, (f"baked on {n} ({estimate}, at least the {limit:g} s they cost to start)"
                  if pays else f"baked in this process, not on {n} ({estimate}, under the "
                  f"{limit:g} s they cost to start)")


# this worker process's loaded asset: {(path, mtime, size): (Scene, states of the files it read)}
_scenes: dict[tuple[str, int, int], tuple[Scene, list]] = {}
_buffers = KB.BufferPool()  # this process's chunks of frames, reused from task to task (run_clip)


@dataclass(frozen=True)
class ClipJob:
    """One clip of a clip bake: everything a worker needs besides the asset file.

    Attributes
    ----------
    index : int
    source : str
        Absolute path of the asset (read by the worker).
    times : (F_k,) float64
        The clip layer's time codes (its own frames and the next clip's first).
    path : str
        Absolute path of the clip layer.
    key : str
        The plan key recorded with the layer.
    targets : dict (prim, what) → Target
    rigid : list of RigidPrim
    options : dqskin.SkinOptions
        What the meshes and rigid prims are skinned with.
    time_codes_per_second : float
    """

    index: int
    source: str
    times: np.ndarray
    path: str
    key: str
    targets: dict
    rigid: list
    options: SkinOptions
    time_codes_per_second: float


def worker_threads(nthreads: int, environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """The thread budget of a worker process with Dask ``nthreads`` task threads:
    ``{"DQSKIN_THREADS": .., "PXR_WORK_THREAD_LIMIT": ..}`` (dqskin's CPU launch pool, USD's
    thread pool), each the variable's value when set in ``environ`` (a LocalCluster of
    :func:`bake_clips` sets both), else ``nthreads``: ``dask worker --nthreads 1`` per core gives
    one-thread workers, ``--nthreads 4`` a pool of 4 shared by its 4 concurrent clips."""
    budget = str(max(1, int(nthreads)))
    return {k: environ.get(k) or budget for k in ("DQSKIN_THREADS", "PXR_WORK_THREAD_LIMIT")}


def _worker_plugin(own_cluster: bool) -> "WorkerPlugin":
    """A Dask worker plugin, for every worker process (restarted ones too): Warp's banner and
    module-load messages off (the worker's stdout is the caller's), and the process's thread
    budget (:func:`worker_threads`) applied to dqskin's launch pool and USD's thread pool (a
    worker forked from a forkserver that imported USD before its environment was set would
    otherwise use every core); on the workers of a LocalCluster the bake started
    (``own_cluster``), :func:`~.forkserver.keep_freed_memory` and
    :func:`~.forkserver.freeze_heap` (not on a caller's cluster). (Made
    here so that importing this module does not import Dask; a local class travels by value.)"""
    from distributed import WorkerPlugin

    class DqskinWorker(WorkerPlugin):
        name = "dqskin-worker"

        def setup(self, worker):
            import warp as wp
            from pxr import Work
            wp.config.log_level = wp.LOG_ERROR
            state = getattr(worker, "state", worker)
            budget = worker_threads(getattr(state, "nthreads", 1))
            os.environ.update(budget)  # read by dqskin.kernels.grid.cpu_threads at each launch
            Work.SetConcurrencyLimitArgument(int(budget["PXR_WORK_THREAD_LIMIT"]))
            if own_cluster:  # our own processes: a clip reuses what the one before freed
                forkserver.keep_freed_memory()
                forkserver.freeze_heap()

    return DqskinWorker()


def _worker_scene(path):
    """The asset at ``path``, loaded once per worker process (reloaded if the file, or any layer
    it reads, changed: a sublayer edited between two bakes on a long-lived cluster)."""
    st = os.stat(path)
    key = (path, st.st_mtime_ns, st.st_size)
    if key not in _scenes or usd_clips.file_states(f for f, *_ in _scenes[key][1]) != \
            _scenes[key][1]:
        from pxr import Usd

        from .readers import load
        global _buffers
        _scenes.clear()
        _buffers = KB.BufferPool()  # another asset's chunks: their own sizes
        stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)  # (its layers stay open for the load)
        read = usd_clips.input_files(stage, path) if stage is not None else [path]
        _scenes[key] = (load(path), usd_clips.file_states(read))
        del stage
    return _scenes[key][0]


def _preload(path):
    _worker_scene(path)


def _peak_rss_mb():
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def _sample_writer(scene, job):
    """The :class:`SampleWriter` of ``job``'s clip layers (the plan's targets, its options)."""
    def target(name, what):
        try:
            return job.targets[name, what]
        except KeyError:
            raise InputError(f"{job.source}: {name}: no {what} in this bake's plan") from None

    return SampleWriter(scene, target, job.rigid, job.options)


def _result(job, digest, t0, c0):
    seconds, ended = time.perf_counter() - t0, time.time()
    return dict(index=job.index, checksum=digest, seconds=seconds,
                cpu_seconds=time.process_time() - c0, pid=os.getpid(),
                peak_rss_mb=_peak_rss_mb(), started=ended - seconds, ended=ended)


def run_clip(job: ClipJob, scene: Scene | None = None) -> dict[str, Any]:
    """Skin one clip and write its layer; ``scene`` defaults to the worker's copy of
    ``job.source``. Returns ``index``, ``checksum`` (:data:`~.writers.usd_clips.CHECKSUM`),
    ``seconds``, ``cpu_seconds`` (of the whole process while the task ran: all its threads, a
    worker running one task at a time), ``pid``, ``peak_rss_mb``, and ``started`` and ``ended``
    (``time.time()`` seconds)."""
    t0, c0 = time.perf_counter(), time.process_time()
    scene = _worker_scene(job.source) if scene is None else scene
    with usd_clips.ClipLayer(job.path, job.time_codes_per_second) as layer:
        _sample_writer(scene, job).write_chunks(
            layer.samples,
            (res for _, res in scene.skin_chunks(job.times, chunk_frames(scene, job.options),
                                                 buffers=_buffers, options=job.options)),
            lambda res: check_skinned(scene.path, res), checked=True)
        digest = usd_clips.write_clip(layer, job.key, job.times)
    return _result(job, digest, t0, c0)


def run_here(jobs: "list[ClipJob]", scene: Scene, done: Callable[[dict[str, Any]], object],
             until: Callable[[int, float, float], bool] | None = None) -> int:
    """Every job, in order, in this process (``done(result)`` after each; results as
    :func:`run_clip`'s), pipelined across chunks instead of :func:`run_clip` one by one: one
    :meth:`dqskin.Scene.skin_chunks` stream of chunks
    (:data:`~.writers.usd_cache.CHUNK_BYTES`) over all their frames keeps skinning (the first
    chunk of clip ``k + 1`` while clip ``k``'s layer is finished), and clip ``k``'s layer
    (hashed as it was written) is recorded and renamed
    (:func:`~.writers.usd_clips.commit_clip`) once clip ``k + 1``'s is filled. Memory is as
    :func:`run_clip`'s: a few chunks (the one being skinned, two being checked, one being
    written), no layer (each goes to its file as it fills).

    On an error or interrupt while clip ``k + 1`` is filled, clip ``k`` is still recorded and
    renamed (as the one-by-one bake would have had it), then the error raised; nothing else is
    left under a final name.

    ``until(k, wall, cpu)``, when given, is asked before clip ``k >= 1`` starts, with the wall
    and CPU seconds (this process's) that filling clip ``k - 1`` took: True stops there (the
    clips before ``k`` are still recorded). Returns the number of clips baked."""
    if not jobs:
        return 0
    opts = jobs[0].options
    size = chunk_frames(scene, opts)
    chunks = [[min(size, len(j.times) - a) for a in range(0, len(j.times), size)] for j in jobs]
    # through the page cache when all the layers fit in what the system buffers without
    # slowing their writer, as a single-layer cache
    direct = direct_pays(frame_bytes(scene, opts.normals, opts.velocities)
                         * sum(len(j.times) for j in jobs))
    writer = _sample_writer(scene, jobs[0])
    stream = scene.skin_chunks(np.concatenate([j.times for j in jobs]),
                               [n for c in chunks for n in c], options=jobs[0].options)
    # (job, claim, checksum, start) of the finished, unrecorded layer
    pending: tuple[ClipJob, atomic.atomic_path, str | None, tuple[float, float]] | None = None
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="dqskin-usd-values") as values:
        baked = 0
        try:
            start = time.perf_counter(), time.process_time()
            for job, c in zip(jobs, chunks):
                if baked and until is not None and pending is not None:
                    began = pending[3]  # clip k - 1's, filled since
                    if until(baked, time.perf_counter() - began[0],
                             time.process_time() - began[1]):
                        break
                with usd_clips.ClipLayer(job.path, job.time_codes_per_second,
                                         direct=direct) as layer:
                    writer.write_chunks(layer.samples, (next(stream)[1] for _ in c),
                                        lambda r: check_skinned(scene.path, r), checked=True,
                                        executor=values)
                    if pending is not None:
                        finished, pending = pending, None
                        done(_commit(*finished))
                    claim = layer.finish(job.times)
                pending = (job, claim, layer.digest, start)
                start = time.perf_counter(), time.process_time()
                baked += 1
            if pending is not None:
                finished, pending = pending, None
                done(_commit(*finished))
            return baked
        except BaseException:
            if pending is not None:
                finished, pending = pending, None
                _commit_on_error(*finished)
            raise
        finally:
            stream.close()


def _commit(job, claim, digest, start):
    """Record and rename the finished layer in ``claim`` (checksum ``digest``)."""
    return _result(job, usd_clips.commit_clip(claim, job.key, job.times, digest), *start)


def _commit_on_error(job, claim, digest, start):
    """:func:`_commit`, while :func:`run_here` is failing: an error of its own is dropped (the
    failure being raised matters; commit_clip removed the layer). An interrupt the CLI recorded
    (:func:`~.files.atomic.interrupt`; nothing commits after one) is set aside for this one
    complete, hashed file and raised again at the end."""
    try:
        atomic.check_interrupted()
    except BaseException as exc:
        recorded: BaseException | None = exc
    else:
        recorded = None
    with atomic.critical():  # a recorded interrupt is raised at the end of this block
        atomic.reset_interrupt()
        try:
            _commit(job, claim, digest, start)
        except Exception:
            pass  # commit_clip removed the layer
        finally:
            if recorded is not None:
                atomic.interrupt(recorded)


def bake_clips(scene: Scene, out: str | Path, times: np.ndarray, options: SkinOptions,
               settings: "BakeSettings", *, threads: int | None = None) -> dict[str, Any]:
    """Bake ``scene`` at ``times`` to the value-clip cache ``out``
    (:class:`~.writers.usd_clips.ClipBake`) with ``options`` (for the meshes and the rigidly
    bound prims; :meth:`SkinOptions.plan` goes into the plan key) and ``settings``
    (:class:`dqskin.baking.BakeSettings`: ``chunk`` is the frames of each clip, ``workers``,
    ``scheduler``, ``resume``, ``force``, ``progress``, ``inputs``: other files the bake reads,
    refused inside the clip folder). ``threads``: CPU threads of each LocalCluster worker
    process (default cores / ``workers``); the workers of an external ``scheduler`` follow their
    own ``--nthreads`` (:func:`worker_threads`).

    Returns
    -------
    dict
        ``clips`` (in total), ``baked`` (this run), ``kept`` (verified from an earlier run),
        ``folder``, ``tasks``: what each task returned (pid, seconds, peak RSS), and ``chose``:
        with ``workers`` (unless ``DQSKIN_WORKERS_PAY_SECONDS`` is 0), the line
        :func:`workers_choice` wrote (whether the workers were started), else None.

    Raises
    ------
    KeyboardInterrupt
        Interrupted: when finished clips are kept for ``resume``, the exception's ``resumable``
        attribute is ``(kept, clips, folder)``.
    """
    with clip_lock.bake_lock(out):  # one bake of ``out`` at a time, --resume and --force too
        # before starting workers
        usd_clips.ClipBake.check_free(out, force=settings.force, resume=settings.resume)
        return _bake_clips(scene, out, times, options, settings, threads)


def _bake_clips(scene, out, times, options, settings, threads):
    """:func:`bake_clips` once ``out`` is locked and free."""
    s = settings
    source = str(Path(scene.path).resolve())
    tasks = []
    bake = None
    if s.workers is not None and not s.scheduler and workers_pay_seconds() > 0:
        return _bake_clips_measured(scene, out, times, options, settings, threads, source)
    try:
        with _dask(s.workers, s.scheduler, threads) as client:
            # the workers load the asset while this process flattens it (kept until the end: a
            # released future is cancelled)
            # each worker's task slots (scheduler_info() lists at most 5 workers in some versions)
            slots = {} if client is None else client.nthreads()
            preload = [client.submit(_preload, source, pure=False, workers=[w],
                                     allow_other_workers=False) for w in slots]
            bake, jobs = _plan(scene, out, times, options, s, source,
                               None if client is None else max(1, sum(slots.values())))
            bar = _bar(len(bake.bounds), len(bake.bounds) - len(jobs), s.progress)

            def done(result):
                tasks.append(result)
                bar.update(1)
            try:
                if client is None:
                    run_here(jobs, scene, done)
                elif jobs:
                    _run_on_dask(client, jobs, done)
            finally:
                bar.close()
                del preload
        bake.finish()
    except BaseException as exc:
        if bake is not None:  # (only when no clip was kept: nothing for --resume to complete)
            bake.abandon()
            kept = bake.kept()
            if isinstance(exc, KeyboardInterrupt) and kept:
                exc.resumable = (kept, len(bake.bounds), str(bake.folder))  # type: ignore[attr-defined]
        raise
    return dict(clips=len(bake.bounds), baked=len(jobs), kept=len(bake.bounds) - len(jobs),
                folder=str(bake.folder), tasks=tasks, chose=None)


def _plan(scene, out, times, options, settings, source, slots):
    """The :class:`~.writers.usd_clips.ClipBake` of ``out`` and a :class:`ClipJob` per clip
    left to bake: clips of ``settings.chunk`` frames, else the earlier bake's when resuming,
    else by size and ``slots`` task slots (None: this process alone)."""
    s = settings
    chunk = s.chunk
    if chunk is None:
        chunk = (s.resume and not s.force and usd_clips.recorded_chunk(out)) or \
            usd_clips.clip_frames(scene, len(np.unique(times)), options.normals,
                                  options.velocities, slots)
    bake = usd_clips.ClipBake(scene, out, times, chunk, options, force=s.force, resume=s.resume,
                              inputs=s.inputs)
    jobs = [ClipJob(k, source, bake.chunk_times(k), str(bake.clip_path(k).resolve()), bake.key,
                    bake.targets, bake.cache.rigid, options, float(scene.time_codes_per_second))
            for k in bake.pending()]
    return bake, jobs


def _bake_clips_measured(scene, out, times, options, settings, threads, source):
    """:func:`_bake_clips` with ``workers=N`` (a LocalCluster of its own): the clips are baked
    here (one :func:`run_here` stream) and the second one timed (wall and CPU); the
    LocalCluster starts for the rest only when it would save at least
    :func:`workers_pay_seconds` (:func:`workers_choice`), else they are baked here too. Clips
    are planned as ``--clips`` plans them in one process. The result's ``chose`` says which
    (None when nothing was left to bake)."""
    s = settings
    tasks: list[dict[str, Any]] = []
    bake = None
    try:
        # clips as a bake in this process plans them, so that one the workers do not pay for is
        # that bake (where they pay, the shot holds many clips for them to take in turn)
        bake, jobs = _plan(scene, out, times, options, s, source, None)
        bar = _bar(len(bake.bounds), len(bake.bounds) - len(jobs), s.progress)

        def done(result):
            tasks.append(result)
            bar.update(1)
        try:
            chose = None
            workers = int(s.workers)
            left = sum(len(j.times) for j in jobs[2:])

            def until(k: int, wall: float, cpu: float) -> bool:
                """After the first clip (a warm-up: kernels loaded, threads started, pages
                first touched): if even its cost says the workers may pay, their forkserver
                starts importing while the second is baked (unless it started while the source
                loaded), else it stops. After the second, whose cost is the rest's: whether
                the rest goes to the workers."""
                nonlocal chose
                frames = len(jobs[k - 1].times)
                if k == 1:
                    if len(jobs) > 2 and workers_choice(workers, wall / max(1, frames), left,
                                                        1.0)[0]:
                        try:
                            forkserver.prestart_workers()
                        except Exception:  # only a head start: the cluster says why it cannot
                            pass
                    else:  # its imports would only slow this bake
                        forkserver.stop_workers()
                    return False
                if k == 2:
                    pays, chose = workers_choice(workers, wall / max(1, frames), left,
                                                 cpu / max(wall, 1e-9))
                    if not pays:
                        forkserver.stop_workers()  # (if started: not needed)
                    return pays
                return False

            if len(jobs) <= 2:  # nothing left for workers (if started while the source loaded)
                forkserver.stop_workers()
            baked = run_here(jobs, scene, done, until)
            if baked < len(jobs):
                with _dask(s.workers, None, threads) as client:
                    _run_on_dask(client, jobs[baked:], done)
            elif 0 < len(jobs) <= 2:
                chose = (f"baked in this process, not on {s.workers} worker process"
                         f"{'es' if s.workers != 1 else ''} ({len(jobs)} clip"
                         f"{'s' if len(jobs) != 1 else ''} to bake)")
        finally:
            bar.close()
        bake.finish()
    except BaseException as exc:
        if bake is not None:
            bake.abandon()
            kept = bake.kept()
            if isinstance(exc, KeyboardInterrupt) and kept:
                exc.resumable = (kept, len(bake.bounds), str(bake.folder))  # type: ignore[attr-defined]
        raise
    finally:
        forkserver.stop_workers()
    return dict(clips=len(bake.bounds), baked=len(jobs), kept=len(bake.bounds) - len(jobs),
                folder=str(bake.folder), tasks=tasks, chose=chose)


def _bar(total, done, progress):
    return progress_bar(enabled=progress and total >= 2, total=total, initial=done, unit="clip",
                        desc="baking clips")


@contextlib.contextmanager
def _dask(workers, scheduler, threads=None):
    """A Dask client of a new LocalCluster of ``workers`` processes of ``threads`` CPU threads
    each (default cores / ``workers``) or of the cluster at ``scheduler`` (None for neither),
    closed (the LocalCluster stopped) at the end."""
    if workers is None and not scheduler:
        yield None
        return
    import logging

    import dask
    from distributed import Client, LocalCluster

    cluster = client = None
    stack = contextlib.ExitStack()
    try:
        if scheduler:
            _probe(scheduler, CONNECT_SECONDS)
            try:
                client = Client(scheduler, timeout=f"{CONNECT_SECONDS}s")
            except (OSError, ValueError) as exc:
                raise DqskinError(Param("scheduler", scheduler),
                                  f": cannot connect ({exc})") from None
        else:
            if int(workers) < 1:
                raise InputError(Param("workers", workers), ": must be at least 1")
            threads = str(max(1, int(threads or (os.cpu_count() or 1) // int(workers))))
            # for the cluster's lifetime: a restarted worker is forked from the same server
            stack.enter_context(dask.config.set(forkserver.dask_config()))
            stack.enter_context(dask.config.set(_worker_ttl(dask.config)))
            with forkserver.owning_forkserver():  # its first worker starts it, unless running
                cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1,
                                       processes=True, host="127.0.0.1", dashboard_address=None,
                                       silence_logs=logging.ERROR,
                                       env=dict(PXR_WORK_THREAD_LIMIT=threads,
                                                DQSKIN_THREADS=threads))
            client = Client(cluster)
        client.register_plugin(_worker_plugin(own_cluster=not scheduler))
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
        if not scheduler:  # started by the cluster or by prestart_workers
            forkserver.stop_workers()
        stack.close()


CONNECT_SECONDS = 20
"""Seconds a ``scheduler`` has to accept the connection and greet (a Dask scheduler sends its
handshake at once; a port that accepts and says nothing is refused after this long)."""

WORKER_TTL = "60s"
"""How long a worker of a bake's own LocalCluster may go without a heartbeat (a process stopped
with SIGSTOP, or hung) before the scheduler drops it and its clips run on the others: Dask's
``distributed.scheduler.worker-ttl`` (default 5 minutes), unless that is configured otherwise.
The workers of an external ``scheduler`` follow that scheduler's own setting."""


def _worker_ttl(config: Any) -> dict[str, str]:
    """``{"distributed.scheduler.worker-ttl": WORKER_TTL}`` unless Dask's configuration (its
    files or ``DASK_DISTRIBUTED__SCHEDULER__WORKER_TTL``) sets another value than Dask's
    default."""
    key = "distributed.scheduler.worker-ttl"
    given = config.get(key, None)
    return {key: WORKER_TTL} if given in (None, "5 minutes", "300s") else {}


def _probe(address: str, seconds: float) -> None:
    """DqskinError unless something at the ``tcp://HOST:PORT`` ``address`` accepts a connection
    and sends its first bytes (a Dask scheduler's handshake) within ``seconds``: Dask's own
    connect waits for ever on a port that accepts and never answers."""
    import socket
    host, _, port = address[len("tcp://"):].rstrip("/").rpartition(":")
    host = host.strip("[]")
    end = time.monotonic() + seconds
    try:
        with socket.create_connection((host, int(port)), timeout=seconds) as sock:
            sock.settimeout(max(0.1, end - time.monotonic()))
            first = sock.recv(1)
    except TimeoutError:
        raise DqskinError(Param("scheduler", address), f": no answer within {seconds:g} s (not a "
                          "Dask scheduler, or one that does not respond)") from None
    except OSError as exc:
        raise DqskinError(Param("scheduler", address),
                          f": cannot connect ({exc.strerror or exc})") from None
    if not first:
        raise DqskinError(Param("scheduler", address), ": closed the connection without a "
                          "greeting (not a Dask scheduler?)")


def _run_on_dask(client, jobs, done):
    """Run the jobs as tasks; ``done(result)`` for each as it finishes."""
    from distributed import as_completed
    from distributed.scheduler import KilledWorker

    futures = {client.submit(run_clip, job, key=f"dqskin-clip-{job.index}-{job.key[:12]}",
                             pure=False): job for job in jobs}
    for fut in as_completed(futures):
        try:
            result = fut.result()
        except KilledWorker:
            job = futures[fut]
            raise DqskinError(
                f"{job.path}: the worker processes baking it died repeatedly (out of memory? "
                "try a smaller ", Param("chunk"), "); finished clips are kept: rerun with ",
                Param("resume", True)) from None
        done(result)
