"""Does Blender's USD importer show a value-clip cache as it shows the single-layer cache?

Run with a Python that has ``bpy`` (Blender as a module, from PyPI, in its own virtual
environment: never dqskin's), on two caches of the same bake::

    dqskin skin assets/humanoid.usda --out /tmp/single.usdc --no-clips
    dqskin skin assets/humanoid.usda --out /tmp/shot.usd --clips --chunk 7
    /tmp/bpyenv/bin/python tools/check_blender_clips.py /tmp/single.usdc /tmp/shot.usd

Imports each (``bpy.ops.wm.usd_import``: meshes with a Mesh Sequence Cache modifier), evaluates
every mesh at frames and sub-frames (6.5 and 6.9 lie between the first two chunks of 7 frames)
and prints the largest vertex difference between the two imports (0 when Blender reads the clips
as one animation), how far the meshes move, and how far the sub-frame is from the mean of its
neighbours (0: Blender interpolates linearly between samples).
"""

import sys

import bpy
import numpy as np

FRAMES = [0.0, 3.25, 6.0, 6.5, 6.9, 7.0, 13.5, 20.0, 34.75, 48.0]


def sample(path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=str(path))
    scene = bpy.context.scene
    meshes = sorted((o for o in scene.objects if o.type == "MESH"), key=lambda o: o.name)
    out = {}
    for f in FRAMES:
        whole = int(np.floor(f))
        scene.frame_set(whole, subframe=f - whole)
        graph = bpy.context.evaluated_depsgraph_get()
        for o in meshes:
            mesh = o.evaluated_get(graph).data
            co = np.empty(len(mesh.vertices) * 3, np.float32)
            mesh.vertices.foreach_get("co", co)
            out[(o.name, f)] = co.reshape(-1, 3)
    modifiers = sorted({m.type for o in meshes for m in o.modifiers})
    return out, [o.name for o in meshes], modifiers, (scene.frame_start, scene.frame_end)


def main(single, clips):
    a, names_a, mods_a, range_a = sample(single)
    b, names_b, mods_b, range_b = sample(clips)
    assert names_a == names_b, (names_a, names_b)
    worst = max(float(np.abs(a[k] - b[k]).max()) for k in a)
    motion = max(float(np.abs(a[(n, 20.0)] - a[(n, 0.0)]).max()) for n in names_a)
    sub = max(float(np.abs(a[(n, 6.5)] - 0.5 * (a[(n, 6.0)] + a[(n, 7.0)])).max())
              for n in names_a)
    print(f"Blender {bpy.app.version_string}: {len(names_a)} meshes, modifiers {mods_a} / "
          f"{mods_b}, frame range {range_a} / {range_b}")
    print(f"max |single - clips| over {len(a)} mesh-frames: {worst:.3g}; motion frame 0 -> 20: "
          f"{motion:.3g}; sub-frame 6.5 vs the mean of 6 and 7: {sub:.3g}")
    return 0 if worst == 0 and motion > 0 else 1


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
