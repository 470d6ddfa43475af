"""Benchmark ``dqskin compare`` on a ~35k-vertex character.

    python tools/bench_compare.py [OUT_DIR] [--methods lbs,dqs,blend] [--repeat N] [--full]

The bundled humanoid (assets/humanoid.usda, 5.3k vertices) is midpoint-subdivided -- the body
twice, the limbs once; new vertices take the average of their edge's weights, cut to the 4
largest -- to 35.6k vertices, then compared: 10 frames × 3 methods (LBS, DQS, blend) × 3 views,
512 px, 2× supersampled, the rig sweeps and the animated viewer (48 frames). Prints the wall time
of ``run_compare`` and its parts, and the size of report.html. The target (issue 13) is under
30 s on the 2-core development machine; run it on a quiet machine (other processes change it).
"""

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

import dqskin
from dqskin.report.compare import run_compare

ROOT = Path(__file__).resolve().parents[1]


def subdivide(mesh):
    """One midpoint subdivision of a skinned mesh, weights averaged along each split edge."""
    V, J = len(mesh.points), int(mesh.joint_indices.max()) + 1
    dense = np.zeros((V, J))
    np.add.at(dense, (np.arange(V)[:, None], mesh.joint_indices), mesh.joint_weights)
    edges = np.unique(np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]],
                                              mesh.faces[:, [2, 0]]]), 1), axis=0)
    # trimesh appends one midpoint per unique edge after the original vertices; match them to
    # edges by position (its edge order is its own)
    points, faces = trimesh.remesh.subdivide(mesh.points, mesh.faces)[:2]
    mid = 0.5 * (mesh.points[edges[:, 0]] + mesh.points[edges[:, 1]])
    _, k = cKDTree(mid).query(points[V:])
    w = np.concatenate([dense, 0.5 * (dense[edges[k, 0]] + dense[edges[k, 1]])])
    idx = np.argsort(-w, 1)[:, :4]
    wts = np.take_along_axis(w, idx, 1)
    wts /= wts.sum(1, keepdims=True)
    return replace(mesh, points=points.astype(np.float32), faces=faces.astype(np.int32),
                   joint_indices=idx.astype(np.int32), joint_weights=wts.astype(np.float32),
                   normals=None, normal_vertex=None, uvs=None, face_vertex_counts=None,
                   face_vertex_indices=None)


def character():
    """The humanoid subdivided to ~35k vertices (a dqskin.Scene)."""
    scene = dqskin.load(ROOT / "assets" / "humanoid.usda")
    meshes = [subdivide(subdivide(m)) if m.name.endswith("Body") else subdivide(m)
              for m in scene.meshes]
    return replace(scene, meshes=meshes)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/bench_compare")
    ap.add_argument("--methods", default="lbs,dqs,blend")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--full", action="store_true", help="full super-sampling (not adaptive)")
    args = ap.parse_args()
    scene = character()
    print("vertices", sum(len(m.points) for m in scene.meshes),
          "faces", sum(len(m.faces) for m in scene.meshes))
    for _ in range(args.repeat):
        t, cpu = time.perf_counter(), time.process_time()
        r = run_compare(scene, args.out, methods=args.methods.split(","), force=True,
                        adaptive=not args.full)
        size = (Path(args.out) / "report.html").stat().st_size
        wall, cpu = time.perf_counter() - t, time.process_time() - cpu
        # CPU seconds over all threads: on an idle 2-core machine the wall time lies between
        # cpu / 2 (everything parallel) and cpu; on a busy one the wall time says little.
        print(f"run_compare: {wall:.1f} s wall, {cpu:.1f} s CPU ({cpu / wall:.2f} cores busy)",
              {k: round(v, 2) for k, v in r["timing_s"].items()},
              f"report.html {size / 1e6:.1f} MB (viewer data {r['viewer']['data_bytes'] / 1e6:.1f}"
              " MB before base64)")


if __name__ == "__main__":
    main()
