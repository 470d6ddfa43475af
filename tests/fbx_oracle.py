"""ufbx's own skinning, the oracle of tests/test_fbx.py: ``python fbx_oracle.py FILE STACK
TIME...`` writes an ``.npz`` to stdout holding, per mesh with a skin deformer (first instance,
key ``m<k>``, in the order of ufbx's meshes), the skinned positions per vertex that
``ufbx.evaluate_scene(..., evaluate_skinning=True)`` gives at each time (seconds), shape
(T, V, 3), world space; ``rest``: the same at the file's stored pose (no stack evaluated);
``b<k>``: the same of each mesh with blend shapes and no skin deformer (ufbx's blended points,
placed in the world by the mesh's geometry-to-world transform).

Runs in its own process (ufbx's Python bindings crash when a wrapper of an object fetched twice
is freed): every wrapper is kept alive and the process ends with ``os._exit``.
"""

import io
import os
import sys

import numpy as np
import ufbx

KEEP = []


def k(x):
    KEEP.append(x)
    return x


def skinned(scene, blended=False):
    out = []
    meshes = k(scene.meshes)
    for i in range(len(meshes)):
        m = k(meshes[i])
        instances = k(m.instances)
        if len(instances) == 0 or (len(k(m.skin_deformers)) == 0) != blended \
                or (blended and len(k(m.blend_deformers)) == 0):
            continue
        pos = k(m.skinned_position)
        values = np.array(memoryview(k(pos.values)), np.float64).reshape(-1, 3)
        index = np.array(list(k(pos.indices)), np.int64)
        vi = np.array(list(k(m.vertex_indices)), np.int64)
        v = np.zeros((m.num_vertices, 3))
        v[vi] = values[index]
        if m.skinned_is_local:
            g = k(k(instances[0]).geometry_to_world)
            cols = np.array([tuple(k(g[c])) for c in range(4)])  # columns: x, y, z axes, origin
            v = v @ cols[:3] + cols[3]
        out.append(v)
    return out


def main():
    path, stack, times = sys.argv[1], int(sys.argv[2]), [float(t) for t in sys.argv[3:]]
    scene = k(ufbx.load_file(path, evaluate_skinning=True))
    anim = k(k(k(scene.anim_stacks)[stack]).anim)
    evaluated = [k(ufbx.evaluate_scene(scene, anim, t, evaluate_skinning=True)) for t in times]
    frames = [skinned(e) for e in evaluated]
    shaped = [skinned(e, blended=True) for e in evaluated]
    arrays = {"rest_" + str(i): v for i, v in enumerate(skinned(scene))}
    for i in range(len(frames[0]) if frames else 0):
        arrays["m" + str(i)] = np.stack([f[i] for f in frames])
    for i in range(len(shaped[0]) if shaped else 0):
        arrays["b" + str(i)] = np.stack([f[i] for f in shaped])
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    sys.stdout.buffer.write(buf.getvalue())
    sys.stdout.buffer.flush()


if __name__ == "__main__":
    main()
    os._exit(0)
