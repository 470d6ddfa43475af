"""End-to-end bake benchmark, side by side in one run: UsdSkel, dqskin single layer, dqskin value
clips in this process and on a Dask LocalCluster of 1 and 2 worker processes.

    python tools/bench_bake.py [--frames 1000,10000] [--asset PATH] [--brainstem PATH]
                               [--impls usdskel,single,clips0,clips1,clips2,clips1t1,...]
                               [--repeat N]
    python tools/bench_bake.py --breakdown 10000

Assets: the looped CesiumMan (its 48-key walk looped over each ``--frames`` count, with root
motion) and BrainStem.usdz's own clip when the file exists (``--brainstem``; default: searched
under ../shared/assets), else a stand-in of its shape (59 meshes of varied sizes cut from
CesiumMan under one skeleton, 1,309 poses of their own: :func:`make_many_meshes`;
``--no-standin`` to skip). Each bake runs in a fresh process so its peak memory (VmHWM) is its
own; the clip bakes also report the peak of every worker process. Implementations (``--impls``):

* ``usdskel``: ``UsdSkel.BakeSkinning(stage)`` + ``Export`` to ``.usdc`` (LBS, points + extent);
* ``single``: ``dqskin.bake(..., clips=False)``, LBS, points + extent (what UsdSkel writes);
* ``clips0``/``clips1``/``clips2``: the same as value clips, in this process / on a LocalCluster
  of 1 / 2 worker processes of cores / workers threads each (cluster start-up and stop included
  in the time);
* ``clips0t1``/``clips1t1``/``clips2t1``: in this process / 1 / 2 worker processes with a
  thread budget of one each (dqskin's launch pool and USD's; what ``dask worker --nthreads 1``
  per core gives on a farm): process scaling without the threads a lone worker also uses;
* ``single+nv``, ``clips2+nv``: with skinned normals and velocities (dqskin's default);
  ``single+n``: with skinned normals (what UsdSkel writes for a mesh with ``normals``);
* ``cli``, ``cli+n``, ``cli+nv``: the whole ``dqskin skin SRC --out DST --method lbs`` process
  (its imports and start-up included; points only, with normals, with normals and
  velocities); ``cliclips+n``: the same with ``--clips`` (value clips in one process),
  ``cliw2+n``: with ``--workers 2`` (the bake decides whether the workers pay).

``--repeat N`` runs N rounds of every impl, interleaved, and reports each impl's median run
(with the range) and the median of the per-round ratios: on a VM a run's speed swings by up to
2× from one minute to the next, and runs of one round see the same machine.

Reports wall seconds of the bake (module imports excluded, shown apart), point-frames/s, the CPU
seconds of the whole process tree (imports and worker start-up included: on a machine shared
with other work, wall time is noise and CPU time is not), peak RSS of the main process and of each
worker, and the largest point difference to UsdSkel's cache.
Also callable from ``tools/bench.py`` (``bench_bake(rows)``).
"""

import argparse
import contextlib
import gc
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "assets"
DEFAULT_ASSET = SHARED / "usd-wg" / "CesiumMan" / "CesiumMan.usdz"
IMPLS = ("usdskel", "single", "clips0", "clips1", "clips2", "clips0t1", "clips1t1", "clips2t1",
         "single+n", "single+nv", "clips2+nv", "cli", "cli+n", "cli+nv", "cliclips+n",
         "cliw2+n")


def cli_command(which, src, dst):
    """The ``dqskin skin`` command line of a ``cli*`` impl (``@before``: see ``--before``)."""
    kind, _, extra = which.removesuffix("@before").partition("+")
    start = ["-m", "dqskin.cli"]
    if which.endswith("@before"):  # that tree, not the editable install's
        start = ["-c", "import sys; sys.meta_path[:] = [f for f in sys.meta_path if not "
                 "type(f).__module__.startswith('__editable__')]; sys.path.insert(0, "
                 f"{os.environ['BENCH_BEFORE']!r}); sys.argv[0] = 'dqskin'; "
                 "from dqskin.cli import main; sys.exit(main())"]
    cmd = [sys.executable, *start, "skin", str(src), "--out", str(dst), "--method", "lbs"]
    cmd += {"": ["--no-normals", "--no-velocities"], "n": ["--no-velocities"], "nv": []}[extra]
    cmd += {"cli": [], "cliclips": ["--clips"], "cliw2": ["--workers", "2"]}[kind]
    return cmd


def is_whole(which):
    """Whether impl ``which`` is a whole ``dqskin skin`` process (``cli``, ``cliclips``,
    ``cliw2``, with ``+n``/``+nv`` and ``@before``), not a bake timed inside this script's child
    (``clips0`` starts with "cli" too)."""
    return which.removesuffix("@before").partition("+")[0] in ("cli", "cliclips", "cliw2")


def find_brainstem():
    hits = sorted(SHARED.rglob("BrainStem*.usd*")) if SHARED.is_dir() else []
    return hits[0] if hits else None


def _resampled(asset, frames, value_at):
    """``asset`` flattened, each SkelAnimation's animated attribute ``attr`` (its sample times
    ``keys``) resampled as ``value_at(attr, keys, f)`` at time codes ``keys[0] + f``, ``f`` in
    ``range(frames)``; the stage's range 1 to ``frames``."""
    from pxr import Usd, UsdSkel
    stage = Usd.Stage.Open(Usd.Stage.Open(str(asset)).Flatten())
    for prim in stage.Traverse():
        if not prim.IsA(UsdSkel.Animation):
            continue
        anim = UsdSkel.Animation(prim)
        for attr in (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr()):
            keys = attr.GetTimeSamples()
            if len(keys) < 2:
                continue
            values = [value_at(attr, keys, f) for f in range(frames)]
            attr.Clear()
            for f, value in enumerate(values):
                attr.Set(value, keys[0] + f)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(frames)
    return stage


def make_long_clip(asset, frames, out, stride=0.5):
    """Flatten ``asset`` and loop every SkelAnimation's samples over ``frames`` time codes; the
    root joint moves ``stride`` along x per loop (root motion), so no two frames are equal (a
    crate layer stores each distinct array once: a plain loop would flatter every writer)."""
    from pxr import Gf

    def looped(attr, keys, f):
        values = looped.cache.setdefault(attr.GetPath(), [attr.Get(k) for k in keys])
        value = values[f % len(values)]
        if attr.GetName() == "translations" and stride:
            value = type(value)(value)
            value[0] = value[0] + Gf.Vec3f(stride * (f // len(values)), 0, 0)
        return value
    looped.cache = {}
    long_stage = _resampled(asset, frames, looped)
    long_stage.GetRootLayer().Export(str(out))


def make_many_meshes(asset, frames, out, meshes=59, points=34_000, step=0.37, seed=0):
    """A BrainStem-shaped stand-in (one skeleton, ``meshes`` meshes of varied sizes, about
    ``points`` points in all, ``frames`` samples of its own) cut from ``asset``'s one skinned
    mesh (CesiumMan). Frame ``f`` poses the skeleton as the asset's animation at
    ``step * f`` past its start (wrapped: a slow walk, every pose its own, with no repeating
    cycle, so that no two frames' normals are equal: a crate file stores each distinct array
    once). Mesh ``i`` is a run of the asset's triangles (sizes spread geometrically, 1:40, in a
    shuffled order) with its points, normals (the ``normals`` attribute: UsdSkel's bake skins
    it, not ``primvars:normals``), UVs and joint influences, its rest points moved ``i``
    millimetres along the up axis so that no two meshes hold the same arrays."""
    from pxr import UsdGeom, UsdSkel, Vt
    stage = _resampled(asset, frames, lambda attr, keys, f: attr.Get(
        keys[0] + (step * f) % (keys[-1] - keys[0])))
    src = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    mesh, parent = UsdGeom.Mesh(src), src.GetParent().GetPath()
    rest = np.asarray(mesh.GetPointsAttr().Get(), np.float32)
    tris = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    pv = {p.GetPrimvarName(): p for p in UsdGeom.PrimvarsAPI(src).GetPrimvars()}
    per_vertex = {n: (p, np.asarray(p.Get()), p.GetElementSize()) for n, p in pv.items()
                  if p.GetInterpolation() == "vertex"}
    rng = np.random.default_rng(seed)
    sizes = np.geomspace(1.0, 40.0, meshes)
    rng.shuffle(sizes)
    # triangles per mesh for about ``points`` points (a run of CesiumMan's triangles holds
    # about 1.75 points a triangle: its points are shared by fewer triangles than in the whole)
    sizes = np.maximum(8, sizes / sizes.sum() * points / 1.75).astype(int)
    skel_rel = UsdSkel.BindingAPI(src).GetSkeletonRel().GetTargets()
    binding = UsdSkel.BindingAPI(src)
    geom_bind = binding.GetGeomBindTransformAttr().Get()
    method = pv.get("skel:skinningMethod")
    start = 0
    for i, n in enumerate(sizes):
        faces = tris[np.arange(start, start + n) % len(tris)]
        start += n
        used, local = np.unique(faces, return_inverse=True)
        m = UsdGeom.Mesh.Define(stage, parent.AppendChild(f"Part_{i:02d}"))
        pts = rest[used] + np.float32(0.001 * i) * np.array([0, 0, 1], np.float32)
        m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        m.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
        m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(local.reshape(-1).astype(np.int32)))
        m.CreateSubdivisionSchemeAttr("none")
        b = UsdSkel.BindingAPI.Apply(m.GetPrim())
        b.CreateSkeletonRel().SetTargets(skel_rel)
        b.CreateGeomBindTransformAttr(geom_bind)
        api = UsdGeom.PrimvarsAPI(m.GetPrim())
        for name, (p, values, size) in per_vertex.items():
            sub = type(p.Get()).FromNumpy(np.ascontiguousarray(
                values.reshape(len(rest), -1)[used].reshape((-1,) + values.shape[1:])))
            if name == "normals":  # as the ``normals`` attribute, which UsdSkel also skins
                m.CreateNormalsAttr(sub)
                m.SetNormalsInterpolation("vertex")
            else:
                api.CreatePrimvar(name, p.GetTypeName(), "vertex", size).Set(sub)
        if method is not None:
            api.CreatePrimvar("skel:skinningMethod", method.GetTypeName(),
                              "constant").Set(method.Get())
    stage.RemovePrim(src.GetPath())
    stage.GetRootLayer().Export(str(out))


def compile_trees(*folders):
    """Write the bytecode of the measured dqskin trees' modules, as installing a wheel does
    (pip compiles them), so that no process measured compiles them from source: an editable
    install in an environment with ``PYTHONDONTWRITEBYTECODE`` (or a read-only tree) would pay
    about 0.07 s of every dqskin process for it; usd-core's modules come compiled."""
    import compileall
    for folder in folders:
        compileall.compile_dir(str(folder), quiet=1)


def import_usdskel():
    import importlib
    for name in ("pxr.Usd", "pxr.UsdSkel"):
        importlib.import_module(name)


def import_dqskin():
    import importlib
    for name in ("dqskin.cli", "dqskin.readers.usd", "dqskin.writers.usd_cache",
                 "dqskin.distributed"):
        importlib.import_module(name)
    import warp as wp
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_ERROR
    wp.init()


def run_usdskel(src, dst):
    from pxr import Usd, UsdSkel
    stage = Usd.Stage.Open(str(src))
    gc.freeze()  # as the dqskin runs do once loaded (UsdSkel's bake is C++: little to walk)
    UsdSkel.BakeSkinning(stage.Traverse())
    stage.GetRootLayer().Export(str(dst))
    return {}


def run_dqskin(src, dst, which):
    """``which``: single | clips0 | clips1 | clips2 | clips1t1 | clips2t1 (``tN``: N threads per
    worker), ``+nv`` for normals and velocities."""
    from dqskin import SkinOptions
    from dqskin.baking import BakeSettings, bake
    from dqskin.distributed import bake_clips
    from dqskin.readers import load
    nv = which.endswith("+nv")
    kind, _, extra = which.partition("+")
    normals = nv or extra == "n"
    workers, _, threads = kind[5:].partition("t")
    scene = load(src)
    gc.freeze()  # as `dqskin skin` does once its input is loaded
    if kind == "single":
        bake(scene, dst, method="lbs", normals=normals, velocities=nv, clips=False, force=True)
        return {}
    if threads and not int(workers):  # in this process: the budget a one-thread worker gets
        from pxr import Work
        os.environ["DQSKIN_THREADS"] = threads
        Work.SetConcurrencyLimitArgument(int(threads))
    done = bake_clips(scene, dst, scene.times,
                      SkinOptions(method="lbs", normals=nv, velocities=nv),
                      BakeSettings(workers=int(workers) or None, force=True),
                      threads=int(threads or 0) or None)
    peaks = {}
    for task in done["tasks"]:
        peaks[task["pid"]] = max(peaks.get(task["pid"], 0.0), task["peak_rss_mb"])
    tasks = done["tasks"]
    return dict(worker_peak_mb=sorted(peaks.values()), clips=done["clips"],
                task_span=(max(t["ended"] for t in tasks) - min(t["started"] for t in tasks)
                           if tasks else None),
                task_seconds=float(np.mean([t["seconds"] for t in tasks])) if tasks else None,
                task_cpu_seconds=(float(np.mean([t["cpu_seconds"] for t in tasks]))
                                  if tasks and int(workers) else None))


def peak_rss_mb():
    """This process's peak resident memory (VmHWM; unlike ru_maxrss it restarts at exec, so a
    child forked from a large parent reports its own)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(which, src, dst):
    """Time imports and the bake separately, in this fresh process."""
    t0 = time.perf_counter()
    kind = which.removesuffix("+nv")
    if kind.startswith("clips") and int(kind[5:].partition("t")[0]):
        from dqskin.forkserver import prestart_workers
        prestart_workers()  # first, as `dqskin skin --workers`: its imports overlap dqskin's
    (import_usdskel if which == "usdskel" else import_dqskin)()
    # the full garbage collection the imports' objects make due runs now, not at a random point
    # of the load or bake (36 ms after dqskin's imports; where it fell moved with any change to
    # what is imported)
    gc.collect()
    gc.freeze()  # and never walked again (the peers alike; `dqskin skin` freezes after its load)
    t1 = time.perf_counter()
    extra = run_usdskel(src, dst) if which == "usdskel" else run_dqskin(src, dst, which)
    t2 = time.perf_counter()
    print(json.dumps(dict(seconds=t2 - t1, import_seconds=t1 - t0, peak_mb=peak_rss_mb(),
                          **extra)))


class _Phases:
    """``with phases("name"):`` records CPU seconds of this process (all its threads) and wall
    seconds of the block."""

    def __init__(self):
        self.rows = []

    @contextlib.contextmanager
    def __call__(self, name):
        c0, w0 = time.process_time(), time.perf_counter()
        yield
        self.rows.append((name, time.process_time() - c0, time.perf_counter() - w0))


def breakdown_usdskel(src, dst):
    """UsdSkel's points-only bake phase by phase; its skinning alone estimated apart (the same
    LBS per frame through ``UsdSkel.SkinningQuery``, Python calls included)."""
    ph = _Phases()
    with ph("imports"):
        from pxr import Usd, UsdGeom, UsdSkel, Vt
    with ph("open stage"):
        stage = Usd.Stage.Open(str(src))
    cache, pred = UsdSkel.Cache(), Usd.TraverseInstanceProxies()
    with ph("(apart) its skinning alone: SkinningQuery.ComputeSkinnedPoints per frame"):
        for prim in stage.Traverse():
            if not prim.IsA(UsdSkel.Root):
                continue
            cache.Populate(UsdSkel.Root(prim), pred)
            for binding in cache.ComputeSkelBindings(UsdSkel.Root(prim), pred):
                skel = cache.GetSkelQuery(binding.GetSkeleton())
                for target in binding.GetSkinningTargets():
                    rest = UsdGeom.PointBased(target.GetPrim()).GetPointsAttr().Get()
                    for f in range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1):
                        target.ComputeSkinnedPoints(skel.ComputeSkinningTransforms(f),
                                                    Vt.Vec3fArray(rest), f)
    with ph("BakeSkinning: skin + Vt arrays + set samples (C++, TBB)"):
        UsdSkel.BakeSkinning(stage.Traverse())
    with ph("Export (crate)"):
        stage.GetRootLayer().Export(str(dst))
    return ph.rows


def breakdown_dqskin(src, dst, chunk=256):
    """dqskin's points-only LBS single-layer bake (:func:`dqskin.bake`'s steps), each step over
    every frame before the next (no overlap), then what ``--resume`` pays per clip layer
    (reading one back to check its checksum: a clip bake hashes its layers as it writes them)."""
    ph = _Phases()
    with ph("imports"):
        from dqskin.files.atomic import atomic_path
        from dqskin.files.crate import CrateSamples
        from dqskin.readers import load
        from dqskin.validation import check_skinned
        from dqskin.writers.usd_cache import CacheLayer, _extents, export_layer
        from dqskin.writers.usd_clips import file_checksum
        import_dqskin()
    with ph("load (dqskin.readers.load)"):
        scene = load(src)
    with ph("CacheLayer: open, Flatten, unbind"):
        cache = CacheLayer(scene, dst)
    res = []
    with ph("skinning (Scene.skin_chunks, LBS points, 2 threads)"):
        for _, r in scene.skin_chunks(scene.times, chunk, method="lbs", normals=False,
                                      velocities=False):
            res.append(r)
    with ph("check_skinned (all finite)"):
        for r in res:
            check_skinned(src, r)
    names = [m.name for m in scene.meshes]
    with ph("extents"):
        ext = [{n: _extents(r.points[n], 0.0) for n in names} for r in res]
    targets = {n: (cache.target(n, "points"), cache.target(n, "extent")) for n in names}
    cache.set_metadata(scene.times.min(), scene.times.max())
    claim = atomic_path(dst, overwrite=True)
    tmp = claim.open()
    base = tmp.with_name(".base.usdc")
    with ph("export the source's copy (the base: topology, UVs, specs)"):
        export_layer(cache.layer, claim, tmp=base)
    with ph("crate: base values copied, then every frame written (writer thread)"):
        crate = CrateSamples(tmp, scene.time_codes_per_second, base=base)
        for r, e in zip(res, ext):
            for n in names:
                for target, values in zip(targets[n], (r.points[n], e[n])):
                    crate.add(target.attr, target.type_name, r.times, values)
        crate._drain()
    with ph("crate: the base's sections decoded, merged and written"):
        crate.close(scene.times.min(), scene.times.max())
    base.unlink()
    del res, ext
    with ph("(--resume only) checksum of a layer read back"):
        file_checksum(tmp)
    claim.commit()
    return ph.rows


def breakdown(frames, asset=DEFAULT_ASSET):
    """Print the CPU-seconds breakdown of a looped CesiumMan bake of ``frames`` frames."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = tmp / "long.usdc"
        make_long_clip(asset, frames, src)
        tables = {}
        for which in ("usdskel", "dqskin"):
            os.sync()  # no dirty pages from the run before (see bench_one)
            proc = subprocess.run([sys.executable, __file__, "--child-breakdown", which, str(src),
                                   str(tmp / f"{which}.usd")], capture_output=True, text=True)
            if proc.returncode:
                sys.exit(f"breakdown {which} failed:\n{proc.stderr[-2000:]}")
            tables[which] = json.loads(proc.stdout.strip().splitlines()[-1])
    print(f"\nPoints-only LBS bake of CesiumMan looped over {frames} frames, step by step (no "
          "overlap); CPU s counts every thread of the process")
    print("| bake | step | CPU s | wall s |\n|---|---|---|---|")
    for which, rows in tables.items():
        total = [0.0, 0.0]
        for name, cpu, wall in rows:
            print(f"| {which} | {name} | {cpu:.2f} | {wall:.2f} |")
            if name != "imports" and not name.startswith("("):
                total = [total[0] + cpu, total[1] + wall]
        print(f"| {which} | **sum without imports and (apart) rows** | {total[0]:.2f} "
              f"| {total[1]:.2f} |")


def compare_caches(a, b, probe_times):
    """Largest point distance between meshes of the same path in two caches."""
    from pxr import Usd, UsdGeom
    sa, sb = Usd.Stage.Open(str(a)), Usd.Stage.Open(str(b))
    worst = 0.0
    for prim in sa.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        other = sb.GetPrimAtPath(prim.GetPath())
        for t in probe_times:
            pa = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(t))
            pb = np.asarray(UsdGeom.Mesh(other).GetPointsAttr().Get(t))
            worst = max(worst, float(np.abs(pa - pb).max()))
    return worst


def output_mb(dst):
    """Size of a cache: the file and, for clips, its ``.clips`` folder."""
    from dqskin.writers.usd_clips import clips_folder  # (here: a child times its own imports)
    folder = clips_folder(dst)
    files = [dst] + (list(folder.iterdir()) if folder.is_dir() else [])
    return sum(f.stat().st_size for f in files) / 2**20


def _remove_output(dst):
    """Remove an earlier run's output (and its clips folder) before the next run writes it."""
    from dqskin.writers.usd_clips import clips_folder
    for f in (dst, clips_folder(dst)):
        if f.is_dir():
            shutil.rmtree(f)
        elif f.exists():
            f.unlink()


def bench_one(rows, label, src, impls, tmp, repeat=1):
    """Run every impl ``repeat`` times, interleaved (round 1: each impl once, round 2: ...):
    one row per impl, from its median run, with the range of all runs and, against UsdSkel,
    the median of the per-round ratios (on a VM, a run's speed swings by 2x between minutes;
    runs side by side in one round see the same machine)."""
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.Open(str(src))
    points = sum(len(UsdGeom.Mesh(p).GetPointsAttr().Get()) for p in stage.Traverse()
                 if p.IsA(UsdGeom.Mesh))
    t0, t1 = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    frames = int(round(t1 - t0)) + 1
    dsts, runs = {}, {which: [] for which in impls}
    for _ in range(repeat):
        for which in impls:
            dst = tmp / f"{label}_{which.replace('+', '_')}.usd"
            _remove_output(dst)
            # every bake starts with no dirty pages: the kernel throttles a writer once earlier
            # runs' outputs (hundreds of MB, not yet on disk) pass its dirty limit, which would
            # charge one implementation for the writeback of the one run before it
            os.sync()
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            whole = is_whole(which)
            w0 = time.perf_counter()
            proc = subprocess.run(cli_command(which, src, dst) if whole else
                                  [sys.executable, __file__, "--child", which, str(src),
                                   str(dst)], capture_output=True, text=True)
            process_seconds = time.perf_counter() - w0
            after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the process tree, reaped
            cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
            if proc.returncode:
                print(f"  {label} {which}: failed (exit {proc.returncode}):\n"
                      f"{proc.stderr[-1000:]}", file=sys.stderr)
                continue
            if whole:  # the whole process: no split of its imports
                r = dict(seconds=process_seconds, import_seconds=0.0, peak_mb=float("nan"),
                         said=proc.stdout.strip())
            else:
                r = json.loads(proc.stdout.strip().splitlines()[-1])
            dsts[which] = dst
            runs[which].append(dict(
                kind="bake", asset=label, frames=frames, points=points, impl=which,
                seconds=r["seconds"], import_seconds=r["import_seconds"], cpu_seconds=cpu,
                process_seconds=process_seconds, said=r.get("said"),
                peak_mb=r["peak_mb"], worker_peak_mb=r.get("worker_peak_mb", []),
                task_seconds=r.get("task_seconds"), task_cpu_seconds=r.get("task_cpu_seconds"),
                task_span=r.get("task_span"),
                mpoint_frames_per_s=points * frames / r["seconds"] / 1e6,
                output_mb=output_mb(dst)))
            print(f"  {label} {frames} frames {which}: {r['seconds']:.2f} s", file=sys.stderr)
    new = []
    for which, rs in runs.items():
        if not rs:
            continue
        secs = [r["seconds"] for r in rs]
        procs = [r["process_seconds"] for r in rs]
        cpus = [r["cpu_seconds"] for r in rs]
        new.append(dict(sorted(rs, key=lambda r: r["seconds"])[(len(rs) - 1) // 2],
                        seconds_range=(min(secs), max(secs)), runs=len(rs), all_seconds=secs,
                        all_task_spans=[r.get("task_span") for r in rs],
                        all_process_seconds=procs, all_cpu_seconds=cpus))
    rows.extend(new)
    if "usdskel" in dsts:
        probes = [t0, t0 + (t1 - t0) // 2, t1, t0 + 0.5]
        for r in new:
            if r["impl"] in dsts and r["impl"] != "usdskel":
                r["max_point_diff"] = compare_caches(dsts["usdskel"], dsts[r["impl"]], probes)


def bench_bake(rows, frames=(1000, 10000), asset=DEFAULT_ASSET, brainstem=None, impls=IMPLS,
               standin=True, repeat=1, work_dir=None):
    """``work_dir``: where the sources and outputs go (a temporary folder in it; default the
    system's), e.g. a tmpfs to take the disk's file system out of the figures."""
    with tempfile.TemporaryDirectory(dir=work_dir) as tmp:
        tmp = Path(tmp)
        brainstem = brainstem or find_brainstem()
        if brainstem and Path(brainstem).is_file():
            bench_one(rows, "BrainStem", Path(brainstem), impls, tmp, repeat)
        elif Path(asset).is_file() and standin:
            print("bake: BrainStem.usdz not found under ../shared/assets; a stand-in of its "
                  "shape instead: 59 meshes of 75 to 2,900 points (35,114 in all) cut from "
                  "CesiumMan, one skeleton, 1,309 poses of its own")
            make_many_meshes(asset, 1309, tmp / "many_1309.usdc")
            bench_one(rows, "59-mesh stand-in", tmp / "many_1309.usdc", impls, tmp, repeat)
        if not Path(asset).is_file():
            print(f"bake: skipped, {asset} not found")
        else:
            for n in frames:
                src = tmp / f"long_{n}.usdc"
                make_long_clip(asset, n, src)
                bench_one(rows, f"CesiumMan×{n}", src, impls, tmp, repeat)
                src.unlink()
                for f in tmp.glob(f"CesiumMan×{n}*"):  # keep /tmp small between sizes
                    shutil.rmtree(f) if f.is_dir() else f.unlink()
    print_bake(rows)


def _ratio(a, b):
    """``a``'s seconds / ``b``'s: with several rounds, the median of the per-round ratios (and
    their range), since runs in one round see the same machine."""
    sa, sb = a.get("all_seconds", [a["seconds"]]), b.get("all_seconds", [b["seconds"]])
    if len(sa) < 2 or len(sa) != len(sb):
        return f"{a['seconds'] / b['seconds']:.2f}×"
    ratios = sorted(x / y for x, y in zip(sa, sb))
    return (f"{ratios[(len(ratios) - 1) // 2]:.2f}× (median of {len(ratios)} rounds, "
            f"{ratios[0]:.2f}–{ratios[-1]:.2f}×)")


def print_bake(rows):
    bake = [r for r in rows if r["kind"] == "bake"]
    if not bake:
        return
    print("\nEnd-to-end bake to .usd (open + skin every frame + write), LBS; seconds exclude the "
          "one-off module imports (shown apart, and with them: a worker bake's forkserver starts "
          "first and imports beside them), include Dask cluster start-up")
    print("| asset | frames | impl | seconds | M point-frames/s | imports s | with imports s "
          "| CPU s, all processes | peak RSS MB, main | workers MB | output MB "
          "| max \\|Δp\\| vs UsdSkel |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in bake:
        workers = ", ".join(f"{w:.0f}" for w in r.get("worker_peak_mb", [])) or "–"
        diff = r.get("max_point_diff")
        secs = f"{r['seconds']:.2f}"
        if r.get("runs", 1) > 1:
            secs += f" ({r['seconds_range'][0]:.2f}–{r['seconds_range'][1]:.2f})"
        print(f"| {r.get('asset', '')} | {r['frames']} | {r['impl']} | {secs} "
              f"| {r['mpoint_frames_per_s']:.1f} | {r['import_seconds']:.2f} "
              f"| {r['seconds'] + r['import_seconds']:.2f} "
              f"| {r.get('cpu_seconds', float('nan')):.1f} | {r['peak_mb']:.0f} "
              f"| {workers} | {r.get('output_mb', float('nan')):.0f} "
              f"| {'–' if diff is None else f'{diff:.1e}'} |")
    for key in dict.fromkeys((r.get("asset"), r["frames"]) for r in bake):
        sel = {r["impl"]: r for r in bake if (r.get("asset"), r["frames"]) == key}
        line = []
        for one, two, what in (("clips1", "clips2", "2 workers / 1 worker"),
                               ("clips1t1", "clips2t1", "2 workers / 1 worker, 1 thread each"),
                               ("clips0t1", "clips2t1", "2 one-thread workers / in-process, 1 "
                                "thread")):
            if one in sel and two in sel:
                a, b = sel[one], sel[two]
                total = (a["seconds"] + a["import_seconds"]) / (b["seconds"] + b["import_seconds"])
                line.append(f"{what} = {_ratio(a, b)} (with imports {total:.2f}×")
                if a.get("task_span") and b.get("task_span"):  # the tasks alone: no start-up
                    spans = [dict(seconds=a["task_span"], all_seconds=a["all_task_spans"]),
                             dict(seconds=b["task_span"], all_seconds=b["all_task_spans"])]
                    line[-1] += (f"; first task's start to last task's end "
                                 f"{_ratio(*spans)}")
                line[-1] += ")"
        for impl in ("clips1t1", "clips2t1", "clips1", "clips2"):
            r = sel.get(impl, {})
            if r.get("task_cpu_seconds"):  # a worker runs one task at a time: its process CPU
                line.append(f"{impl} task {1e3 * r['task_seconds']:.0f} ms, worker CPU "
                            f"{1e3 * r['task_cpu_seconds']:.0f} ms "
                            f"({r['task_cpu_seconds'] / r['task_seconds']:.2f} cores)")
        if "usdskel" in sel:
            for impl in ("single", "clips0", "clips2", "single+nv"):
                if impl in sel:
                    line.append(f"{impl} / UsdSkel throughput = "
                                f"{_ratio(sel['usdskel'], sel[impl])}")
        print(f"  {key[0]}: " + "; ".join(line))
        print_whole(sel)


def _median(values):
    v = sorted(values)
    return v[(len(v) - 1) // 2]


def print_whole(sel):
    """Whole processes (interpreter start, imports, load, bake, write, exit): each impl's median
    wall and CPU seconds with their ranges, and UsdSkel's over each ``cli*`` impl's, round by
    round (the median of the per-round ratios and their range)."""
    if not any(is_whole(i) for i in sel):
        return
    print("  whole processes, median (range) of the rounds:")
    for impl, r in sel.items():
        if impl != "usdskel" and not is_whole(impl):
            continue
        w, c = r["all_process_seconds"], r["all_cpu_seconds"]
        line = (f"    {impl}: wall {_median(w):.2f} s ({min(w):.2f}–{max(w):.2f}), CPU "
                f"{_median(c):.2f} s ({min(c):.2f}–{max(c):.2f})")
        base = sel.get("usdskel")
        if base is not None and impl != "usdskel" and len(base["all_process_seconds"]) == len(w):
            for what, a, b in (("wall", base["all_process_seconds"], w),
                               ("CPU", base["all_cpu_seconds"], c)):
                ratios = sorted(x / y for x, y in zip(a, b))
                line += (f"; UsdSkel / this, {what}: {_median(ratios):.2f}× "
                         f"({ratios[0]:.2f}–{ratios[-1]:.2f}×)")
        if r.get("said") and ";" in r["said"]:
            line += f" [{r['said'].split(';', 1)[1].strip()}]"
        print(line)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:5])
        sys.exit(0)
    if len(sys.argv) > 1 and sys.argv[1] == "--child-breakdown":
        fn = breakdown_usdskel if sys.argv[2] == "usdskel" else breakdown_dqskin
        print(json.dumps(fn(*sys.argv[3:5])))
        sys.exit(0)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="1000,10000")
    ap.add_argument("--asset", default=str(DEFAULT_ASSET))
    ap.add_argument("--brainstem", help="BrainStem.usdz (default: searched under ../shared)")
    ap.add_argument("--impls", default=",".join(IMPLS))
    ap.add_argument("--no-standin", action="store_true", help="no BrainStem stand-in")
    ap.add_argument("--json", help="also write the rows here")
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds of every impl, interleaved; rows from each impl's median run")
    ap.add_argument("--work-dir", help="folder for the sources and outputs (default: the "
                    "system's temporary folder), e.g. /dev/shm to leave the disk's file system "
                    "out")
    ap.add_argument("--before", metavar="TREE", help="a copy of another dqskin tree (e.g. "
                    "`git archive main`, with dqskin/kernels linked to its kernels/): the "
                    "``cli*@before`` impls run it, for before/after figures in one run")
    ap.add_argument("--breakdown", type=int, metavar="FRAMES",
                    help="only the step-by-step CPU-seconds breakdown of a FRAMES-frame bake")
    a = ap.parse_args()
    if a.before:
        os.environ["BENCH_BEFORE"] = str(Path(a.before).resolve())
    if a.breakdown:
        breakdown(a.breakdown, a.asset)
        sys.exit(0)
    import dqskin.kernels  # which trees the child processes import (see tools/bench.py)
    print(f"dqskin from {Path(dqskin.__file__).parent}, its kernels from "
          f"{Path(dqskin.kernels.__file__).parent}")
    compile_trees(Path(dqskin.__file__).parent, Path(dqskin.kernels.__file__).parent,
                  *([Path(a.before) / "dqskin", Path(a.before) / "kernels"] if a.before else []))
    out_rows = []
    bench_bake(out_rows, [int(x) for x in a.frames.split(",") if x], a.asset, a.brainstem,
               [x for x in a.impls.split(",") if x], not a.no_standin, a.repeat, a.work_dir)
    if a.json:
        Path(a.json).write_text(json.dumps(out_rows, indent=1))
