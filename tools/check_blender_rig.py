"""Does Blender's USD importer skin a ``dqskin rig`` as dqskin does?

Run with a Python that has ``bpy`` (Blender as a module, from PyPI, in its own virtual
environment: never dqskin's), on a rig and dqskin's skinning of it::

    dqskin rig body.obj --skeleton walk.bvh --out /tmp/rig.usda
    dqskin skin /tmp/rig.usda --method lbs --out /tmp/lbs.npz
    /tmp/bpyenv/bin/python tools/check_blender_rig.py /tmp/rig.usda /tmp/lbs.npz

Imports the rig (``bpy.ops.wm.usd_import``: an armature with the SkelAnimation as an action, the
mesh with an Armature modifier and vertex groups from the joint weights), evaluates every mesh
at the ``.npz``'s times (as frames) and compares its world-space vertices with dqskin's points
(in each mesh prim's own space). Blender converts the axes (Y-up to Z-up) and may scale by the
stage's metersPerUnit, and a rig's placement (``/Root/Placement``) lies between the two spaces,
so one affine map from dqskin's points to Blender's is fitted on the first frame and applied to
every frame (the map is printed); the distances left are the skinning's. A placement animated
over time is not absorbed by one map: check still ones. Prints the worst and mean distance in %
of the mesh's height, and how far the mesh moves (so a rig Blender leaves still cannot pass);
exits 1 when the worst exceeds ``--tolerance`` % (default 0.1).

Blender 5.0.1 skins with LBS whatever ``skinningMethod`` says, so compare with
``--method lbs``.
"""

import argparse
import sys

import bpy
import numpy as np


def blender_points(rig, frames):
    """{mesh name: (F, V, 3) world-space vertices} of the imported rig at ``frames``."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=str(rig))
    scene = bpy.context.scene
    meshes = [o for o in scene.objects if o.type == "MESH"]
    out = {o.name: [] for o in meshes}
    for f in frames:
        whole = int(np.floor(f))
        scene.frame_set(whole, subframe=float(f - whole))
        graph = bpy.context.evaluated_depsgraph_get()
        for o in meshes:
            ev = o.evaluated_get(graph)
            co = np.empty(len(ev.data.vertices) * 3, np.float32)
            ev.data.vertices.foreach_get("co", co)
            m = np.array(ev.matrix_world, np.float64)
            p = co.reshape(-1, 3).astype(np.float64)
            out[o.name].append(p @ m[:3, :3].T + m[:3, 3])
    modifiers = sorted({m.type for o in meshes for m in o.modifiers})
    return {k: np.stack(v) for k, v in out.items()}, modifiers


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("rig")
    ap.add_argument("npz", help="dqskin skin RIG --out X.npz")
    ap.add_argument("--tolerance", type=float, default=0.1, help="% of the height")
    args = ap.parse_args(argv)
    data = np.load(args.npz)
    times = data["times"]
    ours = {str(n).rsplit("/", 1)[-1]: data[f"points_{i}"].astype(np.float64)
            for i, n in enumerate(data["names"])}
    theirs, modifiers = blender_points(args.rig, times)
    ok = True
    for name, mine in ours.items():
        got = theirs.get(name)
        if got is None or got.shape != mine.shape:
            print(f"{name}: not in Blender's import with the same vertex count "
                  f"({ {k: v.shape for k, v in theirs.items()} })")
            return 1
        # one affine map (axes, units) from dqskin's first frame to Blender's
        a = np.c_[mine[0], np.ones(len(mine[0]))]
        fit, *_ = np.linalg.lstsq(a, got[0], rcond=None)
        mapped = np.concatenate([mine, np.ones(mine.shape[:2] + (1,))], -1) @ fit
        height = float(np.ptp(got[0], axis=0).max())
        d = np.linalg.norm(mapped - got, axis=-1) / height * 100
        moves = float(np.linalg.norm(got - got[:1], axis=-1).max()) / height * 100
        print(f"Blender {bpy.app.version_string}, modifiers {modifiers}: {name}, "
              f"{len(times)} frames × {mine.shape[1]} vertices: worst {d.max():.4f}%, mean "
              f"{d.mean():.4f}% of the height (the mesh moves up to {moves:.1f}%)")
        print(f"  fitted map (dqskin → Blender world, rows): "
              f"{np.round(fit[:3].T, 4).tolist()}, offset {np.round(fit[3], 4).tolist()}")
        ok &= bool(d.max() <= args.tolerance and moves > 1.0)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
