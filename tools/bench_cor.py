"""Benchmark ``method="cor"``: center precomputation and runtime skinning next to LBS and DQS.

    python tools/bench_cor.py [--json out/bench_cor.json] [--frames 32] [--repeat 5] [--exact]
    DQSKIN_THREADS=1 python tools/bench_cor.py --kernels

Meshes: CesiumMan (../shared/assets/khronos-gltf/CesiumMan, when present), the bundled humanoid
subdivided to ~35.6k vertices as in tools/bench_compare.py, and a hard case: a 35.2k-point tube
along a chain of 40 joints, 4 influences per vertex from overlapping ramps with 5% per-vertex noise
(no two weight vectors equal, every joint pair shared by thousands of triangles), which
``cluster="auto"`` clusters. ``--exact`` also times ``cluster=None`` and prints what the default
costs in accuracy: the largest distance between default and exact centers, and between the points
skinned with them (the asset's frames; the tube, which has no animation, bent 30° and twisted 15°
at every joint), absolute and relative to the mesh's bounding-box diagonal. The disk cache is a
fresh temporary folder (``$DQSKIN_CACHE_DIR``), so every computation is a miss. Precompute:
``rotation_centers`` without the disk cache, first call in the process (Warp kernel already
compiled) and the best of ``--repeat`` more; with the paper's refinement (``subdivide=0.1``, one
call); then the cache hit (second run of the same mesh). Runtime: ``Skinner.skin`` of ``--frames``
frames of the asset's own animation (host transforms in, host points out), the best of ``--repeat``
rounds, for LBS, DQS (both sign rules) and COR; in million point-frames per second. Prints a table
and writes JSON.
"""

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import dqskin
from dqskin import cor

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from bench_compare import subdivide  # noqa: E402

CESIUM = ROOT.parent / "shared" / "assets" / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb"


def meshes():
    """``(label, scene, mesh)`` of every benchmark mesh."""
    out = []
    if CESIUM.is_file():
        scene = dqskin.load(CESIUM)
        out += [(f"CesiumMan {m.name}", scene, m) for m in scene.meshes]
    else:
        print(f"skipping CesiumMan: {CESIUM} not found", file=sys.stderr)
    scene = dqskin.load(ROOT / "assets" / "humanoid.usda")
    body = [subdivide(subdivide(m)) if m.name.endswith("Body") else subdivide(m)
            for m in scene.meshes]
    # one mesh of all parts (same skeleton), so the figure is for one ~35k-point mesh
    offsets = np.cumsum([0] + [len(m.points) for m in body[:-1]])
    merged = replace(body[0], name="/Humanoid/All",
                     points=np.concatenate([m.points for m in body]),
                     faces=np.concatenate([m.faces + o for m, o in zip(body, offsets)]),
                     joint_indices=np.concatenate([m.joint_indices for m in body]),
                     joint_weights=np.concatenate([m.joint_weights for m in body]),
                     deformer=None, output_transforms=None)
    scene = replace(scene, meshes=[merged])
    out.append(("humanoid subdivided", scene, merged))
    tube = tube_scene()
    out.append(("noisy tube", tube, tube.meshes[0]))
    return out


def tube_scene(around=64, rings=550, joints=40, influences=4):
    """The hard case above, as a one-mesh Scene on a flat skeleton (rest pose only)."""
    x = np.linspace(0, joints, rings)
    a = np.linspace(0, 2 * np.pi, around, endpoint=False)
    X, A = np.meshgrid(x, a, indexing="ij")
    pts = np.stack([X, np.cos(A), np.sin(A)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(around), indexing="ij")
    p, q = (i * around + j).ravel(), (i * around + (j + 1) % around).ravel()
    faces = np.concatenate([np.stack([p, q, q + around], 1), np.stack([p, q + around, p + around],
                                                                       1)])
    w = np.maximum(0, 1 - np.abs(pts[:, :1] - (np.arange(joints) + 0.5)) / 2.0)
    w *= 1 + 0.05 * np.random.default_rng(0).random(w.shape)
    idx = np.argsort(-w, 1)[:, :influences]
    wts = np.take_along_axis(w, idx, 1)
    wts /= wts.sum(1, keepdims=True)
    mesh = dqskin.Mesh("/Tube", pts.astype(np.float32), faces.astype(np.int32),
                       idx.astype(np.int32), wts.astype(np.float32))
    bind = np.tile(np.eye(4), (joints, 1, 1))
    skel = dqskin.Skeleton([f"j{k}" for k in range(joints)], np.full(joints, -1), bind, bind)
    return dqskin.Scene("tube", [mesh], [skel], np.zeros(1))


def tube_bend(joints, angle=np.radians(30.0)):
    """(1, J, 4, 4) skinning transforms of :func:`tube_scene`'s chain (joint j at x = j) bent by
    ``angle`` about z and twisted by half of it about x at every joint."""
    from scipy.spatial.transform import Rotation

    out = np.zeros((1, joints, 4, 4))
    world = np.eye(4)
    for j in range(joints):
        local = np.eye(4)
        local[:3, :3] = Rotation.from_rotvec([angle / 2, 0.0, angle]).as_matrix()
        local[0, 3] = 1.0 if j else 0.0
        world = world @ local
        inv_bind = np.eye(4)
        inv_bind[0, 3] = -j
        out[0, j] = world @ inv_bind
    return out


def cluster_error(scene, mesh, pts, centers, xf):
    """Exact centers (timed, a cache miss) and the default's errors against them."""
    t0 = time.perf_counter()
    exact = cor.rotation_centers(pts, mesh.faces, mesh.joint_indices, mesh.joint_weights,
                                 cluster=None)
    seconds = time.perf_counter() - t0
    if scene.path == "tube":
        xf = tube_bend(len(scene.skeletons[0].joint_names))
    skinned = [dqskin.Skinner(mesh.points, mesh.joint_indices, mesh.joint_weights,
                              geom_bind_transform=mesh.geom_bind_transform, faces=mesh.faces,
                              cor=dqskin.CorOptions(cluster=c)).skin(xf, "cor").astype(np.float64)
               for c in ("auto", None)]  # (the exact one reads the cache just filled)
    size = float(np.linalg.norm(np.ptp(pts, axis=0)))
    c_err = float(np.nanmax(np.linalg.norm(centers - exact, axis=1), initial=0.0))
    p_err = float(np.linalg.norm(skinned[0] - skinned[1], axis=-1).max())
    return dict(precompute_exact_s=seconds, size=size, center_error=c_err,
                point_error=p_err)


def bind_points(mesh):
    g = np.asarray(mesh.geom_bind_transform, np.float64)
    return np.asarray(mesh.points, np.float64) @ g[:3, :3].T + g[:3, 3]


def bench(frames, repeat, exact):
    rows = []
    for label, scene, mesh in meshes():
        pts = bind_points(mesh)
        args = (pts, mesh.faces, mesh.joint_indices, mesh.joint_weights)
        t0 = time.perf_counter()
        centers = cor.rotation_centers(*args, cache=False)
        first = time.perf_counter() - t0
        best = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            cor.rotation_centers(*args, cache=False)
            best = min(best, time.perf_counter() - t0)
        t0 = time.perf_counter()
        cor.rotation_centers(*args, subdivide=0.1, cache=False)
        subdivided = time.perf_counter() - t0
        cor.rotation_centers(*args)  # fills the cache
        t0 = time.perf_counter()
        cor.rotation_centers(*args)
        hit = time.perf_counter() - t0
        row = dict(mesh=label, vertices=len(mesh.points), faces=len(mesh.faces),
                   influences=int(mesh.joint_indices.shape[1]),
                   joints=len(scene.skeletons[mesh.skeleton].joint_names),
                   with_center=int(np.sum(~np.isnan(centers[:, 0]))),
                   precompute_first_s=first, precompute_s=best, cache_hit_s=hit,
                   precompute_subdivided_s=subdivided)
        times = np.resize(scene.times, frames) if len(scene.times) else np.zeros(frames)
        xf = scene.skinning_transforms(times, mesh.skeleton)
        if exact:
            row.update(cluster_error(scene, mesh, pts, centers, xf))
        sk = dqskin.Skinner(mesh.points, mesh.joint_indices, mesh.joint_weights,
                            geom_bind_transform=mesh.geom_bind_transform, faces=mesh.faces)
        for name, meth, rule in (("lbs", "lbs", "largest_weight"), ("dqs", "dqs", "largest_weight"),
                                 ("dqs running_sum", "dqs", "running_sum"),
                                 ("cor", "cor", "largest_weight")):
            sk.skin(xf, meth, sign_reference=rule)  # warm-up (kernels, centers, buffers)
            t = float("inf")
            for _ in range(repeat):
                t0 = time.perf_counter()
                sk.skin(xf, meth, sign_reference=rule)
                t = min(t, time.perf_counter() - t0)
            row[f"{name} M pt-frames/s"] = len(mesh.points) * frames / t / 1e6
        rows.append(row)
    return rows


def bench_kernels(rounds=15, V=200_000, F=8, J=64, K=4):
    """The skinning kernel alone (no upload, preparation or readback): ``V`` random points, ``K``
    influences of ``J`` random rigid joints, ``F`` frames, one launch per method, best of
    ``rounds``; M point-frames per second. Run with ``DQSKIN_THREADS=1`` for one thread."""
    import warp as wp
    from scipy.spatial.transform import Rotation

    from dqskin.kernels import skin as K_

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(V, 3)).astype(np.float32)
    idx, w = rng.integers(0, J, (V, K)), rng.random((V, K)).astype(np.float32)
    xf = np.tile(np.eye(4), (F, J, 1, 1))
    xf[..., :3, :3] = Rotation.random(F * J, random_state=1).as_matrix().reshape(F, J, 3, 3)
    sk = dqskin.Skinner(pts, idx, w, faces=rng.integers(0, V, (1000, 3)),
                        cor=dqskin.CorOptions(cluster=None))
    prep, frames, _ = sk._prepare(xf)
    out = wp.empty((frames, V), dtype=wp.vec3, device=sk.device)
    cases = {"lbs": (K_.LBS, "largest_weight"), "dqs": (K_.DQS, "largest_weight"),
             "dqs running_sum": (K_.DQS, "running_sum"), "cor": (K_.COR, "largest_weight")}
    infs = {name: sk._influences(code, rule) for name, (code, rule) in cases.items()}
    best = dict.fromkeys(cases, float("inf"))
    for _ in range(rounds):
        for name, (code, _rule) in cases.items():
            t0 = time.perf_counter()
            K_.skin_points(method=code, points=sk._points, influences=infs[name],
                           joints=prep["joints"], rigid=True, out=out, device=sk.device)
            best[name] = min(best[name], time.perf_counter() - t0)
    return {name: V * frames / t / 1e6 for name, t in best.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--exact", action="store_true",
                    help="also time cluster=None (the tube takes ~30 s) and print the default's "
                         "center and skinned-point errors against it")
    ap.add_argument("--kernels", action="store_true",
                    help="only the skinning kernels, no meshes (DQSKIN_THREADS=1: one thread)")
    ap.add_argument("--json")
    args = ap.parse_args()
    if args.kernels:
        print("kernel M point-frames/s: " + ", ".join(f"{k} {v:.1f}"
                                                      for k, v in bench_kernels().items()))
        return
    os.environ["DQSKIN_CACHE_DIR"] = tempfile.mkdtemp(prefix="bench_cor-")  # all misses
    rows = bench(args.frames, args.repeat, args.exact)
    for r in rows:
        print(f"{r['mesh']}: {r['vertices']} vertices, {r['faces']} triangles, "
              f"{r['joints']} joints, K={r['influences']}, {r['with_center']} with a center")
        print(f"  precompute {r['precompute_s']:.3f} s (first call "
              f"{r['precompute_first_s']:.3f} s), cache hit {r['cache_hit_s'] * 1e3:.1f} ms, "
              f"subdivide=0.1 {r['precompute_subdivided_s']:.3f} s"
              + (f", exact {r['precompute_exact_s']:.2f} s" if "precompute_exact_s" in r else ""))
        if "center_error" in r:
            print(f"  default vs exact: centers {r['center_error']:.2e} "
                  f"({r['center_error'] / r['size']:.1e} of the {r['size']:.3g} diagonal), "
                  f"skinned points {r['point_error']:.2e} "
                  f"({r['point_error'] / r['size']:.1e}); exact / default time "
                  f"{r['precompute_exact_s'] / r['precompute_s']:.1f}x")
        print("  runtime M point-frames/s: " + ", ".join(
            f"{k.split(' M ')[0]} {v:.1f}" for k, v in r.items() if k.endswith("M pt-frames/s")))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        machine = platform.processor() or platform.machine()
        Path(args.json).write_text(json.dumps(dict(machine=machine, frames=args.frames,
                                                   rows=rows), indent=1))


if __name__ == "__main__":
    main()
