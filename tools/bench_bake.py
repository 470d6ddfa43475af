"""End-to-end bake benchmark: load → skin every frame → write ``.usdc``, dqskin vs UsdSkel.

    python tools/bench_bake.py [--frames 1000,2000,4000] [--asset PATH]

Makes a long clip by looping the asset's SkelAnimation (CesiumMan.usdz: 48 keys) over N frames,
then, each in a fresh process so peak memory (max RSS) is its own:

* UsdSkel: ``UsdSkel.BakeSkinning(stage)`` + ``Export`` to ``.usdc`` (LBS, what usd-core bakes);
* dqskin: ``dqskin skin --method lbs`` (load, skin chunks of frames on a worker thread while the
  previous chunk is written with ``UsdCacheWriter``), writing points and extent as UsdSkel does;
  and again with skinned normals too (UsdSkel's bake leaves ``primvars:normals`` at rest).

Reports point-frames/s end to end, the ratio, peak RSS and the largest point difference between
the two caches. Also callable from ``tools/bench.py`` (``bench_bake(rows)``).
"""

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ASSET = ROOT.parent / "shared" / "assets" / "usd-wg" / "CesiumMan" / "CesiumMan.usdz"


def make_long_clip(asset, frames, out):
    """Flatten ``asset`` and loop every SkelAnimation's samples over ``frames`` time codes."""
    from pxr import Usd, UsdSkel
    stage = Usd.Stage.Open(str(asset))
    layer = stage.Flatten()
    long_stage = Usd.Stage.Open(layer)
    for prim in long_stage.Traverse():
        if not prim.IsA(UsdSkel.Animation):
            continue
        anim = UsdSkel.Animation(prim)
        for attr in (anim.GetTranslationsAttr(), anim.GetRotationsAttr(), anim.GetScalesAttr()):
            keys = attr.GetTimeSamples()
            if len(keys) < 2:
                continue
            values = [attr.Get(k) for k in keys]
            attr.Clear()
            for f in range(frames):
                attr.Set(values[f % len(values)], keys[0] + f)
    long_stage.SetStartTimeCode(1)
    long_stage.SetEndTimeCode(frames)
    long_stage.GetRootLayer().Export(str(out))


def import_usdskel():
    import importlib
    for name in ("pxr.Usd", "pxr.UsdSkel"):
        importlib.import_module(name)


def import_dqskin():
    import importlib
    for name in ("dqskin.cli", "dqskin.formats.usd", "dqskin.formats.usd_cache"):
        importlib.import_module(name)


def run_usdskel(src, dst):
    from pxr import Usd, UsdSkel
    stage = Usd.Stage.Open(str(src))
    UsdSkel.BakeSkinning(stage.Traverse())
    stage.GetRootLayer().Export(str(dst))


def run_dqskin(src, dst, normals=False):
    """Like UsdSkel's bake: points and extent (UsdSkel leaves ``primvars:normals`` unskinned)."""
    from dqskin.cli import main
    rc = main(["skin", str(src), "--out", str(dst), "--method", "lbs", "--force", "--no-velocities"]
              + ([] if normals else ["--no-normals"]))
    if rc:
        raise SystemExit(rc)


def run_dqskin_normals(src, dst):
    run_dqskin(src, dst, normals=True)


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
    (import_usdskel if which == "usdskel" else import_dqskin)()
    t1 = time.perf_counter()
    {"usdskel": run_usdskel, "dqskin": run_dqskin, "dqskin+normals": run_dqskin_normals}[which](
        src, dst)
    t2 = time.perf_counter()
    peak_mb = peak_rss_mb()
    print(json.dumps(dict(seconds=t2 - t1, import_seconds=t1 - t0, peak_mb=peak_mb)))


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


def bench_bake(rows, frames=(1000, 2000, 4000), asset=DEFAULT_ASSET):
    if not Path(asset).is_file():
        print(f"bake: skipped, {asset} not found")
        return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for n in frames:
            src = tmp / f"long_{n}.usdc"
            make_long_clip(asset, n, src)
            res = {}
            for which in ("usdskel", "dqskin", "dqskin+normals"):
                dst = tmp / f"{which}_{n}.usdc"
                proc = subprocess.run(
                    [sys.executable, __file__, "--child", which, str(src), str(dst)],
                    capture_output=True, text=True)
                if proc.returncode:
                    raise RuntimeError(f"{which} bake failed:\n{proc.stderr[-2000:]}")
                res[which] = json.loads(proc.stdout.strip().splitlines()[-1])
            from pxr import Usd, UsdGeom
            stage = Usd.Stage.Open(str(src))
            points = sum(len(UsdGeom.Mesh(p).GetPointsAttr().Get()) for p in stage.Traverse()
                         if p.IsA(UsdGeom.Mesh))
            diff = compare_caches(tmp / f"usdskel_{n}.usdc", tmp / f"dqskin_{n}.usdc",
                                  [1, n // 2, n])
            for which, r in res.items():
                rows.append(dict(kind="bake", frames=n, points=points, impl=which,
                                 seconds=r["seconds"], import_seconds=r["import_seconds"],
                                 peak_mb=r["peak_mb"],
                                 mpoint_frames_per_s=points * n / r["seconds"] / 1e6,
                                 max_point_diff=diff))
    print_bake(rows)


def print_bake(rows):
    bake = [r for r in rows if r["kind"] == "bake"]
    if not bake:
        return
    print("\nEnd-to-end bake to .usdc (open + skin every frame + write points, normals, "
          "extent), LBS;\nseconds exclude the one-off module imports, shown apart")
    print("| frames | impl | seconds | M point-frames/s | imports s | peak RSS MB "
          "| max |Δp| vs UsdSkel |")
    print("|---|---|---|---|---|---|---|")
    for r in bake:
        print(f"| {r['frames']} | {r['impl']} | {r['seconds']:.2f} "
              f"| {r['mpoint_frames_per_s']:.1f} "
              f"| {r['import_seconds']:.2f} | {r['peak_mb']:.0f} | {r['max_point_diff']:.2e} |")
    for n in dict.fromkeys(r["frames"] for r in bake):
        sel = {r["impl"]: r for r in bake if r["frames"] == n}
        ratio = sel["dqskin"]["mpoint_frames_per_s"] / sel["usdskel"]["mpoint_frames_per_s"]
        print(f"  {n} frames: dqskin / UsdSkel throughput = {ratio:.2f}×")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:5])
        sys.exit(0)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="1000,2000,4000")
    ap.add_argument("--asset", default=str(DEFAULT_ASSET))
    a = ap.parse_args()
    bench_bake([], [int(x) for x in a.frames.split(",")], a.asset)
