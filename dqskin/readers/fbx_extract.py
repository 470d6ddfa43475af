"""The one place that calls ufbx: run as a script in a process of its own by :mod:`.fbx`.

``python fbx_extract.py FILE CLIP MAX_BYTES`` loads ``FILE`` with ufbx and writes to stdout
an ``.npz`` (no pickles) of plain arrays and one JSON record (``meta``): the nodes that drive
meshes, their world transforms at the file's stored pose and at every whole frame of the chosen
animation stack (``CLIP``: a name, an index, or ``-`` for the first; ``seconds``: the frames'
times), every mesh's geometry, skin clusters and blend-shape weights, and the seconds each step
took (``timing_s``). ``python fbx_extract.py FILE INDEX MAX_BYTES at`` evaluates stack number
``INDEX`` at the times (seconds, raw float64) read from stdin instead of its frames, and writes
only the animated values (``seconds``, ``world``, blend-shape weights). Transforms of more than
``MAX_BYTES`` are refused before they are evaluated. Errors: one line on stderr and exit
status 2.

The ufbx bindings are young: a Python wrapper of a ufbx object that is fetched a second time
(a node's ``parent`` after the node itself, say) crashes the process when one of the two
wrappers is freed. So every wrapper fetched here is kept alive (:data:`_KEEP`) until the process
ends with :func:`os._exit`, which frees nothing. A crash still takes down only this process,
which :mod:`.fbx` reports as bad input. Imports NumPy and ufbx only (not dqskin): it starts fast.
"""

import io
import json
import math
import os
import sys
import time

import numpy as np

_KEEP: list = []
"""Every ufbx wrapper fetched, alive to the end of the process (see the module docstring)."""

_BAD = 2


def _k(obj):
    """Keep ``obj`` alive and return it."""
    _KEEP.append(obj)
    return obj


def _array(values, dtype, width=None):
    """A ufbx list as a NumPy array: through the buffer protocol where the list has it, else
    element by element."""
    try:
        a = np.array(memoryview(values), dtype=dtype)
    except TypeError:
        a = np.array([tuple(v) if width else v for v in values], dtype=dtype)
    if width is not None:
        a = a.reshape(-1, width)
    return a


def _matrix(m):
    """ufbx Matrix (four columns) → (4, 4) float64, column vectors."""
    out = np.eye(4)
    for c in range(4):
        out[:3, c] = tuple(m[c])
    return out


def _pick_stack(stacks, clip):
    """Index of the animation stack ``clip`` names (``-``: the first, -1 when there is none)."""
    names = [_k(stacks[i]).name for i in range(len(stacks))]
    if clip == "-":
        return (0 if names else -1), names
    if clip in names:
        return names.index(clip), names
    if clip.lstrip("-").isdigit() and -len(names) <= int(clip) < len(names):
        return int(clip) % len(names), names
    raise LookupError(f"no animation stack {clip!r}; stacks: {names}")


MAX_FRAMES = 1_000_000
"""Longest animation stack read, in frames."""


class LimitExceeded(Exception):
    """The file asks for more than this reader takes (:data:`MAX_FRAMES`)."""


class LimitBytes(Exception):
    """The evaluated transforms would take more bytes than the reader was allowed: the message
    is the count and what asks for them."""


def _frames(name, begin, end, fps):
    """Whole frames at ``fps`` from ``begin`` to ``end`` seconds (at least one)."""
    f0 = math.ceil(begin * fps - 1e-6)
    f1 = max(f0, math.floor(end * fps + 1e-6))
    if f1 - f0 >= MAX_FRAMES:
        raise LimitExceeded(f"animation stack {name!r} spans {f1 - f0 + 1} frames at {fps:g} fps "
                         f"(more than {MAX_FRAMES})")
    return np.arange(f0, f1 + 1, dtype=np.float64)


def extract(path, clip, at=None, max_bytes=None):
    start = time.perf_counter()
    import ufbx  # type: ignore[import-untyped]

    imported = time.perf_counter()
    scene = _k(ufbx.load_file(path))
    loaded = time.perf_counter()
    settings = _k(scene.settings)
    axes = settings.axes
    fps = float(settings.frames_per_second) or 24.0
    nodes = _k(scene.nodes)
    node_list = [_k(nodes[i]) for i in range(len(nodes))]
    ids = {n.typed_id: i for i, n in enumerate(node_list)}
    parents, names, depth = [], [], []
    for n in node_list:
        p = n.parent
        _k(p)
        parents.append(-1 if p is None else ids[p.typed_id])
        names.append(n.name)
        depth.append(n.node_depth)
    rest_world = np.stack([_matrix(n.node_to_world) for n in node_list]) if node_list \
        else np.zeros((0, 4, 4))
    arrays = {"rest_world": rest_world}
    meshes_meta: list[dict] = []
    needed: set[int] = set()
    meshes = _k(scene.meshes)
    for mi in range(len(meshes)):
        mesh = _k(meshes[mi])
        instances = _k(mesh.instances)
        if len(instances) == 0:
            continue
        inst = _k(instances[0])
        k = len(meshes_meta)
        key = f"m{k}/"
        arrays[key + "points"] = _array(mesh.vertices, np.float64, 3)
        arrays[key + "faces"] = _array(mesh.faces, np.int64, 2)
        arrays[key + "indices"] = _array(mesh.vertex_indices, np.int64)
        normal = _k(mesh.vertex_normal)
        if normal.exists:
            arrays[key + "normals"] = _array(normal.values, np.float64, 3)
            arrays[key + "normals_index"] = _array(normal.indices, np.int64)
        uv = _k(mesh.vertex_uv)
        if uv.exists:
            arrays[key + "uvs"] = _array(uv.values, np.float64, 2)
            arrays[key + "uvs_index"] = _array(uv.indices, np.int64)
        node = ids[inst.typed_id]
        arrays[key + "geometry_to_world"] = _matrix(inst.geometry_to_world)
        meta = {"name": inst.name, "node": node, "method": None, "channels": 0,
                "visible": bool(inst.visible)}
        skins = _k(mesh.skin_deformers)
        if len(skins):
            skin = _k(skins[0])
            meta["method"] = int(skin.skinning_method)
            meta["skins"] = len(skins)
            clusters = _k(skin.clusters)
            bones, to_bone = [], []
            for ci in range(len(clusters)):
                c = _k(clusters[ci])
                b = c.bone_node
                _k(b)
                bones.append(-1 if b is None else ids[b.typed_id])
                to_bone.append(_matrix(c.geometry_to_bone))
            arrays[key + "bones"] = np.asarray(bones, np.int64)
            arrays[key + "geometry_to_bone"] = np.asarray(to_bone, np.float64).reshape(-1, 4, 4)
            arrays[key + "skin_vertices"] = _array(skin.vertices, np.float64, 3)
            arrays[key + "skin_weights"] = _array(skin.weights, np.float64, 2)
            needed.update(b for b in bones if b >= 0)
        else:
            needed.add(node)
        blends = _k(mesh.blend_deformers)
        shapes = []
        for bi in range(len(blends)):
            channels = _k(_k(blends[bi]).channels)
            for ci in range(len(channels)):
                keyframes = _k(_k(channels[ci]).keyframes)
                for ki in range(len(keyframes)):
                    shape = _k(_k(keyframes[ki]).shape)
                    offsets = np.zeros_like(arrays[key + "points"])
                    index = _array(_k(shape.offset_vertices), np.int64)
                    offsets[index] = _array(_k(shape.position_offsets), np.float64, 3)
                    shapes.append(offsets)
        if shapes:
            arrays[key + "shape_offsets"] = np.stack(shapes)
        meta["shapes"] = len(shapes)
        meshes_meta.append(meta)
    # the nodes the meshes need, with their ancestors (not the scene root unless it is a bone)
    for j in list(needed):
        p = parents[j]
        while p >= 0 and parents[p] >= 0 and p not in needed:
            needed.add(p)
            p = parents[p]
    joints = sorted(needed, key=lambda j: (depth[j], j))
    stacks = _k(scene.anim_stacks)
    if at is None:
        which, clips = _pick_stack(stacks, clip)
    else:  # (an index the reader resolved)
        which, clips = int(clip), [_k(stacks[i]).name for i in range(len(stacks))]
        arrays = {}
    read = time.perf_counter()
    if which >= 0:
        stack = _k(stacks[which])
        anim = _k(stack.anim)
        seconds = (_frames(stack.name, stack.time_begin, stack.time_end, fps) / fps
                   if at is None else at)
        need = 128 * len(seconds) * len(joints)
        if max_bytes is not None and need > max_bytes:
            raise LimitBytes(f"{need} animation stack {stack.name!r}: {len(seconds)} times of "
                             f"{len(joints)} nodes' transforms")
        world = np.empty((len(seconds), len(joints), 4, 4))
        weights: list[list] = [[] for _ in meshes_meta]
        for f, second in enumerate(seconds):
            ev = _k(ufbx.evaluate_scene(scene, anim, float(second)))
            ev_nodes = _k(ev.nodes)
            for j, node in enumerate(joints):
                world[f, j] = _matrix(_k(ev_nodes[node]).node_to_world)
            if any(m["shapes"] for m in meshes_meta):
                ev_meshes = _k(ev.meshes)
                _shape_weights(ev_meshes, len(meshes), weights)
        arrays["seconds"] = seconds
        arrays["world"] = world
        for k, w in enumerate(weights):
            if meshes_meta[k]["shapes"]:
                arrays[f"m{k}/shape_weights"] = np.asarray(w, np.float64)
    done = time.perf_counter()
    timing = {"import": imported - start, "load": loaded - imported, "meshes": read - loaded,
              "frames": done - read}
    meta = {"fps": fps, "up": int(axes.up), "unit": float(settings.unit_meters),
            "timing_s": timing, "stack": which,
            "clips": clips, "clip": clips[which] if which >= 0 else None, "joints": joints,
            "names": names, "parents": parents, "meshes": meshes_meta}
    arrays["meta"] = np.array(json.dumps(meta))
    return arrays


def _shape_weights(ev_meshes, count, weights):
    """Append each mesh's effective blend-shape weights (one per in-between keyframe, in the
    order of the offsets) at the evaluated time."""
    k = -1
    for mi in range(count):
        mesh = _k(ev_meshes[mi])
        if len(_k(mesh.instances)) == 0:
            continue
        k += 1
        row: list[float] = []
        blends = _k(mesh.blend_deformers)
        for bi in range(len(blends)):
            channels = _k(_k(blends[bi]).channels)
            for ci in range(len(channels)):
                keyframes = _k(_k(channels[ci]).keyframes)
                row.extend(_k(keyframes[ki]).effective_weight for ki in range(len(keyframes)))
        weights[k].append(row)


def main(argv):
    at = argv[4:] == ["at"]
    if len(argv) != (5 if at else 4):
        sys.stderr.write("usage: fbx_extract.py FILE CLIP MAX_BYTES [at]\n")
        return _BAD
    try:
        seconds = np.frombuffer(sys.stdin.buffer.read(), np.float64) if at else None
        arrays = extract(argv[1], argv[2], seconds, int(argv[3]))
    except MemoryError:
        sys.stderr.write("out of memory\n")
        return _BAD
    except Exception as exc:  # ufbx's errors, and anything the file's data breaks here
        text = " ".join(str(exc).split()) or type(exc).__name__
        sys.stderr.write(f"{type(exc).__name__}: {text}\n"[:2000])
        return _BAD
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    sys.stdout.buffer.write(buf.getvalue())
    sys.stdout.buffer.flush()
    return 0


if __name__ == "__main__":
    status = main(sys.argv)
    sys.stderr.flush()
    os._exit(status)  # frees nothing: no wrapper of ufbx's is ever deallocated
