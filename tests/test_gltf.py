"""glTF loader against an independent float64 NumPy oracle of the glTF 2.0 skinning equation.

The oracle reads accessors itself (pygltflib for the JSON, NumPy for the bytes), composes node
transforms recursively from TRS or matrices, samples channels with its own LINEAR (lerp / slerp
from the spec's formula), STEP and CUBICSPLINE (hand-written Hermite) code, and skins with
``v' = Σ w · global(joint) · IBM · v`` using sum-normalized weights.
"""

import base64
import copy
import functools
import json
import math
import re
import signal
import struct
import warnings
from contextlib import contextmanager
from urllib.parse import unquote

import numpy as np
import pygltflib as gl
import pytest

from dqskin.readers.gltf import load_gltf

ASSETS = ["khronos-gltf/RiggedSimple/RiggedSimple.glb",
          "khronos-gltf/RiggedFigure/RiggedFigure.glb",
          "khronos-gltf/CesiumMan/CesiumMan.glb",
          "khronos-gltf/SimpleSkin/SimpleSkin.gltf",
          "raylib-gltf/greenman.glb"]

# --------------------------------------------------------------------------------------------
# Independent oracle
# --------------------------------------------------------------------------------------------

_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
_DTYPE = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}


class Oracle:
    """The glTF skinning equation in float64, straight from the document."""

    def __init__(self, g, bufs=()):
        self.g, self.bufs = g, list(bufs)
        self.parent = {c: i for i, n in enumerate(g.nodes) for c in (n.children or [])}

    @classmethod
    def load(cls, path):
        g = gl.GLTF2().load(str(path))
        bufs = []
        for b in g.buffers:
            if b.uri is None:
                bufs.append(g.binary_blob())
            elif b.uri.startswith("data:"):
                bufs.append(base64.b64decode(b.uri.split(",", 1)[1]))
            else:
                bufs.append((path.parent / unquote(b.uri)).read_bytes())
        return cls(g, bufs)

    def read(self, index):
        a = self.g.accessors[index]
        assert a.sparse is None
        v = self.g.bufferViews[a.bufferView]
        n, dt = _WIDTH[a.type], np.dtype(_DTYPE[a.componentType])
        stride = v.byteStride or n * dt.itemsize
        raw = self.bufs[v.buffer][v.byteOffset or 0:(v.byteOffset or 0) + v.byteLength]
        x = np.array([np.frombuffer(raw, dt, n, (a.byteOffset or 0) + k * stride)
                      for k in range(a.count)], dtype=np.float64).reshape(a.count, n)
        if a.normalized:
            x = {5121: x / 255, 5123: x / 65535, 5120: np.maximum(x / 127, -1),
                 5122: np.maximum(x / 32767, -1)}[a.componentType]
        return x

    def channels(self, clip):
        if isinstance(clip, str):
            clip = [a.name or f"animation_{i}" for i, a in enumerate(self.g.animations)].index(clip)
        anim = self.g.animations[clip]
        out = {}
        for ch in anim.channels:
            if ch.target.path not in ("translation", "rotation", "scale"):
                continue
            s = anim.samplers[ch.sampler]
            out[(ch.target.node, ch.target.path)] = (self.read(s.input)[:, 0], self.read(s.output),
                                                     s.interpolation or "LINEAR")
        return out

    def key_times(self, clip):
        """Union of the input times of every channel of the clip (morph weights included)."""
        anim = self.g.animations[clip]
        return np.unique(np.concatenate([self.read(anim.samplers[c.sampler].input)[:, 0]
                                         for c in anim.channels]))

    def local(self, i, t, chans):
        node = self.g.nodes[i]
        if node.matrix is not None:
            return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T
        trs = {"translation": node.translation or [0, 0, 0],
               "rotation": node.rotation or [0, 0, 0, 1], "scale": node.scale or [1, 1, 1]}
        for path in trs:
            if (i, path) in chans:
                trs[path] = ref_sample(t, *chans[(i, path)], path == "rotation")
        m = np.eye(4)
        m[:3, :3] = quat_xyzw_matrix(trs["rotation"]) @ np.diag(trs["scale"])
        m[:3, 3] = trs["translation"]
        return m

    def global_(self, i, t, chans, memo=None):
        """Global transform of node ``i``: global(parent) · local, recursively."""
        memo = {} if memo is None else memo
        if i not in memo:
            m = self.local(i, t, chans)
            memo[i] = self.global_(self.parent[i], t, chans, memo) @ m if i in self.parent else m
        return memo[i]

    def skin(self, t, clip=0):
        """name → (V, 3) world points at time ``t`` (mesh naming as documented by load_gltf)."""
        chans = self.channels(clip) if self.g.animations else {}
        out, memo = {}, {}
        for i, node in enumerate(self.g.nodes):
            if node.mesh is None or node.skin is None:
                continue
            skin = self.g.skins[node.skin]
            if skin.inverseBindMatrices is None:
                ibm = np.tile(np.eye(4), (len(skin.joints), 1, 1))
            else:  # column-major MAT4
                ibm = self.read(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
            jm = np.stack([self.global_(j, t, chans, memo) @ ibm[k]
                           for k, j in enumerate(skin.joints)])
            prims = self.g.meshes[node.mesh].primitives
            for k, prim in enumerate(prims):
                p = self.read(prim.attributes.POSITION)
                js, ws, n = [], [], 0
                while getattr(prim.attributes, f"JOINTS_{n}", None) is not None:
                    js.append(self.read(getattr(prim.attributes, f"JOINTS_{n}")).astype(int))
                    ws.append(self.read(getattr(prim.attributes, f"WEIGHTS_{n}")))
                    n += 1
                jj, ww = np.concatenate(js, 1), np.concatenate(ws, 1)
                total = ww.sum(axis=1, keepdims=True)
                w = np.where(total > 0, ww / np.where(total > 0, total, 1), np.eye(ww.shape[1])[0])
                m = np.einsum("vk,vkij->vij", w, jm[jj])  # Σ_k w_k · jointMatrix[j_k]
                ph = np.concatenate([p, np.ones((len(p), 1))], axis=1)
                res = np.einsum("vij,vj->vi", m, ph)[:, :3]
                name = node.name or f"node{i}"
                out[name if len(prims) == 1 else f"{name}/primitive{k}"] = res
        return out


@functools.cache
def oracle_of(path):
    return Oracle.load(path)


def quat_xyzw_matrix(q):
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def ref_slerp(a, b, u):
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    d = float(a @ b)
    if d < 0:
        b, d = -b, -d
    if d > 1 - 1e-12:
        return a
    theta = math.acos(d)
    return (math.sin((1 - u) * theta) * a + math.sin(u * theta) * b) / math.sin(theta)


def ref_hermite(v0, b0, v1, a1, u, dt):
    """glTF CUBICSPLINE between keys: value v, out-tangent b, in-tangent a, interval dt."""
    return ((2 * u**3 - 3 * u**2 + 1) * v0 + (u**3 - 2 * u**2 + u) * dt * b0
            + (-2 * u**3 + 3 * u**2) * v1 + (u**3 - u**2) * dt * a1)


def ref_sample(t, keys, out, interp, rotation):
    vals = out[1::3] if interp == "CUBICSPLINE" else out
    if t <= keys[0]:
        return vals[0]
    if t >= keys[-1]:
        return vals[-1]
    i = max(k for k in range(len(keys)) if keys[k] <= t)
    if keys[i] == t or interp == "STEP":
        return vals[i]
    dt = keys[i + 1] - keys[i]
    u = (t - keys[i]) / dt
    if interp == "LINEAR" and rotation:
        return ref_slerp(vals[i], vals[i + 1], u)
    if interp == "LINEAR":
        return (1 - u) * vals[i] + u * vals[i + 1]
    p = ref_hermite(vals[i], out[3 * i + 2], vals[i + 1], out[3 * (i + 1)], u, dt)
    return p / np.linalg.norm(p) if rotation else p


def check_against_oracle(path, times, clip=0, method="lbs", *, device):
    scene = load_gltf(path, clip=clip)
    got = scene.skin(times, method=method, device=device).points
    oracle = oracle_of(path)
    want = [oracle.skin(t, clip) for t in times]
    assert sorted(got) == sorted(want[0])
    for name, pts in got.items():
        ref = np.stack([w[name] for w in want])
        size = np.linalg.norm(np.ptp(ref.reshape(-1, 3), axis=0))
        err = np.abs(pts - ref).max()
        assert err <= 1e-5 * size, f"{path.name} {name}: max error {err} for size {size}"
    return scene, got, want


def mid_times(keys, n=2):
    k = np.asarray(keys)
    if k.size < 2:
        return []
    idx = np.linspace(0, k.size - 2, n).astype(int)
    return list(0.37 * k[idx] + 0.63 * k[idx + 1])


# --------------------------------------------------------------------------------------------
# Real assets
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("asset", ASSETS)
def test_asset_matches_oracle(shared_assets, asset, device):
    path = shared_assets / asset
    oracle = oracle_of(path)
    keys = oracle.key_times(0)
    times = np.concatenate([keys, mid_times(keys), [keys[0] - 1.0, keys[-1] + 1.0]])
    scene, _, _ = check_against_oracle(path, times, device=device)
    np.testing.assert_array_equal(scene.times, keys)
    assert scene.time_codes_per_second == 1.0 and scene.up_axis == "Y"
    for skel in scene.skeletons:
        assert np.all(skel.parents < np.arange(skel.joint_count))
    skinned = [n for n in oracle.g.nodes if n.mesh is not None and n.skin is not None]
    assert len(scene.meshes) == len(skinned) == 1  # one single-primitive skinned mesh each
    m, prim = scene.meshes[0], oracle.g.meshes[skinned[0].mesh].primitives[0]
    assert m.points.dtype == np.float32 and m.faces.dtype == np.int32
    assert m.output_transforms is None and np.array_equal(m.geom_bind_transform, np.eye(4))
    np.testing.assert_array_equal(m.points, oracle.read(prim.attributes.POSITION))
    np.testing.assert_array_equal(m.faces.reshape(-1), oracle.read(prim.indices)[:, 0])
    for field, attr in (("normals", "NORMAL"), ("uvs", "TEXCOORD_0")):
        index = getattr(prim.attributes, attr)
        if index is None:
            assert getattr(m, field) is None
        else:
            np.testing.assert_array_equal(getattr(m, field), oracle.read(index))
    np.testing.assert_allclose(m.joint_weights.sum(axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("asset", ASSETS)
def test_asset_dqs_rigid_vertices(shared_assets, asset, device):
    """DQS runs; where one joint has all the weight it equals the rigid (LBS) oracle."""
    path = shared_assets / asset
    scene = load_gltf(path)
    times = scene.times[:: max(1, scene.times.size // 6)]
    dqs = scene.skin(times, method="dqs", device=device).points
    want = [oracle_of(path).skin(t) for t in times]
    for m in scene.meshes:
        single = np.sum(m.joint_weights > 0, axis=1) == 1
        ref = np.stack([w[m.name] for w in want])
        assert np.all(np.isfinite(dqs[m.name]))
        if single.any():
            size = np.linalg.norm(np.ptp(ref.reshape(-1, 3), axis=0))
            assert np.abs(dqs[m.name][:, single] - ref[:, single]).max() <= 1e-5 * size


def test_greenman_clips(shared_assets, device):
    path = shared_assets / "raylib-gltf/greenman.glb"
    oracle = oracle_of(path)
    names = [a.name for a in oracle.g.animations]
    assert len(names) == 4
    default = load_gltf(path)
    assert default.clips == names and default.clip == names[0]
    by_name, by_index = load_gltf(path, clip=names[2]), load_gltf(path, clip=2)
    assert by_name.clip == by_index.clip == names[2]
    np.testing.assert_array_equal(by_name.times, oracle.key_times(2))
    np.testing.assert_array_equal(
        by_name.skin(by_name.times, "lbs", device=device).points["1_body"],
        by_index.skin(by_index.times, "lbs", device=device).points["1_body"])
    keys = oracle.key_times(3)
    check_against_oracle(path, np.concatenate([keys[::3], mid_times(keys)]), clip=names[3],
                         device=device)
    for bad in ("nope", 4):
        with pytest.raises(ValueError, match=r"greenman\.glb.*available clips.*1_idle"):
            load_gltf(path, clip=bad)


# --------------------------------------------------------------------------------------------
# Synthetic files
# --------------------------------------------------------------------------------------------

FLOAT, UBYTE, SHORT, USHORT = 5126, 5121, 5122, 5123


class Doc:
    """A glTF document under construction: arrays become accessors in one buffer."""

    def __init__(self):
        self.g = gl.GLTF2(asset=gl.Asset(version="2.0"))
        self.blob = bytearray()

    def acc(self, array, kind, ctype=FLOAT, normalized=False):
        a = np.ascontiguousarray(array, dtype=_DTYPE[ctype])
        if kind == "MAT4":
            a = np.ascontiguousarray(a.transpose(0, 2, 1))  # glTF stores column-major
        self.blob += b"\0" * (-len(self.blob) % 4)
        self.g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(self.blob),
                                                byteLength=a.nbytes))
        self.blob += a.tobytes()
        count = a.shape[0]
        self.g.accessors.append(gl.Accessor(bufferView=len(self.g.bufferViews) - 1, count=count,
                                            componentType=ctype, type=kind,
                                            normalized=normalized or None))
        return len(self.g.accessors) - 1

    def save(self, path, how="glb"):
        data = bytes(self.blob)
        if how == "glb":
            self.g.buffers = [gl.Buffer(byteLength=len(data))]
            self.g.set_binary_blob(data)
            self.g.save_binary(str(path))
        else:
            if how == "embedded":
                uri = "data:application/octet-stream;base64," + base64.b64encode(data).decode()
            else:
                uri = path.stem + " data.bin"
                (path.parent / uri).write_bytes(data)
                uri = uri.replace(" ", "%20")
            self.g.buffers = [gl.Buffer(uri=uri, byteLength=len(data))]
            self.g.save_json(str(path))
        return path


def column_major(m):
    return [float(x) for x in np.asarray(m, dtype=np.float64).T.reshape(-1)]


def trs(t=(0, 0, 0), axis=(0, 0, 1), angle=0.0, s=(1, 1, 1)):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    q = np.append(axis * math.sin(angle / 2), math.cos(angle / 2))
    return dict(translation=[float(x) for x in t], rotation=[float(x) for x in q],
                scale=[float(x) for x in s])


def quats(angles, axis):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.asarray(angles, float)[:, None]
    return np.concatenate([axis * np.sin(a / 2), np.cos(a / 2)], axis=1)


def skin_arrays(rng, V, J, sets):
    """Random points, faces and 4·sets influences per vertex; rows 0-2 single-joint, row 3 zero."""
    pts = rng.uniform(-1, 1, (V, 3))
    joints = rng.integers(0, J, (V, 4 * sets))
    weights = rng.uniform(0, 2, (V, 4 * sets)) * (rng.random((V, 4 * sets)) < 0.7)
    weights[:3] = 0
    weights[:3, 1] = [0.5, 1.0, 3.0]  # unnormalized single influences
    weights[3] = 0
    faces = rng.integers(0, V, (V, 3))
    return pts, joints, weights, faces


def build_rig(path, how="glb", weights_ctype=FLOAT):
    """Two skins, non-joint animated and static ancestors, a matrix joint, mesh node transforms,
    8 influences (JOINTS_1), two primitives, LINEAR/STEP/CUBICSPLINE channels, two clips."""
    rng = np.random.default_rng(7)
    d = Doc()
    g = d.g
    head = [[0, -1, 0, 0.1], [1, 0, 0, 0.4], [0, 0, 1, 0], [0, 0, 0, 1]]
    grp = [[1, 0, 0, 0], [0, 0, -1, 0.5], [0, 1, 0, 0], [0, 0, 0, 1]]
    g.nodes = [
        gl.Node(name="mover", children=[1], **trs((0.3, 0.1, 0), (0, 1, 0), 0.2)),  # non-joint
        gl.Node(name="hips", children=[2, 4], **trs((0, 1, 0), (1, 0, 0), 0.1)),
        gl.Node(name="spine", children=[3], **trs((0, 0.5, 0), (0, 0, 1), 0.3)),
        gl.Node(name="head", matrix=column_major(head)),  # a static matrix joint
        gl.Node(name="leg", children=[5], **trs((0.2, -0.1, 0), (0, 1, 1), -0.4, (1, 1.2, 0.9))),
        gl.Node(name="foot", **trs((0, -0.6, 0.1), (1, 1, 0), 0.5)),
        gl.Node(name="body", mesh=0, skin=0, **trs((5, -2, 1), (1, 2, 3), 1.1, (2, 2, 2))),
        gl.Node(name="grp", children=[0], matrix=column_major(grp)),  # non-joint root
        gl.Node(name="prop", mesh=1, skin=1, **trs((1, 1, 1))),
    ]
    g.scenes = [gl.Scene(nodes=[7, 6, 8])]
    g.scene = 0
    skin0 = [4, 2, 1, 5, 3]
    rest = Oracle(g)  # the oracle's node composition on the in-memory document
    ibm0 = np.stack([np.linalg.inv(rest.global_(j, 0.0, {})) for j in skin0])
    ibm0[1, :3, 3] += [0.05, -0.02, 0.1]  # any invertible matrix is valid
    g.skins = [gl.Skin(joints=skin0, inverseBindMatrices=d.acc(ibm0, "MAT4"), name="main"),
               gl.Skin(joints=[5, 3])]  # no IBMs: identity
    prims = []
    for k in range(2):
        pts, jn, wt, faces = skin_arrays(rng, 12, len(skin0), 2)
        if weights_ctype == UBYTE:
            wt = np.round(wt / wt.max(axis=1, keepdims=True).clip(1e-9) * 255)
        attrs = gl.Attributes(POSITION=d.acc(pts, "VEC3"), NORMAL=d.acc(pts / np.linalg.norm(
            pts, axis=1, keepdims=True), "VEC3"), TEXCOORD_0=d.acc(pts[:, :2], "VEC2"))
        for s in range(2):
            setattr(attrs, f"JOINTS_{s}", d.acc(jn[:, 4 * s:4 * s + 4], "VEC4", UBYTE))
            setattr(attrs, f"WEIGHTS_{s}", d.acc(wt[:, 4 * s:4 * s + 4], "VEC4", weights_ctype,
                                                 normalized=weights_ctype != FLOAT))
        target = gl.Attributes(POSITION=d.acc(np.zeros_like(pts), "VEC3"))  # a null morph target
        prims.append(gl.Primitive(attributes=attrs, targets=[target],
                                  indices=d.acc(faces.reshape(-1), "SCALAR", USHORT)))
    pts, jn, wt, faces = skin_arrays(rng, 6, 2, 1)
    prop = gl.Primitive(attributes=gl.Attributes(POSITION=d.acc(pts, "VEC3"),
                                                 JOINTS_0=d.acc(jn, "VEC4", USHORT),
                                                 WEIGHTS_0=d.acc(wt, "VEC4")))
    g.meshes = [gl.Mesh(primitives=prims, weights=[0.0]), gl.Mesh(primitives=[prop])]

    def channel(anim, node, path, keys, values, interp="LINEAR", ctype=FLOAT):
        kind = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[values.shape[1]]
        anim.samplers.append(gl.AnimationSampler(input=d.acc(np.asarray(keys)[:, None], "SCALAR"),
                                                 output=d.acc(values, kind, ctype, ctype != FLOAT),
                                                 interpolation=interp))
        target = gl.AnimationChannelTarget(node=node, path=path)
        anim.channels.append(gl.AnimationChannel(sampler=len(anim.samplers) - 1, target=target))

    walk = gl.Animation(name="walk")
    channel(walk, 0, "translation", [0, 0.5, 1.0], np.array([[0, 0, 0], [0.5, 0.2, 0],
                                                             [1, 0, -0.3]]))
    # opposite-sign quaternion keys: slerp must take the short way
    channel(walk, 0, "rotation", [0.2, 1.3], quats([0.1, 2.9], (0, 1, 0)) * [[1], [-1]])
    channel(walk, 1, "rotation", [0, 0.4, 0.8, 1.6], quats([0, 0.5, -0.3, 0.9], (1, 0, 0)), "STEP")
    ck = [0.1, 0.6, 1.5]
    cv = np.stack([rng.normal(0, 0.5, (3, 4)), quats([0, 1.0, -0.6], (0, 0, 1)),
                   rng.normal(0, 0.5, (3, 4))], axis=1).reshape(-1, 4)  # (in, value, out) per key
    channel(walk, 2, "rotation", ck, cv, "CUBICSPLINE")
    channel(walk, 2, "translation", ck, rng.normal(0, 0.3, (9, 3)), "CUBICSPLINE")
    channel(walk, 4, "scale", [0, 2.0], np.array([[1, 1, 1], [1.5, 0.7, 1.1]]))
    # the skinned mesh node's transform is ignored, animated or not
    channel(walk, 6, "translation", [0, 1.0], np.array([[0, 0, 0], [9, 9, 9.0]]))
    channel(walk, 6, "weights", [0, 2.5], np.array([[0.0], [1.0]]))  # morph weights: only key times
    idle = gl.Animation()
    short_quats = np.round(quats([0, 1.2], (1, 0, 0)) * 32767)  # normalized signed shorts
    channel(idle, 5, "rotation", [0, 1.0], short_quats, ctype=SHORT)
    g.animations = [walk, idle]
    return d.save(path, how)


@pytest.mark.parametrize("how", ["glb", "embedded", "external"])
def test_synthetic_rig(tmp_path, how, device):
    path = build_rig(tmp_path / ("rig.glb" if how == "glb" else "rig.gltf"), how)
    keys = oracle_of(path).key_times(0)
    times = np.concatenate([keys, mid_times(keys, 6), [-0.3, 2.5]])
    scene, _, _ = check_against_oracle(path, times, device=device)
    np.testing.assert_array_equal(scene.times, keys)
    assert scene.times[-1] == np.float32(2.5)
    assert [m.name for m in scene.meshes] == ["body/primitive0", "body/primitive1", "prop"]
    assert [m.skeleton for m in scene.meshes] == [0, 0, 1]
    assert scene.clips == ["walk", "animation_1"] and scene.clip == "walk"
    assert scene.meshes[0].joint_indices.shape[1] == 8
    skel = scene.skeletons[0]
    assert set(skel.joint_names) == {"grp", "mover", "hips", "spine", "head", "leg", "foot"}
    assert np.all(skel.parents < np.arange(skel.joint_count))
    # skin 1 = [foot, head]: every ancestor up to the root joins, parents first
    assert set(scene.skeletons[1].joint_names) == set(skel.joint_names)
    # the loader's weights: sum-normalized; the all-zero row follows its first influence
    w = scene.meshes[0].joint_weights
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(w[3], np.eye(8)[0])
    # the second clip
    check_against_oracle(path, [0.0, 0.25, 1.0], clip="animation_1", device=device)
    check_against_oracle(path, [0.5], clip=1, device=device)


def test_synthetic_dqs_single_influence(tmp_path, device):
    path = build_rig(tmp_path / "rig.glb")
    scene = load_gltf(path)
    times = np.concatenate([scene.times, mid_times(scene.times, 3)])
    dqs = scene.skin(times, method="dqs", device=device).points
    want = [oracle_of(path).skin(t) for t in times]
    for m in scene.meshes:
        single = np.sum(m.joint_weights > 0, axis=1) == 1
        assert single[:4].all()
        ref = np.stack([w[m.name] for w in want])[:, single]
        size = np.linalg.norm(np.ptp(ref.reshape(-1, 3), axis=0))
        assert np.abs(dqs[m.name][:, single] - ref).max() <= 1e-5 * size


def test_normalized_ubyte_weights(tmp_path, device):
    path = build_rig(tmp_path / "rig.glb", weights_ctype=UBYTE)
    oracle = oracle_of(path)
    scene, _, _ = check_against_oracle(path, np.concatenate([oracle.key_times(0), [0.33]]),
                                       device=device)
    attrs = oracle.g.meshes[0].primitives[1].attributes
    raw = np.concatenate([oracle.read(attrs.WEIGHTS_0), oracle.read(attrs.WEIGHTS_1)], axis=1)
    ok = raw.sum(axis=1) > 0
    np.testing.assert_allclose(scene.meshes[1].joint_weights[ok],
                               raw[ok] / raw[ok].sum(axis=1, keepdims=True), atol=1e-6)


def test_samplers_step_and_cubic_by_hand(tmp_path):
    """STEP holds the left key; CUBICSPLINE follows the hand-written Hermite formula."""
    path = build_rig(tmp_path / "rig.glb")
    scene = load_gltf(path)
    skel = scene.skeletons[0]
    oracle = oracle_of(path)
    anim = oracle.g.animations[0]
    cub = anim.samplers[anim.channels[4].sampler]   # spine translation, CUBICSPLINE
    keys, out = oracle.read(cub.input)[:, 0], oracle.read(cub.output)
    t = np.array([0.1, 0.35, 0.6, 0.9, 1.5, 2.0])
    local = scene.animations[0].local_transforms(t)
    spine = skel.joint_names.index("spine")
    for f, tt in enumerate(t):
        i = int(np.clip(np.searchsorted(keys, tt, side="right") - 1, 0, len(keys) - 2))
        u = np.clip((tt - keys[i]) / (keys[i + 1] - keys[i]), 0.0, 1.0)
        want = ref_hermite(out[3 * i + 1], out[3 * i + 2], out[3 * i + 4], out[3 * i + 3], u,
                           keys[i + 1] - keys[i])
        np.testing.assert_allclose(local[f, spine, :3, 3], want, atol=1e-12)
    step = anim.samplers[anim.channels[2].sampler]  # hips rotation, STEP
    keys, out = oracle.read(step.input)[:, 0], oracle.read(step.output)
    hips = skel.joint_names.index("hips")
    local = scene.animations[0].local_transforms([0.39, keys[1], 0.79, 5.0])  # keys are float32
    for f, k in enumerate([0, 1, 1, 3]):
        np.testing.assert_allclose(local[f, hips, :3, :3], quat_xyzw_matrix(out[k]), atol=1e-12)


def write_static(path, *, joints=None, weights=None, skin=True, count_mismatch=False, mode=4,
                 indices=True):
    """One skin of two joints, a rest pose IBM = inverse(global), a transformed mesh node."""
    d = Doc()
    g = d.g
    g.nodes = [gl.Node(name="root", children=[1], **trs((0, 2, 0), (0, 0, 1), 0.7)),
               gl.Node(name="tip", **trs((1, 0, 0), (1, 0, 0), 0.3, (1, 2, 1))),
               gl.Node(name="mesh", mesh=0, skin=0 if skin else None,
                       **trs((3, 4, 5), (1, 1, 0), 2.0, (3, 3, 3)))]
    g.scenes = [gl.Scene(nodes=[0, 2])]
    ibm = np.stack([np.linalg.inv(Oracle(g).global_(j, 0.0, {})) for j in (0, 1)])
    V = 5
    pts = np.arange(V * 3, dtype=float).reshape(V, 3) / 7
    jn = np.array([[0, 1, 0, 0]] * V) if joints is None else joints
    wt = np.array([[0.3, 0.7, 0, 0]] * V) if weights is None else weights
    if skin:
        g.skins = [gl.Skin(joints=[0, 1], inverseBindMatrices=d.acc(ibm, "MAT4"))]
    uv = np.arange(V * 2).reshape(V, 2) * 6000  # normalized unsigned short texture coordinates
    attrs = gl.Attributes(POSITION=d.acc(pts, "VEC3"), TEXCOORD_0=d.acc(uv, "VEC2", USHORT, True),
                          JOINTS_0=d.acc(jn, "VEC4", UBYTE),
                          WEIGHTS_0=d.acc(wt[:V - 1] if count_mismatch else wt, "VEC4"))
    idx = d.acc(np.array([0, 1, 2, 3, 4, 0], np.uint16), "SCALAR", USHORT) if indices else None
    g.meshes = [gl.Mesh(primitives=[gl.Primitive(attributes=attrs, indices=idx, mode=mode)])]
    return d.save(path), pts


def test_mesh_node_transform_ignored(tmp_path, device):
    """Closed form: IBM = inverse(rest global) and no animation → skinned points are the rest
    points, whatever the skinned mesh node's own transform."""
    path, pts = write_static(tmp_path / "static.glb")
    scene = load_gltf(path)
    assert scene.clips == [] and scene.clip is None and np.array_equal(scene.times, [0.0])
    assert scene.animations == [None]
    np.testing.assert_allclose(scene.meshes[0].uvs, np.arange(10).reshape(5, 2) * 6000 / 65535,
                               rtol=1e-6)
    for method in ("lbs", "dqs"):
        got = scene.skin(method=method, device=device).points["mesh"][0]
        np.testing.assert_allclose(got, pts, atol=1e-5)
    with pytest.raises(ValueError, match=r"static\.glb.*available clips: \[\]"):
        load_gltf(path, clip=0)


def test_triangle_modes(tmp_path):
    path, _ = write_static(tmp_path / "strip.glb", mode=5, indices=False)
    strip = [[0, 1, 2], [1, 3, 2], [2, 3, 4]]  # glTF: {v_i, v_(i+1+i%2), v_(i+2-i%2)}
    np.testing.assert_array_equal(load_gltf(path).meshes[0].faces, strip)
    path, _ = write_static(tmp_path / "fan.glb", mode=6, indices=False)
    fan = [[1, 2, 0], [2, 3, 0], [3, 4, 0]]  # glTF: {v_(i+1), v_(i+2), v_0}
    np.testing.assert_array_equal(load_gltf(path).meshes[0].faces, fan)
    path, _ = write_static(tmp_path / "lines.glb", mode=1)
    with pytest.raises(ValueError, match=r"lines\.glb: mesh 0 primitive 0: mode 1 \(LINES\)"):
        load_gltf(path)


@pytest.mark.parametrize("case, pattern", [
    (dict(joints=np.array([[0, 1, 0, 0]] * 4 + [[0, 2, 0, 0]])),
     r"bad\.glb: mesh 0 primitive 0 JOINTS_0: index 2 out of range for skin 0 with 2 joints"),
    (dict(weights=np.array([[0.3, 0.7, 0, 0]] * 4 + [[np.nan, 1, 0, 0]])),
     r"bad\.glb: mesh 0 primitive 0 WEIGHTS_0.*NaN"),
    (dict(weights=np.array([[0.3, 0.7, 0, 0]] * 4 + [[-0.5, 1, 0, 0]])),
     r"bad\.glb: mesh 0 primitive 0 WEIGHTS_0.*negative"),
    (dict(count_mismatch=True),
     r"bad\.glb: mesh 0 primitive 0 WEIGHTS_0.*4 elements for 5 POSITION"),
    (dict(skin=False), r"bad\.glb: no skin"),
])
def test_bad_content(tmp_path, case, pattern):
    path, _ = write_static(tmp_path / "bad.glb", **case)
    with pytest.raises(ValueError, match=pattern):
        load_gltf(path)


def test_bad_files(tmp_path):
    with pytest.raises(ValueError, match=r"missing\.glb: cannot read"):
        load_gltf(tmp_path / "missing.glb")
    good, _ = write_static(tmp_path / "good.glb")
    data = good.read_bytes()
    cases = {"noise.glb": np.random.default_rng(0).bytes(300),
             "truncated.glb": data[:len(data) // 2], "header.glb": data[:10],
             "broken.gltf": b'{"asset": {"version": "2.0"}, "nodes": [', "empty.gltf": b"",
             "nulls.gltf": b'{"asset": {"version": "2.0"}, "nodes": [null]}',
             "version1.gltf": b'{"asset": {"version": "1.0"}}'}
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=name.replace(".", r"\.") + ": "):
            load_gltf(tmp_path / name)


# --------------------------------------------------------------------------------------------
# Hostile input: only ValueError("file: field: ..."), no silent garbage, no warnings, no hang
# --------------------------------------------------------------------------------------------


def read_glb(path):
    """(JSON document, BIN chunk or None) of a GLB file as the builders write it."""
    data = path.read_bytes()
    size = struct.unpack_from("<I", data, 12)[0]
    rest = data[20 + size:]
    blob = rest[8:8 + struct.unpack_from("<I", rest)[0]] if rest else None
    return json.loads(data[20:20 + size]), blob


def glb_chunk(kind, payload):
    """One GLB chunk: length, type, payload padded to 4 bytes (spaces for JSON, else zeros)."""
    payload += (b" " if kind == b"JSON" else b"\0") * (-len(payload) % 4)
    return struct.pack("<I", len(payload)) + kind + payload


def glb_container(chunks, version=2):
    body = b"".join(chunks)
    return struct.pack("<4sII", b"glTF", version, 12 + len(body)) + body


def glb_bytes(doc, blob=None, *, version=2, chunks=()):
    """A GLB file: the JSON chunk, the BIN chunk when ``blob`` is given, then ``chunks``."""
    first = [glb_chunk(b"JSON", json.dumps(doc).encode())]
    first += [] if blob is None else [glb_chunk(b"BIN\0", blob)]
    return glb_container(first + [glb_chunk(kind, payload) for kind, payload in chunks], version)


def static_parts(tmp_path):
    """write_static's valid file as (JSON document, BIN chunk)."""
    path, _ = write_static(tmp_path / "source.glb")
    return read_glb(path)


def acc(doc, attribute):
    """The accessor object of ``attribute`` (or "indices", "ibm") of write_static's mesh."""
    prim = doc["meshes"][0]["primitives"][0]
    index = {"indices": prim.get("indices"), "ibm": doc["skins"][0].get("inverseBindMatrices")}
    return doc["accessors"][index.get(attribute, prim["attributes"].get(attribute))]


def view(doc, attribute):
    return doc["bufferViews"][acc(doc, attribute)["bufferView"]]


def sparse(values_of, count):
    """Mutation: a sparse block on POSITION with ``count`` entries, values from another view."""
    def mutate(d):
        acc(d, "POSITION")["sparse"] = {
            "count": count, "indices": {"bufferView": acc(d, "indices")["bufferView"],
                                        "componentType": USHORT},
            "values": {"bufferView": acc(d, values_of)["bufferView"]}}
    return mutate


# (mutation of write_static's JSON, message after "bad.glb: "). write_static: 5 POSITION
# (VEC3 FLOAT, 60 bytes), TEXCOORD_0 (VEC2 USHORT, 20 bytes), 6 USHORT indices, 2 joints.
LAYOUT = {
    "stride smaller than element": (
        lambda d: view(d, "WEIGHTS_0").update(byteStride=4),
        r"accessors\[\d+\]\.bufferView: bufferViews\[\d+\]\.byteStride 4 is smaller than one "
        r"VEC4 of FLOAT element \(16 bytes\)"),
    "stride not a multiple of the component": (
        lambda d: view(d, "POSITION").update(byteStride=14),
        r"accessors\[\d+\]\.bufferView: bufferViews\[\d+\]\.byteStride 14 is not a multiple of "
        r"the 4-byte components of VEC3 of FLOAT"),
    "stride runs past the view": (
        lambda d: view(d, "POSITION").update(byteStride=16),
        r"accessors\[\d+\]\.count: 5 elements \(VEC3 of FLOAT, 12 bytes every 16\) from "
        r"byteOffset 0 need 76 bytes; bufferViews\[\d+\] has 60"),
    "offset past the view": (
        lambda d: acc(d, "POSITION").update(byteOffset=64),
        r"accessors\[\d+\]\.byteOffset: 64 is past the end of bufferViews\[\d+\] \(60 bytes\)"),
    "huge offset": (
        lambda d: acc(d, "POSITION").update(byteOffset=2**64),
        r"accessors\[\d+\]\.byteOffset: 18446744073709551616 is past the end"),
    "misaligned offset": (
        lambda d: acc(d, "POSITION").update(byteOffset=2),
        r"accessors\[\d+\]\.byteOffset: 2 puts the data at byte \d+ of buffers\[0\], not a "
        r"multiple of the 4-byte components of VEC3 of FLOAT"),
    "count past the view": (
        lambda d: acc(d, "POSITION").update(count=6),
        r"accessors\[\d+\]\.count: 6 elements .* need 72 bytes; bufferViews\[\d+\] has 60"),
    "view past the buffer": (
        lambda d: view(d, "POSITION").update(byteLength=10**6),
        r"bufferViews\[\d+\]: byteOffset \d+ \+ byteLength 1000000 = \d+ runs past the end of "
        r"buffers\[0\] \(byteLength \d+\)"),
    "buffer shorter than byteLength": (
        lambda d: d["buffers"][0].update(byteLength=d["buffers"][0]["byteLength"] + 64),
        r"buffers\[0\]: \d+ bytes of data, byteLength is \d+"),
    "negative count": (
        lambda d: acc(d, "POSITION").update(count=-1),
        r"accessors\[\d+\]\.count: expected an integer >= 1, got -1"),
    "zero count": (
        lambda d: acc(d, "WEIGHTS_0").update(count=0),
        r"accessors\[\d+\]\.count: expected an integer >= 1, got 0"),
    "fractional count": (
        lambda d: acc(d, "POSITION").update(count=2.5),
        r"accessors\[\d+\]\.count: expected an integer, got 2\.5"),
    "string offset": (
        lambda d: acc(d, "POSITION").update(byteOffset="8"),
        r'accessors\[\d+\]\.byteOffset: expected an integer, got "8"'),
    "negative stride": (
        lambda d: view(d, "POSITION").update(byteStride=-16),
        r"bufferViews\[\d+\]\.byteStride: expected an integer >= 0, got -16"),
    "boolean stride": (
        lambda d: view(d, "POSITION").update(byteStride=True),
        r"bufferViews\[\d+\]\.byteStride: expected an integer, got true"),
    "bufferView out of range": (
        lambda d: acc(d, "POSITION").update(bufferView=99),
        r"accessors\[\d+\]\.bufferView: 99 is out of range \(bufferViews has 6 entries\)"),
    "unknown componentType": (
        lambda d: acc(d, "POSITION").update(componentType=5124),
        r"accessors\[\d+\]\.componentType: expected one of \[5120, .*\], got 5124"),
    "sparse count above count": (
        sparse("TEXCOORD_0", 9),
        r"accessors\[\d+\]\.sparse\.count: 9 is more than the accessor's count 5"),
    "sparse values past their view": (
        sparse("TEXCOORD_0", 5),
        r"accessors\[\d+\]\.sparse\.count: 5 elements \(VEC3 of FLOAT, 12 bytes every 12\) "
        r"from byteOffset 0 need 60 bytes; bufferViews\[\d+\] has 20"),
    "zeros too large to allocate": (
        lambda d: acc(d, "POSITION").update(bufferView=None, count=10**9),
        r"mesh 0 primitive 0 POSITION \(accessor \d+\): count 1000000000: needs 22.4 GiB, more "
        r"than the limit of 2 GiB; raise max_input_gib"),
}


@pytest.mark.parametrize("case", LAYOUT)
def test_accessor_layout_rejected(tmp_path, case):
    """Accessor byte ranges are checked against the spec before any data is read."""
    mutate, message = LAYOUT[case]
    doc, blob = static_parts(tmp_path)
    mutate(doc)
    path = tmp_path / "bad.glb"
    path.write_bytes(glb_bytes(doc, blob))
    with pytest.raises(ValueError, match=rf"^bad\.glb: {message}"):
        load_gltf(path)


def test_valid_strides_still_read(tmp_path):
    """Interleaved data (POSITION and TEXCOORD_0 every 16 bytes, explicit byteStride) reads as
    the tightly packed original does: the layout checks reject only what the spec forbids."""
    doc, blob = static_parts(tmp_path)
    want = load_gltf(tmp_path / "source.glb").meshes[0]
    pos, uv = acc(doc, "POSITION"), acc(doc, "TEXCOORD_0")
    p = np.frombuffer(blob, "<f4", 15, view(doc, "POSITION").get("byteOffset", 0))
    t = np.frombuffer(blob, "<u2", 10, view(doc, "TEXCOORD_0").get("byteOffset", 0))
    rows = np.zeros((5, 16), np.uint8)
    rows[:, :12] = p.reshape(5, 3).copy().view(np.uint8)
    rows[:, 12:] = t.reshape(5, 2).copy().view(np.uint8)
    start = len(blob)
    blob += rows.tobytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": start, "byteLength": 80,
                               "byteStride": 16})
    doc["buffers"][0]["byteLength"] = len(blob)
    pos.update(bufferView=len(doc["bufferViews"]) - 1, byteOffset=0)
    uv.update(bufferView=len(doc["bufferViews"]) - 1, byteOffset=12)
    view(doc, "WEIGHTS_0")["byteStride"] = 16  # explicit, equal to the element size
    path = tmp_path / "interleaved.glb"
    path.write_bytes(glb_bytes(doc, blob))
    got = load_gltf(path).meshes[0]
    np.testing.assert_array_equal(got.points, want.points)
    np.testing.assert_array_equal(got.uvs, want.uvs)
    np.testing.assert_array_equal(got.joint_weights, want.joint_weights)


def test_valid_sparse_accessor_read(tmp_path):
    """Sparse substitution still reads (indices and values tightly packed, as glTF asks)."""
    doc, blob = static_parts(tmp_path)
    want = load_gltf(tmp_path / "source.glb").meshes[0].points.copy()
    values = np.array([[9, 8, 7], [-1, -2, -3]], np.float32)
    want[[1, 3]] = values
    for data in (np.array([1, 3, 0, 0], np.uint16), values):  # indices padded to 4 bytes
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob),
                                   "byteLength": data.nbytes})
        blob += data.tobytes()
    doc["buffers"][0]["byteLength"] = len(blob)
    n = len(doc["bufferViews"])
    acc(doc, "POSITION")["sparse"] = {"count": 2, "values": {"bufferView": n - 1},
                                      "indices": {"bufferView": n - 2, "componentType": USHORT}}
    path = tmp_path / "sparse.glb"
    path.write_bytes(glb_bytes(doc, blob))
    np.testing.assert_array_equal(load_gltf(path).meshes[0].points, want)


def add_animation(channel_sampler):
    def mutate(d):
        d["animations"] = [{"channels": [{"sampler": channel_sampler,
                                          "target": {"node": 0, "path": "rotation"}}],
                            "samplers": []}]
    return mutate


def drop(key):
    def mutate(obj):
        del obj[key]
    return mutate


# (mutation of write_static's JSON, message after "bad.glb: ")
STRUCTURE = {
    "top level array": (lambda d: [d], r"top level: expected an object, got an array of 1"),
    "nodes a string": (lambda d: d.update(nodes="abc"), r'nodes: expected an array, got "abc"'),
    "accessors an object": (lambda d: d.update(accessors={}),
                            r"accessors: expected an array, got an object"),
    "bufferViews a number": (lambda d: d.update(bufferViews=5),
                             r"bufferViews: expected an array, got 5"),
    "buffers a boolean": (lambda d: d.update(buffers=True), r"buffers: expected an array"),
    "meshes of numbers": (lambda d: d.update(meshes=[1]),
                          r"meshes\[0\]: expected an object, got 1"),
    "skins a string": (lambda d: d.update(skins="x"), r"skins: expected an array"),
    "animations a string": (lambda d: d.update(animations="x"), r"animations: expected an array"),
    "children a string": (lambda d: d["nodes"][0].update(children="12"),
                          r'nodes\[0\]\.children: expected an array, got "12"'),
    "children of floats": (lambda d: d["nodes"][0].update(children=[1.5]),
                           r"nodes\[0\]\.children\[0\]: expected an integer, got 1\.5"),
    "child out of range": (lambda d: d["nodes"][0].update(children=[7]),
                           r"nodes\[0\]\.children\[0\]: 7 is out of range \(nodes has 3 entries\)"),
    "node cycle": (lambda d: d["nodes"][1].update(children=[0]), r"nodes\[0\]: cycle"),
    "matrix of 15": (lambda d: d["nodes"][1].update(matrix=[1.0] * 15),
                     r"nodes\[1\]\.matrix: expected an array of 16 numbers, got an array of 15"),
    "translation of strings": (lambda d: d["nodes"][0].update(translation=[0, "a", 0]),
                               r'nodes\[0\]\.translation\[1\]: expected a finite number, got "a"'),
    "rotation underflows": (lambda d: d["nodes"][0].update(rotation=[1e-300, 0, 0, 0]),
                            r"nodes\[0\]\.rotation: zero quaternion"),
    "name a number": (lambda d: d["nodes"][2].update(name=5),
                      r"nodes\[2\]\.name: expected a string, got 5"),
    "primitives a string": (lambda d: d["meshes"][0].update(primitives="x"),
                            r'meshes\[0\]\.primitives: expected an array, got "x"'),
    "attributes an array": (lambda d: d["meshes"][0]["primitives"][0].update(attributes=[]),
                            r"meshes\[0\]\.primitives\[0\]\.attributes: expected an object"),
    "attribute a string": (
        lambda d: d["meshes"][0]["primitives"][0]["attributes"].update(POSITION="1"),
        r'meshes\[0\]\.primitives\[0\]\.attributes\.POSITION: expected an integer, got "1"'),
    "attributes missing": (lambda d: drop("attributes")(d["meshes"][0]["primitives"][0]),
                           r"meshes\[0\]\.primitives\[0\]\.attributes: missing"),
    "joints a string": (lambda d: d["skins"][0].update(joints="01"),
                        r'skins\[0\]\.joints: expected an array, got "01"'),
    "joints missing": (lambda d: drop("joints")(d["skins"][0]), r"skins\[0\]\.joints: missing"),
    "asset missing": (drop("asset"), r"asset: missing"),
    "version a number": (lambda d: d["asset"].update(version=2),
                         r"asset\.version: expected a string, got 2"),
    "extensionsRequired a string": (lambda d: d.update(extensionsRequired="KHR_x"),
                                    r"extensionsRequired: expected an array"),
    "sampler out of range": (add_animation(3), r"animations\[0\]\.channels\[0\]\.sampler: 3 is "
                             r"out of range \(samplers has 0 entries\)"),
}


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
@pytest.mark.parametrize("case", STRUCTURE)
def test_document_structure_rejected(tmp_path, case, suffix):
    """Wrong JSON types, missing required members and bad references name the field."""
    mutate, message = STRUCTURE[case]
    doc, blob = static_parts(tmp_path)
    result = mutate(doc)
    doc = result if isinstance(result, list) else doc
    path = tmp_path / f"bad{suffix}"
    if suffix == ".glb":
        path.write_bytes(glb_bytes(doc, blob))
    else:
        if isinstance(doc, dict) and isinstance(doc.get("buffers"), list):
            doc["buffers"][0]["uri"] = "data:;base64," + base64.b64encode(blob).decode()
        path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=rf"^bad\{suffix}: {message}"):
        load_gltf(path)


def test_long_node_chain(tmp_path):
    """The parent and cycle checks walk long chains: a 500-node chain above the root loads (all
    of it joins the skeleton), and a cycle closed at its far end is found."""
    doc, blob = static_parts(tmp_path)
    n = len(doc["nodes"])
    doc["nodes"] += [{"children": [n + k + 1]} for k in range(499)] + [{"children": [0]}]
    path = tmp_path / "chain.glb"
    path.write_bytes(glb_bytes(doc, blob))
    assert load_gltf(path).skeletons[0].joint_count == 502
    doc["nodes"][0]["children"].append(n)
    path.write_bytes(glb_bytes(doc, blob))
    with pytest.raises(ValueError, match=r"^chain\.glb: nodes\[\d+\]: cycle in the node hierarchy"):
        load_gltf(path)


def test_repeated_node_names_load(tmp_path):
    """glTF allows repeated node names: joints named alike get "#{node}" appended."""
    doc, blob = static_parts(tmp_path)
    doc["nodes"][1]["name"] = "root"
    path = tmp_path / "names.glb"
    path.write_bytes(glb_bytes(doc, blob))
    assert load_gltf(path).skeletons[0].joint_names == ["root#0", "root#1"]


def write_external(tmp_path, uri):
    """write_static's mesh as ``asset/static.gltf`` whose buffer is ``uri``; the data is at
    ``asset/data.bin``, ``asset/sub dir/data 1.bin`` and, outside the folder, ``outside.bin``."""
    doc, blob = static_parts(tmp_path)
    folder = tmp_path / "asset"
    (folder / "sub dir").mkdir(parents=True)
    for file in (folder / "data.bin", folder / "sub dir" / "data 1.bin", tmp_path / "outside.bin"):
        file.write_bytes(blob)
    doc["buffers"] = [{"uri": uri(tmp_path) if callable(uri) else uri, "byteLength": len(blob)}]
    path = folder / "static.gltf"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("uri", [
    "../outside.bin", "%2E%2E/outside.bin", "sub%20dir/../../outside.bin", "/etc/passwd",
    lambda tmp: str(tmp / "outside.bin"), lambda tmp: (tmp / "outside.bin").as_uri(),
    "file:../outside.bin",
], ids=["dotdot", "encoded dotdot", "via subfolder", "absolute", "absolute outside",
        "file uri", "relative file uri"])
def test_buffer_uri_outside_folder_refused(tmp_path, uri):
    """Buffers outside the asset's folder are never opened, even where the file exists."""
    path = write_external(tmp_path, uri)
    with pytest.raises(ValueError, match=r"^static\.gltf: buffers\[0\]\.uri: '.*' resolves "
                                         r"outside the asset's folder"):
        load_gltf(path)


@pytest.mark.parametrize("uri, message", [
    ("http://example.com/data.bin", "is neither a relative file path nor a data: URI"),
    ("//server/share/data.bin", "is neither a relative file path nor a data: URI"),
    ("missing.bin", r"cannot be read \(No such file or directory\)"),
    ("sub%20dir", "is a folder, not a regular file"),
])
def test_buffer_uri_unusable(tmp_path, uri, message):
    path = write_external(tmp_path, uri)
    with pytest.raises(ValueError, match=rf"^static\.gltf: buffers\[0\]\.uri: '[^']*' {message}"):
        load_gltf(path)


@pytest.mark.parametrize("uri", ["data.bin", "sub%20dir/data%201.bin", "./sub%20dir/../data.bin",
                                 lambda tmp: (tmp / "asset" / "data.bin").as_uri()])
def test_buffer_uri_inside_folder_read(tmp_path, uri):
    path = write_external(tmp_path, uri)
    np.testing.assert_array_equal(load_gltf(path).meshes[0].points,
                                  load_gltf(tmp_path / "source.glb").meshes[0].points)


def test_glb_container_checked_without_warnings(tmp_path):
    """pygltflib's UserWarnings never reach the user: unknown chunks are ignored silently (as
    the GLB spec asks) and a wrong container version is a ValueError."""
    doc, blob = static_parts(tmp_path)
    json_chunk, bin_chunk = glb_chunk(b"JSON", json.dumps(doc).encode()), glb_chunk(b"BIN\0", blob)
    long_bin = struct.pack("<I", len(blob) + 100) + bin_chunk[4:]
    cases = {"extra.glb": glb_bytes(doc, blob, chunks=[(b"XTRA", b"1234")]),
             "version1.glb": glb_bytes(doc, blob, version=1),
             "bin-first.glb": glb_container([bin_chunk, json_chunk]),
             "two-bins.glb": glb_container([json_chunk, bin_chunk, bin_chunk]),
             "truncated.glb": glb_bytes(doc, blob)[:-4],
             "long-chunk.glb": glb_container([json_chunk, long_bin]),
             "short.glb": b"glTF\2\0\0\0"}
    expect = {"version1.glb": r"GLB header: container version 1; only version 2",
              "bin-first.glb": r"GLB chunk 0: the first chunk must be the JSON chunk",
              "two-bins.glb": r"GLB chunk 2: one BIN chunk is allowed",
              "truncated.glb": r"GLB header: declares \d+ bytes but the file has \d+",
              "long-chunk.glb": r"GLB chunk 1: \d+ bytes from byte \d+ run past the end",
              "short.glb": r"GLB header: the file has 8 bytes"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for name, data in cases.items():
            (tmp_path / name).write_bytes(data)
            if name in expect:
                with pytest.raises(ValueError, match=rf"^{re.escape(name)}: {expect[name]}"):
                    load_gltf(tmp_path / name)
        np.testing.assert_array_equal(load_gltf(tmp_path / "extra.glb").meshes[0].points,
                                      load_gltf(tmp_path / "source.glb").meshes[0].points)


class FuzzTimeout(BaseException):
    """Raised by the alarm; not an Exception, so no ``except Exception`` in the loader hides it."""


@contextmanager
def time_limit(seconds):
    """Raise FuzzTimeout after ``seconds`` of wall time (where SIGALRM exists)."""
    if not hasattr(signal, "SIGALRM"):
        yield
        return

    def fire(signum, frame):
        raise FuzzTimeout(f"no result after {seconds} s")

    previous = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


FUZZ_KINDS = ("truncate", "json bytes", "bin bytes", "accessor field", "any value")
FUZZ_PER_ASSET = 30
FUZZ_VALUES = [-1, 0, 1, 3, 5, 2**31 - 1, 2**32, 2**64, 10**30, 1.5, -0.0, 1e308, float("inf"),
               float("nan"), "8", None, [], {}, True, [1, 2]]


def json_members(value):
    """Every (container, key) of a decoded JSON tree."""
    out, stack = [], [value]
    while stack:
        node = stack.pop()
        items = (node.items() if isinstance(node, dict) else
                 enumerate(node) if isinstance(node, list) else ())
        for key, child in items:
            out.append((node, key))
            stack.append(child)
    return out


def fuzz_mutation(rng, data, doc, blob, kind):
    """One mutated file: bytes of ``data`` changed, or a member of its JSON ``doc`` replaced."""
    glb = data[:4] == b"glTF"
    if kind == "truncate":
        return data[:int(rng.integers(0, len(data)))]
    if kind in ("json bytes", "bin bytes"):
        json_end = 20 + struct.unpack_from("<I", data, 12)[0] if glb else len(data)
        lo, hi = (json_end + 8, len(data)) if kind == "bin bytes" and blob else (
            20 if glb else 0, json_end)
        out = bytearray(data)
        for pos in rng.integers(lo, hi, size=int(rng.integers(1, 9))):
            out[pos] ^= int(rng.integers(1, 256))
        return bytes(out)
    d = copy.deepcopy(doc)
    value = FUZZ_VALUES[int(rng.integers(len(FUZZ_VALUES)))]
    if kind == "accessor field":
        a = d["accessors"][int(rng.integers(len(d["accessors"])))]
        field = ("count", "byteOffset", "byteStride")[int(rng.integers(3))]
        owner = d["bufferViews"][a["bufferView"]] if field == "byteStride" and "bufferView" in a \
            else a
        owner[field] = value
    else:
        members = json_members(d)
        node, key = members[int(rng.integers(len(members)))]
        node[key] = value
    return glb_bytes(d, blob) if glb else json.dumps(d).encode()


def fuzz_outcome(path):
    """None when load_gltf loads ``path`` or raises a one-line ValueError naming it, within 5 s
    and without warnings; else what went wrong."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with time_limit(5.0):
                load_gltf(path)
        except ValueError as e:
            if not str(e).startswith(f"{path.name}: ") or "\n" in str(e):
                return f"badly worded ValueError {e!r}"
        except (Exception, FuzzTimeout) as e:
            return f"{type(e).__name__}: {e}"
    if caught:
        return f"warning {caught[0].category.__name__}: {caught[0].message}"
    return None


def test_fuzz_shared_assets(shared_assets, tmp_path):
    """Seeded mutations of every shared glTF asset (truncation, flipped JSON or BIN bytes, bad
    accessor count/byteOffset/byteStride, any JSON member replaced): each file loads or raises a
    ValueError naming it; nothing else, no warning, no hang."""
    assets = sorted(p for p in shared_assets.rglob("*") if p.suffix.lower() in (".glb", ".gltf"))
    assert assets
    failures = []
    for a, asset in enumerate(assets):
        data = asset.read_bytes()
        doc, blob = read_glb(asset) if data[:4] == b"glTF" else (json.loads(data), None)
        rng = np.random.default_rng(2024 + a)
        for k in range(FUZZ_PER_ASSET):
            kind = FUZZ_KINDS[k % len(FUZZ_KINDS)]
            path = tmp_path / f"{asset.stem}-{k}{asset.suffix}"
            path.write_bytes(fuzz_mutation(rng, data, doc, blob, kind))
            problem = fuzz_outcome(path)
            if problem:
                failures.append(f"{asset.name} mutation {k} ({kind}): {problem}")
    assert not failures, "\n".join(failures)
