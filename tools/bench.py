"""Side-by-side benchmark: dqskin vs UsdSkel (C++) vs vectorized NumPy, same data, one run.

    python tools/bench.py [--sizes 10000,100000,1000000] [--json out/bench.json] [--quick]

Skinning: random rigid rigs, 4 influences, 64 joints, float32; each implementation skins the same
points with the same transforms; per-call time is the best over ``--repeat`` rounds of the mean of
a burst of back-to-back calls. dqskin times include uploading the
frame's transforms, preparing them and reading the result back (the mesh is uploaded once, as a
pipeline would). FK: 1,000 skeletons × 64 joints. Prints a table and writes JSON.
"""

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp
from pxr import Gf, UsdSkel, Vt
from scipy.spatial.transform import Rotation

import dqskin
from dqskin.skeleton import forward_kinematics

JOINTS, INFLUENCES = 64, 4


def best_times(fns, repeat, burst_seconds=0.1):
    """Per-call wall time of each callable: the best over ``repeat`` rounds of the mean of a burst
    of back-to-back calls (about ``burst_seconds`` long, so steady state, as in a pipeline).
    Rounds are interleaved so machine noise hits every implementation alike, with a pause before
    each burst so the previous implementation's worker threads (TBB, BLAS) go idle."""
    bursts = {}
    for name, fn in fns.items():
        fn()  # warm-up (kernel load, caches)
        t0 = time.perf_counter()
        fn()
        bursts[name] = max(1, min(50, int(burst_seconds / max(time.perf_counter() - t0, 1e-6))))
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeat):
        for name, fn in fns.items():
            time.sleep(0.3)
            t0 = time.perf_counter()
            for _ in range(bursts[name]):
                fn()
            best[name] = min(best[name], (time.perf_counter() - t0) / bursts[name])
    return best


def make_rig(rng, V):
    points = rng.normal(size=(V, 3)).astype(np.float32)
    idx = rng.integers(0, JOINTS, size=(V, INFLUENCES)).astype(np.int32)
    w = rng.random((V, INFLUENCES)).astype(np.float32)
    w /= w.sum(1, keepdims=True)
    M = np.tile(np.eye(4), (JOINTS, 1, 1))
    M[:, :3, :3] = Rotation.random(JOINTS, random_state=rng).as_matrix()
    M[:, :3, 3] = rng.normal(size=(JOINTS, 3))
    return points, idx, w, M


def numpy_lbs(points, idx, w, M):
    A = M[:, :3, :].astype(np.float32)
    blended = np.einsum("vk,vkij->vij", w, A[idx])
    return np.einsum("vij,vj->vi", blended[:, :, :3], points) + blended[:, :, 3]


def numpy_dqs(points, idx, w, M):
    q = Rotation.from_matrix(M[:, :3, :3]).as_quat().astype(np.float32)  # (x, y, z, w)
    t = M[:, :3, 3].astype(np.float32)
    # dual part d = ½·t·q, as (x, y, z, w)
    dv = 0.5 * (q[:, 3:] * t + np.cross(t, q[:, :3]))
    dw = -0.5 * np.sum(t * q[:, :3], 1, keepdims=True)
    d = np.concatenate([dv, dw], 1)
    qr, qd = q[idx], d[idx]
    pivot = qr[np.arange(len(idx)), np.argmax(w, 1)]
    s = np.where(np.einsum("vki,vi->vk", qr, pivot) < 0, -w, w)
    r = np.einsum("vk,vki->vi", s, qr)
    e = np.einsum("vk,vki->vi", s, qd)
    rv, rw, ev, ew = r[:, :3], r[:, 3:], e[:, :3], e[:, 3:]
    inv = 2.0 / np.sum(r * r, 1, keepdims=True)
    return points + inv * (np.cross(rv, np.cross(rv, points) + rw * points)
                           + rw * ev - ew * rv + np.cross(rv, ev))


def bench_skinning(sizes, repeat, devices, rows):
    rng = np.random.default_rng(0)
    for V in sizes:
        points, idx, w, M = make_rig(rng, V)
        rep = repeat
        xf = Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(M.transpose(0, 2, 1)))
        vi, vw = Vt.IntArray.FromNumpy(idx.ravel()), Vt.FloatArray.FromNumpy(w.ravel())
        for method, token in (("lbs", "classicLinear"), ("dqs", "dualQuaternion")):
            fns = {}
            for dev in devices:
                sk = dqskin.Skinner(points, idx, w, device=dev)
                fns[f"dqskin {dev}"] = (lambda sk=sk: (sk.skin(M, method), wp.synchronize()))
            src = Vt.Vec3fArray.FromNumpy(points)
            for serial in (True, False):
                def usd(serial=serial):
                    p = Vt.Vec3fArray(src)
                    UsdSkel.SkinPoints(token, Gf.Matrix4d(1), xf, vi, vw, INFLUENCES, p, serial)
                fns["UsdSkel " + ("serial" if serial else "parallel")] = usd
            oracle = numpy_lbs if method == "lbs" else numpy_dqs
            fns["NumPy"] = lambda oracle=oracle: oracle(points, idx, w, M)
            res = best_times(fns, rep)
            for impl, t in res.items():
                rows.append(dict(kind="skin", method=method, vertices=V, impl=impl, seconds=t,
                                 mpts_per_s=V / t / 1e6))


def bench_fk(devices, rows, skeletons=1000):
    """FK of ``skeletons`` × 64 joints from local matrices and from TRS (what animations store).

    UsdSkel: ``ConcatJointTransforms`` per skeleton (its API is one skeleton per call), after
    ``MakeTransforms`` for TRS. Inputs are converted to each implementation's native form untimed.
    """
    rng = np.random.default_rng(1)
    parents = np.array([-1] + [int(rng.integers(0, j)) for j in range(1, JOINTS)])
    rot = Rotation.random(skeletons * JOINTS, random_state=rng)
    q_wxyz = rot.as_quat()[:, [3, 0, 1, 2]].reshape(skeletons, JOINTS, 4).astype(np.float32)
    trans = rng.normal(size=(skeletons, JOINTS, 3)).astype(np.float32)
    scale = np.ones((skeletons, JOINTS, 3), np.float32)
    local = np.tile(np.eye(4, dtype=np.float32), (skeletons, JOINTS, 1, 1))
    local[..., :3, :3] = rot.as_matrix().reshape(skeletons, JOINTS, 3, 3)
    local[..., :3, 3] = trans

    def numpy_fk():
        world = np.empty_like(local)
        for j, p in enumerate(parents):
            world[:, j] = local[:, j] if p < 0 else world[:, p] @ local[:, j]
        return world
    topo = UsdSkel.Topology(Vt.IntArray([int(p) for p in parents]))
    usd_local = [Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(
        local[s].astype(np.float64).transpose(0, 2, 1))) for s in range(skeletons)]
    usd_trs = [(Vt.Vec3fArray.FromNumpy(trans[s]),
                Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z))
                               for w, x, y, z in q_wxyz[s]]),
                Vt.Vec3hArray.FromNumpy(scale[s].astype(np.float16))) for s in range(skeletons)]
    fns = {}
    for dev in devices:
        fns[f"dqskin {dev} matrices"] = lambda dev=dev: forward_kinematics(
            parents, local, device=dev)
        fns[f"dqskin {dev} TRS"] = lambda dev=dev: forward_kinematics(
            parents, (trans, q_wxyz, scale), device=dev)
    fns["NumPy matrices"] = numpy_fk
    fns["UsdSkel matrices"] = lambda: [UsdSkel.ConcatJointTransforms(topo, x) for x in usd_local]
    fns["UsdSkel TRS"] = lambda: [UsdSkel.ConcatJointTransforms(topo, UsdSkel.MakeTransforms(*x))
                                  for x in usd_trs]
    res = best_times(fns, 5)
    for impl, t in res.items():
        rows.append(dict(kind="fk", skeletons=skeletons, joints=JOINTS, impl=impl, seconds=t,
                         mjoints_per_s=skeletons * JOINTS / t / 1e6))


def print_tables(rows):
    skin = [r for r in rows if r["kind"] == "skin"]
    if skin:
        print_skin_table(skin)
    fk = [r for r in rows if r["kind"] == "fk"]
    if fk:
        print(f"\nFK: {fk[0]['skeletons']} skeletons × {fk[0]['joints']} joints (M joints/s)")
        for r in fk:
            print(f"| {r['impl']:>22} | {r['mjoints_per_s']:8.2f} | {r['seconds'] * 1e3:8.2f} ms |")


def print_skin_table(skin):
    print(f"\nSkinning: {INFLUENCES} influences, {JOINTS} joints, float32 "
          "(Mpts/s, higher is better)")
    impls = list(dict.fromkeys(r["impl"] for r in skin))
    head = f"| {'vertices':>9} | method | " + " | ".join(f"{i:>17}" for i in impls)
    print(head + " | ×UsdSkel par. | DQS/LBS time |")
    print("|" + "---|" * (len(impls) + 4))
    for V in dict.fromkeys(r["vertices"] for r in skin):
        for method in ("lbs", "dqs"):
            sel = {r["impl"]: r for r in skin if r["vertices"] == V and r["method"] == method}
            ours = next(i for i in impls if i.startswith("dqskin"))
            ratio = sel[ours]["mpts_per_s"] / sel["UsdSkel parallel"]["mpts_per_s"]
            other = {r["impl"]: r for r in skin if r["vertices"] == V and r["method"] == "lbs"}
            dl = sel[ours]["seconds"] / other[ours]["seconds"]
            cells = " | ".join(f"{sel[i]['mpts_per_s']:17.1f}" for i in impls)
            print(f"| {V:>9} | {method:6} | {cells} | {ratio:12.2f}× | {dl:11.2f}× |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--json", default="out/bench.json")
    ap.add_argument("--quick", action="store_true", help="10k and 100k only, fewer repeats")
    ap.add_argument("--skip", default="", help="comma list of sections to skip: skin,fk,bake")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.quick:
        sizes, args.repeat = [s for s in sizes if s <= 100_000], 3
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    skip = set(filter(None, args.skip.split(",")))
    rows = []
    if "skin" not in skip:
        bench_skinning(sizes, args.repeat, devices, rows)
    if "fk" not in skip:
        bench_fk(devices, rows)
    if "bake" not in skip:
        from bench_bake import bench_bake  # noqa: E402  (tools/ sibling)
        bench_bake(rows)
    print_tables(rows)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(python=sys.version.split()[0], warp=wp.__version__, numpy=np.__version__,
                machine=platform.machine(), cpus=os.cpu_count(),
                threads=int(os.environ.get("DQSKIN_THREADS", os.cpu_count() or 1)))
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    os.replace(tmp, out)
    print(f"\nwrote {out}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
