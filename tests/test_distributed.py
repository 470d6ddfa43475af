"""Clip bakes on Dask (dqskin.distributed): a 2-process LocalCluster (the embedded default), and
on one external ``dask scheduler`` + ``dask worker`` cluster on 127.0.0.1 shared by two tests:
the CLI's ``--scheduler``, and a worker process killed mid-clip.

Each result must equal the single-process single-layer cache bit for bit at every frame and at
sub-frames across clip boundaries (points, normals, velocities, extent); the oracle comparison of
that cache lives in tests/test_clips.py.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pxr import Usd

from dqskin import bake
from dqskin.options import SkinOptions
from dqskin.readers import load
from dqskin.writers.usd_clips import clips_folder

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_clips import HUMANOID, assert_same_animation, probe_times  # noqa: E402

CHUNK = 7
DASK = Path(sys.executable).with_name("dask")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reference")
    scene = load(HUMANOID)
    single = tmp / "single.usdc"
    bake(scene, single, clips=False)
    return dict(scene=scene, single=Usd.Stage.Open(str(single)),
                names=[m.name for m in scene.meshes], probes=probe_times(scene.times, CHUNK))


def check(reference, shot):
    folder = clips_folder(shot)
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")]  # no partial layer
    n = assert_same_animation(reference["single"], Usd.Stage.Open(str(shot)),
                              reference["names"], reference["probes"])
    assert n > 0


def test_two_worker_local_cluster_equals_the_single_process_cache(reference, tmp_path, capsys):
    """Through the CLI's ``--workers 2`` (the workers started whatever the shot's length:
    ``DQSKIN_WORKERS_PAY_SECONDS=0``, tests/conftest.py); no process of the cluster outlives the
    bake."""
    import multiprocessing.forkserver

    from dqskin.cli import main
    shot = tmp_path / "shot.usd"
    assert main(["skin", str(HUMANOID), "--out", str(shot), "--chunk", str(CHUNK),
                 "--workers", "2"]) == 0
    assert "as 7 clips" in capsys.readouterr().out
    check(reference, shot)
    assert getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None) is None


def test_short_shot_stays_in_this_process(reference, tmp_path, capsys, monkeypatch):
    """``--workers 2`` on the humanoid's short shot: its first clip, timed here, says the rest
    takes far less than starting workers costs, so no worker is started (no forkserver left, no
    Dask imported by the bake), one line says so, and the cache equals the single-process
    one."""
    import multiprocessing.forkserver

    from dqskin.cli import main
    from dqskin.distributed import WORKERS_PAY_SECONDS, workers_choice
    monkeypatch.delenv("DQSKIN_WORKERS_PAY_SECONDS")
    with monkeypatch.context() as m:
        m.setattr(os, "getloadavg", lambda: (1.0, 1.0, 1.0))  # this process alone
        m.setattr(os, "sched_getaffinity", lambda pid: {0, 1})  # on two cores
        assert workers_choice(2, 1e-3, 10_000)[0] and not workers_choice(2, 1e-3, 100)[0]
        assert not workers_choice(2, 1.0, 0)[0]  # nothing left
        assert not workers_choice(2, 1e-3, 10_000, cores_used=2.0)[0]  # it uses both cores
        m.setattr(os, "getloadavg", lambda: (5.0, 5.0, 5.0))  # busy with other work
        assert not workers_choice(2, 1e-3, 10_000)[0]
        m.setattr(os, "getloadavg", lambda: (1.0, 1.0, 1.0))
        m.setenv("DQSKIN_WORKERS_PAY_SECONDS", "1e-9")  # anything saved pays
        assert workers_choice(2, 1e-6, 1)[0]
    shot = tmp_path / "shot.usd"
    assert main(["skin", str(HUMANOID), "--out", str(shot), "--chunk", str(CHUNK),
                 "--workers", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 and "as 7 clips" in out[0]
    assert "; baked in this process, not on 2 worker processes (" in out[0]
    assert out[0].endswith(f"under the {WORKERS_PAY_SECONDS:g} s they cost to start)")
    check(reference, shot)
    assert getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None) is None


def test_the_measured_bake_hands_the_clips_after_the_second_to_the_workers(
        reference, tmp_path, monkeypatch):
    """``workers=2`` where they pay (every second saved pays): the first two clips are baked in
    this process's one stream, timed, and the rest go to the cluster (here a stand-in that runs
    each task with :func:`~dqskin.distributed.run_clip` in this process); the cache equals the
    single-process one and every clip is baked once."""
    import contextlib

    import dqskin.distributed as dist
    monkeypatch.setenv("DQSKIN_WORKERS_PAY_SECONDS", "1e-9")
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    monkeypatch.setattr(dist.forkserver, "prestart_workers", lambda: None)
    asked, on_workers = [], []
    real_run_here = dist.run_here

    def run_here(jobs, scene, done, until=None):
        def ask(k, wall, cpu):
            asked.append((k, wall > 0, cpu >= 0))
            return until(k, wall, cpu)
        return real_run_here(jobs, scene, done, ask if until else None)

    def run_on_dask(client, jobs, done):
        assert client == "cluster"
        for job in jobs:
            on_workers.append(job.index)
            done(dist.run_clip(job, reference["scene"]))

    monkeypatch.setattr(dist, "run_here", run_here)
    monkeypatch.setattr(dist, "_dask", lambda *a, **k: contextlib.nullcontext("cluster"))
    monkeypatch.setattr(dist, "_run_on_dask", run_on_dask)
    shot = tmp_path / "shot.usd"
    said = bake(reference["scene"], shot, chunk=CHUNK, workers=2)
    clips = len(list(clips_folder(shot).glob("*.usdc")))
    assert clips > 3 and "baked on 2 worker processes (" in said
    assert asked == [(1, True, True), (2, True, True)]
    assert on_workers == list(range(2, clips))
    check(reference, shot)


def test_a_measured_bake_the_workers_do_not_pay_for_is_the_clips_bake(reference, tmp_path,
                                                                      monkeypatch):
    """``workers=2`` where they cannot pay plans its clips as ``clips=True`` in one process
    does (not for the workers' task slots): the same clip layers, byte for byte."""
    import dqskin.distributed as dist
    from dqskin.writers import usd_clips
    monkeypatch.setenv("DQSKIN_WORKERS_PAY_SECONDS", "1e9")
    monkeypatch.setattr(dist.forkserver, "prestart_workers", lambda: None)
    # 10-frame clips in one process (5 for the 49 frames); for two slots, 9 frames (6 clips)
    monkeypatch.setattr(usd_clips, "CLIP_CHUNK", 10)
    monkeypatch.setattr(usd_clips, "CLIP_BYTES", 1)
    scene = reference["scene"]
    here, measured = tmp_path / "here.usd", tmp_path / "measured.usd"
    bake(scene, here, clips=True)
    said = bake(scene, measured, workers=2)
    assert "baked in this process, not on 2 worker processes (" in said
    layers = sorted(p.name for p in clips_folder(here).glob("*.usdc"))
    assert len(layers) == 5 and len(scene.times) == 49
    assert usd_clips.clip_frames(scene, 49, workers=2) == 9
    assert sorted(p.name for p in clips_folder(measured).glob("*.usdc")) == layers
    for name in layers:
        assert (clips_folder(here) / name).read_bytes() == \
            (clips_folder(measured) / name).read_bytes()


def _start(args, log):
    env = {k: v for k, v in os.environ.items()  # the workers' budget from --nthreads alone
           if k not in ("DQSKIN_THREADS", "PXR_WORK_THREAD_LIMIT")}
    return subprocess.Popen([str(DASK), *args], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True, env=env)


@pytest.fixture(scope="module")
def external_cluster(tmp_path_factory):
    """``dask scheduler`` and ``dask worker --nworkers 2 --nthreads 1`` started as subprocesses
    on 127.0.0.1 (the README's commands), shared by the tests below (starting a cluster is most
    of each test's time); yields the scheduler's address."""
    if not DASK.exists():
        pytest.skip(f"no dask command beside {sys.executable}")
    from distributed import Client
    tmp = tmp_path_factory.mktemp("dask")
    info = tmp / "scheduler.json"
    log = open(tmp / "dask.log", "w")
    procs = [_start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                     "--scheduler-file", str(info)], log)]
    try:
        end = time.monotonic() + 60
        while not info.exists() and time.monotonic() < end:
            time.sleep(0.1)
        assert info.exists(), (tmp / "dask.log").read_text()
        procs.append(_start(["worker", "--scheduler-file", str(info), "--nworkers", "2",
                             "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard"], log))
        address = json.loads(info.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        log.close()
        shutil.rmtree(tmp / "dask-worker-space", ignore_errors=True)


def test_external_scheduler_and_workers_on_localhost(reference, external_cluster, tmp_path):
    """The bake through the CLI's ``--scheduler``, one task a clip (named for it on the
    cluster's dashboard); each worker's thread budget follows its ``--nthreads 1`` (dqskin's
    launch pool and USD's thread pool)."""
    from distributed import Client, get_task_stream

    from dqskin.cli import main
    shot = tmp_path / "shot.usd"

    def budget():
        from pxr import Work

        from dqskin.kernels.grid import cpu_threads
        return cpu_threads(), Work.GetConcurrencyLimit()
    with Client(external_cluster, timeout="30s") as client:
        with get_task_stream(client) as stream:
            assert main(["skin", str(HUMANOID), "--out", str(shot), "--chunk", str(CHUNK),
                         "--scheduler", external_cluster]) == 0
        assert set(client.run(budget).values()) == {(1, 1)}
    check(reference, shot)
    clips = sorted(int(t["key"].split("-")[2]) for t in stream.data
                   if str(t["key"]).startswith("dqskin-clip-"))
    assert clips == list(range(7))  # the humanoid's 49 frames in clips of 7


def test_default_clips_are_sized_for_the_clusters_task_slots(external_cluster, tmp_path):
    """Without ``chunk``, a bake on a cluster of two one-thread workers cuts the clips for two
    slots (``clip_frames(..., workers=2)``: two clips of the humanoid's frames, where one
    process bakes one), and equals the same bake in one process."""
    from dqskin.writers.usd_clips import clip_frames
    scene = load(HUMANOID)
    F = len(scene.times)
    assert -(-F // clip_frames(scene, F)) == 1
    size = clip_frames(scene, F, workers=2)
    assert -(-F // size) == 2
    shot, here = tmp_path / "shot.usd", tmp_path / "here.usd"
    assert "as 2 clips" in bake(HUMANOID, shot, scheduler=external_cluster)
    assert "as 1 clip " in bake(HUMANOID, here, clips=True)
    plan = json.loads((clips_folder(shot) / "plan.json").read_text())
    assert plan["chunk"] == size
    names = [m.name for m in scene.meshes]
    assert assert_same_animation(Usd.Stage.Open(str(here)), Usd.Stage.Open(str(shot)), names,
                                 probe_times(scene.times, size)) > 0


def test_a_worker_killed_mid_clip_is_replaced_and_the_bake_completes(reference, external_cluster,
                                                                      tmp_path):
    """A worker plugin makes the first worker that has finished a clip layer in its temporary
    file SIGKILL itself before the rename; its nanny starts a new worker process and Dask reruns
    that clip. (The plugin is removed afterwards, its patch undone.)"""
    from distributed import Client, WorkerPlugin

    marker = tmp_path / "killed"

    class KillOnceMidClip(WorkerPlugin):
        name = "kill-once-mid-clip"

        def setup(self, worker):
            from dqskin.writers.usd_clips import ClipLayer
            finish = self.finish = ClipLayer.finish

            def finish_then_die(layer, times):
                claim = finish(layer, times)
                try:
                    os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                except FileExistsError:
                    return claim
                os.kill(os.getpid(), signal.SIGKILL)  # the layer is only in its temporary file
            ClipLayer.finish = finish_then_die

        def teardown(self, worker):
            from dqskin.writers.usd_clips import ClipLayer
            ClipLayer.finish = self.finish

    shot = tmp_path / "shot.usd"
    with Client(external_cluster, timeout="30s") as client:
        client.register_plugin(KillOnceMidClip())
        try:
            pids = set(client.run(os.getpid).values())
            summary = bake(HUMANOID, shot, chunk=CHUNK, scheduler=external_cluster)
            assert marker.exists(), "no worker was killed"
            assert set(client.run(os.getpid).values()) != pids  # the nanny started a new one
        finally:
            client.unregister_worker_plugin(KillOnceMidClip.name)
    assert "as 7 clips" in summary
    check(reference, shot)


def _forkserver_pid():
    import multiprocessing.forkserver
    return getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None)


@pytest.mark.parametrize("args", [["--workers", "0"], ["--workers", "2", "--no-clips"],
                                  ["--workers", "2", "--chunk", "0"],
                                  ["--workers", "99999999999999999999"]])
def test_refused_worker_arguments_start_no_forkserver(tmp_path, monkeypatch, capsys, args):
    """``--workers`` arguments the bake refuses fail before any worker process is prepared."""
    import dqskin.forkserver as forkserver
    from dqskin.cli import main
    started = []
    monkeypatch.setattr(forkserver, "prestart_workers", lambda: started.append(1))
    assert main(["skin", str(HUMANOID), "--out", str(tmp_path / "shot.usd"), *args]) != 0
    assert "dqskin:" in capsys.readouterr().err
    assert started == [] and _forkserver_pid() is None


def test_the_forkserver_starts_while_the_source_loads_and_a_failed_load_stops_it(
        tmp_path, monkeypatch, capsys):
    """``dqskin skin --workers 2`` starts the workers' forkserver before it loads the input
    (its imports overlap the load) where three cores are free, and not where the machine's
    load or size leaves two (its imports would slow the bake); an output it refuses (a clip
    bake to .npz) never starts it, and an input that fails to load stops it before
    the error is reported."""
    import dqskin.forkserver as forkserver
    import dqskin.readers as readers
    from dqskin.cli import main
    events = []
    monkeypatch.setattr(forkserver, "PRELOAD", ["numpy"])
    real, real_load = forkserver.prestart_workers, readers.load
    monkeypatch.setattr(forkserver, "prestart_workers", lambda: (events.append("forkserver"),
                                                                 real()))
    monkeypatch.setattr(readers, "load", lambda *a, **k: (events.append("load"),
                                                          real_load(*a, **k))[1])
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})  # four cores
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))  # free
    out = tmp_path / "shot.npz"
    assert main(["skin", str(HUMANOID), "--out", str(out), "--workers", "2"]) != 0
    assert "--out" in capsys.readouterr().err and not out.exists()
    assert events == [] and _forkserver_pid() is None
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\n(\n")
    assert main(["skin", str(bad), "--out", str(tmp_path / "shot.usd"), "--workers", "2"]) != 0
    assert "bad.usda" in capsys.readouterr().err
    assert events == ["forkserver", "load"] and _forkserver_pid() is None
    events.clear()
    monkeypatch.setattr(os, "getloadavg", lambda: (3.0, 3.0, 3.0))  # two cores busy elsewhere
    assert main(["skin", str(bad), "--out", str(tmp_path / "shot.usd"), "--workers", "2"]) != 0
    assert events == ["load"] and _forkserver_pid() is None
    events.clear()
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})  # two free cores: the
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))  # bake's own threads' share
    assert main(["skin", str(bad), "--out", str(tmp_path / "shot.usd"), "--workers", "2"]) != 0
    assert events == ["load"] and _forkserver_pid() is None


def test_a_failed_load_in_dqskin_bake_stops_the_forkserver_it_started(tmp_path, monkeypatch):
    """From Python (no CLI clean-up behind it): ``dqskin.bake(path, workers=2)`` starts the
    workers' forkserver while it loads, and a source that fails to load stops it."""
    import dqskin
    import dqskin.forkserver as forkserver
    started = []
    monkeypatch.setattr(forkserver, "PRELOAD", ["numpy"])
    real = forkserver.prestart_workers
    monkeypatch.setattr(forkserver, "prestart_workers", lambda: (started.append(1), real()))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})  # four cores
    monkeypatch.setattr(os, "getloadavg", lambda: (0.0, 0.0, 0.0))  # free
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\n(\n")
    with pytest.raises(dqskin.InputError, match="bad.usda"):
        dqskin.bake(bad, tmp_path / "shot.usd", workers=2)
    assert started == [1] and _forkserver_pid() is None


def test_a_forkserver_running_before_dqskin_is_left_running():
    """multiprocessing's one forkserver, started by someone else: prestart_workers uses it and
    the bake's clean-up (stop_workers) does not stop it."""
    import multiprocessing
    import multiprocessing.forkserver

    from dqskin.forkserver import prestart_workers, stop_workers
    assert _forkserver_pid() is None
    multiprocessing.get_context("forkserver").set_forkserver_preload([])
    multiprocessing.forkserver.ensure_running()
    pid = _forkserver_pid()
    try:
        prestart_workers()
        stop_workers()
        assert _forkserver_pid() == pid
        os.kill(pid, 0)  # alive
    finally:
        multiprocessing.forkserver._forkserver._stop()


_FREED = """
import sys
from dqskin.forkserver import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
def rss():
    with open("/proc/self/status") as fh:
        return next(int(ln.split()[1]) for ln in fh if ln.startswith("VmRSS:")) / 1024
drops = []
# pieces first (glibc maps a large block apart only when the heap has no room for it), then
# a clip layer's Vt arrays and blocks just under the threshold
for size, count in ((12_000_000, 8), (40_000, 2_500), (8_000_000, 12)):
    blocks = [bytearray(size) for _ in range(count)]  # 96 MB, 100 MB, 96 MB
    full = rss()
    del blocks
    drops.append(full - rss())
print(applied, *drops)
"""


def _glibc():
    try:
        return os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc")
    except (AttributeError, ValueError, OSError):
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux") or not _glibc(),
                    reason="glibc's malloc settings")
def test_bake_processes_keep_freed_memory_for_the_next_chunk():
    """A bake's LocalCluster worker keeps what a chunk freed, small arrays and large, for the
    next one instead of handing it back and faulting it in again, but not blocks of
    :data:`~dqskin.forkserver.HEAP_BELOW_BYTES` or more (pieces of skinned frames), which would
    fragment its heap; a process with glibc's defaults hands all back (the control: without it
    this test could not fail). glibc's own malloc variables are cleared for both."""
    env = {k: v for k, v in os.environ.items()
           if k != "GLIBC_TUNABLES" and not k.startswith("MALLOC_")}

    def freed_mb(mode):
        out = subprocess.run([sys.executable, "-c", _FREED, mode], capture_output=True,
                             text=True, check=True, env=env).stdout.split()
        return out[0], [float(x) for x in out[1:]]
    applied, kept = freed_mb("keep")
    _, plain = freed_mb("plain")
    assert applied == "True"
    assert min(plain) > 80 and kept[0] > 80 and max(kept[1:]) < 10, (plain, kept)


def test_a_task_reports_its_wall_and_process_cpu_seconds(tmp_path):
    """What a chunk task returns for the benchmark's per-task figures: its wall seconds and the
    CPU seconds of its process while it ran, each within what was measured around the call, and
    its start and end on the system clock (the benchmark's span from the first task's start to
    the last one's end)."""
    from dqskin import distributed
    from dqskin.writers.usd_clips import ClipBake
    scene = load(HUMANOID)
    opts = SkinOptions(method="lbs")
    plan = ClipBake(scene, tmp_path / "shot.usd", scene.times[:40], 40, opts)
    plan.pending()
    job = distributed.ClipJob(0, str(HUMANOID.resolve()), plan.chunk_times(0),
                               str(plan.clip_path(0)), plan.key, plan.targets, plan.cache.rigid,
                               opts, float(scene.time_codes_per_second))
    distributed.run_clip(job, scene)  # warm: kernels loaded
    w0, c0, t0 = time.perf_counter(), time.process_time(), time.time()
    result = distributed.run_clip(job, scene)
    wall, cpu, t1 = time.perf_counter() - w0, time.process_time() - c0, time.time()
    assert 0 < result["seconds"] <= wall and 0 < result["cpu_seconds"] <= cpu
    assert t0 <= result["started"] < result["ended"] <= t1
    assert result["pid"] == os.getpid() and Path(job.path).is_file()


def test_a_worker_reuses_its_buffers_from_task_to_task(tmp_path, monkeypatch):
    """A worker process's chunk tasks skin into one pool of buffers (``distributed._buffers``):
    the second task of a chunk's size allocates no new one, where a pool per task would
    allocate all again (every buffer pooled here)."""
    from dqskin import distributed
    from dqskin.kernels import buffers as KB
    from dqskin.writers.usd_clips import ClipBake
    scene = load(HUMANOID)
    opts = SkinOptions.baking(method="dqs")
    plan = ClipBake(scene, tmp_path / "shot.usd", scene.times[:40], 20, opts)
    plan.pending()
    jobs = [distributed.ClipJob(k, str(HUMANOID.resolve()), plan.chunk_times(k),
                                 str(plan.clip_path(k)), plan.key, plan.targets,
                                 plan.cache.rigid, opts,
                                 float(scene.time_codes_per_second)) for k in range(2)]
    made, new = [], KB._new
    monkeypatch.setattr(KB, "MIN_BYTES", 1)
    monkeypatch.setattr(KB, "_new", lambda *a: made.append(a) or new(*a))
    monkeypatch.setattr(distributed, "_buffers", KB.BufferPool())
    distributed.run_clip(jobs[0], scene)
    assert made
    made.clear()
    distributed.run_clip(jobs[1], scene)
    assert made == []
    assert all(Path(j.path).is_file() for j in jobs)
