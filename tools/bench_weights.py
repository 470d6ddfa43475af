"""Automatic-weights benchmark: speed on a ~35k-vertex mesh, and accuracy against the artists'
weights on the real characters (the figures of issue 14, beside Blender 5.0's).

    python tools/bench_weights.py [--repeat 3] [--no-accuracy] [--no-speed] [--blender PYTHON]

Speed (target: under 10 s for ~35k vertices and ~30 joints): bone heat without the cache
(:func:`dqskin.autoweights.bone_heat_weights`), best of ``--repeat`` runs after one warm-up (Warp
kernel load), with the time of each phase, on

* ``capsules``: a body of capsules around every bone of the CMU capture 131_01 (31 joints), in
  its rest pose, subdivided to ~35k vertices;
* ``cesiumman-x4``: CesiumMan's mesh (welded: one closed surface) subdivided twice (~37k
  vertices), on its 19 skin joints.

Accuracy: each character's artist weights (CesiumMan, RiggedFigure, greenman) replaced by
automatic ones (:func:`dqskin.rigging.replace_weights`) or by nearest-bone rigid weights, both
skinned with LBS under the character's first clip (greenman: "2_move", its first is a still
pose) at 24 frames per second; the error is the
distance to the artist's skinned points in % of the rest mesh's **vertical height** (its extent
along the up axis of its bind pose: Z for CesiumMan and RiggedFigure, Y for greenman): the mean
and the 95th percentile over the vertices, at the worst frame. Blender 5.0.1's best
configuration (issue 31: its bone heat with default bone tails or with bones pointed at their
children, whichever is closer): CesiumMan 0.58% / 1.82%, RiggedFigure 0.27% / 1.22%; no figure
for greenman.

Blender (``--blender PYTHON``, a Python with the ``bpy`` module, e.g. ``bpy`` from PyPI in its own
virtual environment): the capsule body (12×12 capsules) and the CMU capture go through Blender's
own BVH and OBJ importers and "Parent with Automatic Weights"; its weights (normalized, as its
Armature modifier deforms) and dqskin's are both skinned with LBS over the whole capture, and the
distance between the two is reported as above (mean, 95th percentile, max; worst frame).
"""

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "assets"
sys.path.insert(0, str(ROOT / "tests"))  # the capsule body of the weight tests

BLENDER = {"CesiumMan": (0.58, 1.82), "RiggedFigure": (0.27, 1.22)}
"""Blender 5.0.1's best (mean, 95th percentile), % of vertical height (issue 31)."""

ACCURACY = [("CesiumMan", "khronos-gltf/CesiumMan/CesiumMan.glb", 2, None),
            ("RiggedFigure", "khronos-gltf/RiggedFigure/RiggedFigure.glb", 2, None),
            ("greenman", "raylib-gltf/greenman.glb", 1, "2_move")]
"""(name, file under ../shared/assets, vertical axis of the bind pose, clip: None the first)."""


def capsule_mesh():
    from test_autoweights import capsule_body

    from dqskin.autoweights import bone_segments
    from dqskin.readers import bvh
    motion = bvh.read_bvh(SHARED / "cmu-mocap" / "131_01.bvh")
    skel = motion.skeleton()
    pts, faces = capsule_body(skel, motion.end_sites, count=(16, 16), subdivide=1)
    return pts, faces, bone_segments(skel, end_sites=motion.end_sites), skel.joint_count


def cesium_mesh():
    import trimesh

    from dqskin import readers
    from dqskin.autoweights import bone_segments
    scene = readers.load(SHARED / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb")
    m = scene.meshes[0]
    skel = scene.skeletons[m.skeleton]
    g = m.geom_bind_transform
    t = trimesh.Trimesh(np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3], m.faces)
    t.merge_vertices()
    t = t.subdivide().subdivide()
    used = np.unique(np.asarray(m.joint_indices)[np.asarray(m.joint_weights) > 0])
    return (np.asarray(t.vertices), np.asarray(t.faces), bone_segments(skel, joints=used),
            skel.joint_count)


def speed(repeat):
    from dqskin.autoweights import bone_heat_weights
    rows = []
    for name, make in (("capsules", capsule_mesh), ("cesiumman-x4", cesium_mesh)):
        pts, faces, (heads, tails, owners), J = make()
        bone_heat_weights(pts, faces, heads, tails, owners, J)  # warm-up (kernel load)
        best, phases = None, None
        for _ in range(repeat):
            timings = {}
            t0 = time.perf_counter()
            bone_heat_weights(pts, faces, heads, tails, owners, J, timings=timings)
            dt = time.perf_counter() - t0
            if best is None or dt < best:
                best, phases = dt, timings
        rows.append(name)
        parts = ", ".join(f"{k} {v:.2f}" for k, v in phases.items())
        print(f"{name}: {len(pts)} vertices, {len(faces)} triangles, "
              f"{len(np.unique(owners))} joints, {len(heads)} bone segments: {best:.2f} s "
              f"({parts})")
    return rows


def nearest_bone(scene):
    """The scene with every vertex rigidly on its nearest bone segment (over the skin's
    joints)."""
    from dqskin.autoweights import bone_segments
    meshes = []
    for m in scene.meshes:
        skel = scene.skeletons[m.skeleton]
        used = np.unique(np.asarray(m.joint_indices)[np.asarray(m.joint_weights) > 0])
        h, t, owner = bone_segments(skel, joints=used)
        g = m.geom_bind_transform
        p = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
        d = t - h
        u = np.clip(np.einsum("vbk,bk->vb", p[:, None] - h, d)
                    / np.maximum((d * d).sum(1), 1e-30), 0, 1)
        dist = np.linalg.norm(p[:, None] - (h + u[..., None] * d), axis=2)
        j = owner[dist.argmin(1)][:, None].astype(np.int32)
        meshes.append(dataclasses.replace(m, joint_indices=j,
                                          joint_weights=np.ones(j.shape, np.float32)))
    return dataclasses.replace(scene, meshes=meshes, _skinners={})


def accuracy():
    from dqskin import readers
    from dqskin.metrics import character_height
    from dqskin.rigging import replace_weights, skinned_difference
    for name, path, up, clip in ACCURACY:
        scene = readers.load(SHARED / path, clip=clip)
        t0 = time.perf_counter()
        auto = replace_weights(scene, "auto", cache=False)
        dt = time.perf_counter() - t0
        frames = np.arange(scene.times[0], scene.times[-1] + 1e-9, 1 / 24)  # as Blender plays it
        for label, other in (("automatic", auto), ("nearest bone", nearest_bone(scene))):
            for mesh, (mean, p95) in skinned_difference(scene, other, frames).items():
                m = scene.mesh(mesh)
                g = m.geom_bind_transform
                rest = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
                k = character_height(rest) / np.ptp(rest[:, up])  # largest → vertical
                extra = f" (weights {dt:.2f} s)" if label == "automatic" else ""
                blender = ("; Blender's best " + "% / ".join(map(str, BLENDER[name])) + "%"
                           if name in BLENDER else "")
                print(f"{name} {label} ({mesh}): mean {k * mean:.3f}%, 95th percentile "
                      f"{k * p95:.3f}% of vertical height at the worst of {len(frames)} frames "
                      f"(24 fps){blender}{extra}")


BLENDER_SCRIPT = """
import sys
import bpy
import numpy as np
bvh, obj, out = sys.argv[-3:]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_anim.bvh(filepath=bvh, rotate_mode="NATIVE")
arm = [o for o in bpy.context.scene.objects if o.type == "ARMATURE"][0]
bpy.ops.wm.obj_import(filepath=obj)
mesh = [o for o in bpy.context.scene.objects if o.type == "MESH"][0]
for o in bpy.context.scene.objects:
    o.select_set(False)
mesh.select_set(True)
arm.select_set(True)
bpy.context.view_layer.objects.active = arm
bpy.ops.object.parent_set(type="ARMATURE_AUTO")
V, K = len(mesh.data.vertices), 8
idx, w = np.zeros((V, K), np.int64), np.zeros((V, K), np.float32)
for v in mesh.data.vertices:
    for k, (wt, g) in enumerate(sorted(((g.weight, g.group) for g in v.groups), reverse=True)[:K]):
        idx[v.index, k], w[v.index, k] = g, wt
co = np.array([tuple(v.co) for v in mesh.data.vertices])
np.savez(out, joint_indices=idx, joint_weights=w, co=co,
         joint_names=np.array([g.name for g in mesh.vertex_groups]))
"""


def blender(python):
    """dqskin's automatic weights against Blender's on the capsule body under the CMU capture."""
    import subprocess
    import tempfile

    import trimesh
    from test_autoweights import capsule_body

    from dqskin.readers import bvh
    from dqskin.rigging import rig_mesh
    src = SHARED / "cmu-mocap" / "131_01.bvh"
    motion = bvh.read_bvh(src)
    pts, faces = capsule_body(motion.skeleton(), motion.end_sites)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        trimesh.Trimesh(pts, faces, process=False).export(tmp / "body.obj")
        (tmp / "weights.py").write_text(BLENDER_SCRIPT)
        t0 = time.perf_counter()
        subprocess.run([python, str(tmp / "weights.py"), "--", str(src), str(tmp / "body.obj"),
                        str(tmp / "blender.npz")], check=True, capture_output=True)
        dt = time.perf_counter() - t0
        with np.load(tmp / "blender.npz") as z:
            if not np.allclose(z["co"], mesh_points(tmp / "body.obj"), atol=1e-5):
                raise SystemExit("Blender reordered the OBJ's vertices")
            w = z["joint_weights"] / np.maximum(z["joint_weights"].sum(1, keepdims=True), 1e-30)
            np.savez(tmp / "norm.npz", joint_indices=z["joint_indices"], joint_weights=w,
                     joint_names=z["joint_names"])
        t1 = time.perf_counter()
        ours = rig_mesh(tmp / "body.obj", src, as_is=True, cache=False)
        dt_ours = time.perf_counter() - t1
        theirs = rig_mesh(tmp / "body.obj", src, weights=tmp / "norm.npz", as_is=True)
        a = ours.skin(method="lbs").points["body"].astype(np.float64)
        b = theirs.skin(method="lbs").points["body"].astype(np.float64)
    err = np.linalg.norm(a - b, axis=-1) / np.ptp(pts, axis=0).max() * 100
    print(f"capsule body ({len(pts)} vertices) on 131_01, dqskin vs Blender automatic weights "
          f"over {len(a)} frames: mean {err.mean(1).max():.3f}%, 95th percentile "
          f"{np.percentile(err, 95, axis=1).max():.3f}%, max {err.max():.3f}% of height "
          f"(Blender incl. start-up {dt:.1f} s, dqskin {dt_ours:.2f} s)")


def mesh_points(path):
    from dqskin.readers.mesh import load_mesh
    return load_mesh(path)[0]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--blender", metavar="PYTHON", help="a Python with bpy: compare with Blender's "
                    "automatic weights")
    args = ap.parse_args(argv)
    import warp as wp
    wp.config.quiet = True
    if not args.no_speed:
        speed(args.repeat)
    if not args.no_accuracy:
        accuracy()
    if args.blender:
        blender(args.blender)


if __name__ == "__main__":
    main()
