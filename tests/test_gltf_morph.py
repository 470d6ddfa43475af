"""glTF morph targets against an independent float64 evaluation of the glTF 2.0 equations.

The oracle reads the document's JSON and bytes itself (sparse accessors included), takes the
``weights`` of a node from its animation channel (its own LINEAR / STEP / CUBICSPLINE code, from
tests/test_gltf.py), else the node's ``weights``, else the mesh's, else zeros, morphs
``POSITION + Σ wᵢ·targetᵢ`` (NORMAL, TANGENT likewise) and then skins (``Σ w·jointMatrix``) or,
without a skin, applies the node's world transform. Velocities are checked against central
differences of the oracle. Files are generated with pygltflib; the public sample is SimpleMorph
from Khronos' glTF tutorial (no other public asset with morph targets is available offline:
Khronos' AnimatedMorphCube and MorphPrimitivesTest are not in ../shared/assets).
"""

import base64
import json

import numpy as np
import pygltflib as gl
import pytest
from test_gltf import (
    _DTYPE,
    _WIDTH,
    FLOAT,
    SHORT,
    UBYTE,
    USHORT,
    Doc,
    Oracle,
    glb_bytes,
    quats,
    read_glb,
    ref_sample,
    trs,
)

from dqskin.cli import main
from dqskin.readers.gltf import GltfMorph, load_gltf


class MorphOracle(Oracle):
    """:class:`test_gltf.Oracle` plus sparse accessors, default and animated morph weights."""

    def __init__(self, raw, bufs):
        super().__init__(gl.GLTF2.from_json(json.dumps(raw)), bufs)
        self.raw = raw

    @classmethod
    def load(cls, path):
        if path.suffix == ".glb":
            raw, blob = read_glb(path)
            return cls(raw, [blob])
        raw = json.loads(path.read_text())
        return cls(raw, [base64.b64decode(b["uri"].split(",", 1)[1]) for b in raw["buffers"]])

    def _view(self, view, offset, count, n, dtype, stride=None):
        v = self.raw["bufferViews"][view]
        stride = stride or v.get("byteStride") or n * dtype.itemsize
        start = v.get("byteOffset", 0) + offset
        buf = self.bufs[v["buffer"]]
        return np.array([np.frombuffer(buf, dtype, n, start + k * stride) for k in range(count)],
                        dtype=np.float64).reshape(count, n)

    def read(self, index):
        a = self.raw["accessors"][index]
        n, dt = _WIDTH[a["type"]], np.dtype(_DTYPE[a["componentType"]])
        x = np.zeros((a["count"], n))
        if "bufferView" in a:
            x = self._view(a["bufferView"], a.get("byteOffset", 0), a["count"], n, dt)
        sp = a.get("sparse")
        if sp:
            i, v = sp["indices"], sp["values"]
            idx = self._view(i["bufferView"], i.get("byteOffset", 0), sp["count"], 1,
                             np.dtype(_DTYPE[i["componentType"]]))[:, 0].astype(int)
            x[idx] = self._view(v["bufferView"], v.get("byteOffset", 0), sp["count"], n, dt,
                                n * dt.itemsize)
        if a.get("normalized"):
            x = {5121: x / 255, 5123: x / 65535, 5120: np.maximum(x / 127, -1),
                 5122: np.maximum(x / 32767, -1)}[a["componentType"]]
        return x

    def weights(self, i, t, clip):
        node = self.raw["nodes"][i]
        mesh = self.raw["meshes"][node["mesh"]]
        count = len(mesh["primitives"][0].get("targets", []))
        if clip is not None:
            anim = self.raw["animations"][clip]
            for ch in anim["channels"]:
                if ch["target"] == {"node": i, "path": "weights"}:
                    s = anim["samplers"][ch["sampler"]]
                    out = self.read(s["output"]).reshape(-1, count)
                    return ref_sample(t, self.read(s["input"])[:, 0], out,
                                      s.get("interpolation", "LINEAR"), False)
        return np.array(node.get("weights", mesh.get("weights", [0.0] * count)), float)

    def morph(self, t, clip=0):
        """name → (points, unit normals or None, unit tangents or None), world space."""
        anims = self.raw.get("animations", [])
        if isinstance(clip, str):
            clip = [a.get("name") for a in anims].index(clip)
        clip = clip if anims else None
        chans = {} if clip is None else self.channels(clip)
        out, memo = {}, {}
        for i, node in enumerate(self.raw["nodes"]):
            prims = self.raw["meshes"][node["mesh"]]["primitives"] if "mesh" in node else []
            if not prims or ("skin" not in node and not prims[0].get("targets")):
                continue
            w = self.weights(i, t, clip)
            if "skin" in node:
                skin = self.raw["skins"][node["skin"]]
                ibm = self.read(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
                jm = np.stack([self.global_(j, t, chans, memo) @ ibm[k]
                               for k, j in enumerate(skin["joints"])])
            for k, prim in enumerate(prims):
                attrs, targets = prim["attributes"], prim.get("targets", [])
                shape = {}
                for name in ("POSITION", "NORMAL", "TANGENT"):
                    if name not in attrs:
                        continue
                    base = self.read(attrs[name])[:, :3]
                    shape[name] = base + sum(w[m] * self.read(tg[name])
                                             for m, tg in enumerate(targets) if name in tg)
                if "skin" in node:
                    jw = self.read(attrs["WEIGHTS_0"])
                    jw /= jw.sum(1, keepdims=True)
                    m = np.einsum("vk,vkij->vij", jw, jm[self.read(attrs["JOINTS_0"]).astype(int)])
                else:
                    m = np.broadcast_to(self.global_(i, t, chans, memo), (len(shape["POSITION"]),
                                                                          4, 4))
                p = shape["POSITION"]
                pts = np.einsum("vij,vj->vi", m[:, :3, :3], p) + m[:, :3, 3]
                nrm = tan = None
                if "NORMAL" in shape:  # unambiguous for rigid (one-joint) vertices
                    nrm = np.einsum("vji,vj->vi", np.linalg.inv(m[:, :3, :3]), shape["NORMAL"])
                    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
                if "TANGENT" in shape:
                    tan = np.einsum("vij,vj->vi", m[:, :3, :3], shape["TANGENT"])
                    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
                name = node.get("name", f"node{i}")
                out[name if len(prims) == 1 else f"{name}/primitive{k}"] = (pts, nrm, tan)
        return out


# --------------------------------------------------------------------------------------------
# generated assets


def sparse_accessor(d, V, indices, values):
    """A VEC3 float accessor of ``V`` zeros (no bufferView) with sparse substitutions."""
    views = []
    for data in (np.asarray(indices, np.uint16), np.asarray(values, np.float32)):
        d.blob += b"\0" * (-len(d.blob) % 4)
        d.g.bufferViews.append(gl.BufferView(buffer=0, byteOffset=len(d.blob),
                                             byteLength=data.nbytes))
        d.blob += data.tobytes()
        views.append(len(d.g.bufferViews) - 1)
    d.g.accessors.append(gl.Accessor(count=V, componentType=FLOAT, type="VEC3", sparse=gl.Sparse(
        count=len(indices), indices=gl.AccessorSparseIndices(bufferView=views[0],
                                                             componentType=USHORT),
        values=gl.AccessorSparseValues(bufferView=views[1]))))
    return len(d.g.accessors) - 1


def unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def morph_primitive(d, rng, V, targets, *, skin=None, sparse=False, frames=True):
    """A primitive of V vertices (normals, tangents) with ``targets`` morph targets."""
    tangents = np.concatenate([unit(rng, V), np.where(rng.random((V, 1)) < 0.5, -1.0, 1.0)], 1)
    attrs = gl.Attributes(POSITION=d.acc(rng.uniform(-1, 1, (V, 3)), "VEC3"),
                          NORMAL=d.acc(unit(rng, V), "VEC3"), TANGENT=d.acc(tangents, "VEC4"))
    if skin is not None:
        joints, weights = skin
        attrs.JOINTS_0 = d.acc(joints, "VEC4", UBYTE)
        attrs.WEIGHTS_0 = d.acc(weights, "VEC4")
    tg = []
    for k in range(targets):
        if sparse and k == 1:
            idx = np.sort(rng.choice(V, 3, replace=False))
            tg.append(gl.Attributes(POSITION=sparse_accessor(d, V, idx, rng.normal(0, .5, (3, 3)))))
        elif frames and k == 0:  # POSITION, NORMAL and TANGENT offsets
            tg.append(gl.Attributes(POSITION=d.acc(rng.normal(0, 0.3, (V, 3)), "VEC3"),
                                    NORMAL=d.acc(rng.normal(0, 0.3, (V, 3)), "VEC3"),
                                    TANGENT=d.acc(rng.normal(0, 0.3, (V, 3)), "VEC3")))
        else:
            tg.append(gl.Attributes(POSITION=d.acc(rng.normal(0, 0.3, (V, 3)), "VEC3")))
    faces = rng.integers(0, V, (V, 3)).reshape(-1)
    return gl.Primitive(attributes=attrs, targets=tg, indices=d.acc(faces, "SCALAR", USHORT))


def add_channel(d, anim, node, path, keys, values, interp="LINEAR"):
    kind = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[values.shape[1]]
    anim.samplers.append(gl.AnimationSampler(input=d.acc(np.asarray(keys)[:, None], "SCALAR"),
                                             output=d.acc(values, kind), interpolation=interp))
    anim.channels.append(gl.AnimationChannel(sampler=len(anim.samplers) - 1,
                                             target=gl.AnimationChannelTarget(node=node,
                                                                              path=path)))


def write(d, path, node_weights=None, how="gltf"):
    """Save the document; ``node_weights`` {node: list} are added to the JSON (pygltflib's Node
    has no ``weights``)."""
    raw = json.loads(d.g.to_json())
    for node, w in (node_weights or {}).items():
        raw["nodes"][node]["weights"] = w
    blob = bytes(d.blob)
    if how == "glb":
        raw["buffers"] = [{"byteLength": len(blob)}]
        path.write_bytes(glb_bytes(raw, blob + b"\0" * (-len(blob) % 4)))
    else:
        raw["buffers"] = [{"byteLength": len(blob), "uri": "data:application/octet-stream;base64,"
                           + base64.b64encode(blob).decode()}]
        path.write_text(json.dumps(raw))
    return path


def build_morph(path, how="gltf"):
    """A skinned morphing mesh (node weights override mesh weights, LINEAR weights, a sparse
    target), an unskinned one under an animated parent (CUBICSPLINE weights), an unskinned STEP
    one and an unanimated two-primitive one with mesh weights; clip "rest" animates no weights.
    Half of the skinned vertices have one joint (their normals and tangents are unambiguous)."""
    rng = np.random.default_rng(12)
    d = Doc()
    g = d.g
    g.nodes = [gl.Node(name="root", children=[1], **trs((0, 1, 0), (0, 0, 1), 0.3)),
               gl.Node(name="arm", **trs((1, 0, 0), (1, 0, 0), -0.2, (1, 1.5, 1))),
               gl.Node(name="body", mesh=0, skin=0, **trs((4, 4, 4))),  # ignored: skinned
               gl.Node(name="face", mesh=1, **trs((0, 0.5, 0), (0, 1, 0), 0.4, (1, 2, 0.5))),
               gl.Node(name="mover", children=[3], **trs((2, 0, 0))),
               gl.Node(name="blink", mesh=2, **trs((0, 0, -1), (1, 1, 0), 1.0)),
               gl.Node(name="still", mesh=3, **trs(s=(2, 2, 2)))]
    g.scenes = [gl.Scene(nodes=[0, 2, 4, 5, 6])]
    ibm = np.stack([np.linalg.inv(Oracle(g).global_(j, 0.0, {})) for j in (0, 1)])
    g.skins = [gl.Skin(joints=[0, 1], inverseBindMatrices=d.acc(ibm, "MAT4"), name="rig")]
    V = 10
    joints = np.tile([0, 1, 0, 0], (V, 1))
    weights = np.zeros((V, 4))
    weights[:, :2] = rng.uniform(0.1, 1, (V, 2))
    weights[: V // 2, 1] = 0  # one joint: rigid vertices
    weights[V // 2: V - 2, 0] = 0
    g.meshes = [gl.Mesh(primitives=[morph_primitive(d, rng, V, 3, skin=(joints, weights),
                                                    sparse=True)], weights=[0.2, 0.1, 0.0]),
                gl.Mesh(primitives=[morph_primitive(d, rng, 7, 2)]),
                gl.Mesh(primitives=[morph_primitive(d, rng, 5, 1, frames=False)], weights=[0.7]),
                gl.Mesh(primitives=[morph_primitive(d, rng, 4, 1, frames=False),
                                    morph_primitive(d, rng, 6, 1)], weights=[0.4])]
    anim = gl.Animation(name="anim")
    add_channel(d, anim, 0, "rotation", [0, 1, 2], quats([0, 0.8, -0.4], (0, 0, 1)))
    add_channel(d, anim, 1, "rotation", [0.5, 1.5], quats([0.1, 1.2], (1, 0, 0)))
    add_channel(d, anim, 4, "translation", [0, 2], np.array([[2, 0, 0], [2, 1, -1.0]]))
    add_channel(d, anim, 4, "rotation", [0, 2], quats([0, 0.9], (0, 1, 0)))
    add_channel(d, anim, 2, "weights", [0, 0.75, 2],  # (K·T, 1): per key the T weights
                np.array([[0, 0, 0], [1, -0.5, 0.3], [0.2, 1, 1]]).reshape(-1, 1))
    cubic = np.stack([rng.normal(0, 2, (3, 2)), [[0, 0], [1, 0.5], [0.2, -0.4]],
                      rng.normal(0, 2, (3, 2))], axis=1)  # (in, value, out) per key
    add_channel(d, anim, 3, "weights", [0.25, 1, 1.75], cubic.reshape(-1, 1), "CUBICSPLINE")
    add_channel(d, anim, 5, "weights", [0, 0.6, 1.2], np.array([[0], [1], [0.3]]), "STEP")
    rest = gl.Animation(name="rest")
    add_channel(d, rest, 0, "translation", [0, 1], np.array([[0, 1, 0], [0, 2, 0.0]]))
    g.animations = [anim, rest]
    return write(d, path, {2: [0.5, -0.3, 0.25]}, how)


def mid_times(keys):
    k = np.asarray(keys)
    return 0.3 * k[:-1] + 0.7 * k[1:]


def check(path, times, clip=0, method="lbs"):
    scene = load_gltf(path, clip=clip)
    got = scene.skin(times, method=method, normals=True, tangents=True)
    oracle = MorphOracle.load(path)
    want = [oracle.morph(t, clip) for t in times]
    assert sorted(got.points) == sorted(want[0])
    for name in got.points:
        pts, nrm, tan = (np.stack([w[name][k] for w in want]) for k in range(3))
        rigid = slice(None) if name != "body" else slice(0, 8)  # one-joint vertices
        some = slice(None) if method == "lbs" else rigid  # the oracle skins with LBS
        np.testing.assert_allclose(got.points[name][:, some], pts[:, some], atol=2e-5,
                                   err_msg=name)
        np.testing.assert_allclose(got.normals[name][:, rigid], nrm[:, rigid], atol=2e-5)
        np.testing.assert_allclose(got.tangents[name][:, rigid], tan[:, rigid], atol=2e-5)
    return scene, got


@pytest.fixture(scope="module")
def morph_file(tmp_path_factory):
    return build_morph(tmp_path_factory.mktemp("morph") / "morph.gltf")


def test_morph_matches_oracle(morph_file, tmp_path):
    scene = load_gltf(morph_file)
    keys = scene.times
    times = np.concatenate([keys, mid_times(keys), [-0.5, 2.5]])
    scene, got = check(morph_file, times)
    assert [m.name for m in scene.meshes] == ["body", "face", "blink", "still/primitive0",
                                              "still/primitive1"]
    assert [s.name for s in scene.skeletons] == ["rig", "face", "blink", "still"]
    assert all(isinstance(m.deformer, GltfMorph) for m in scene.meshes)
    np.testing.assert_array_equal(scene.meshes[0].tangents[:, 3] ** 2, 1)
    # the base shape with blend_shapes=False, the morphed one otherwise
    base = scene.skin([0.75], blend_shapes=False).points["body"]
    assert np.abs(base - got.points["body"][list(times).index(0.75)]).max() > 0.1
    # the unskinned meshes move with their node (face: animated parent) and DQS is rigid there
    check(morph_file, [0.4, 1.3], method="dqs")
    # GLB container, same answers
    glb = build_morph(tmp_path / "morph.glb", how="glb")
    check(glb, [0.1, 1.0, 1.9])


def test_default_weights(morph_file):
    """Clip "rest" animates no weights: node weights, else mesh weights, else zeros."""
    scene, _ = check(morph_file, [0.0, 0.5, 1.0], clip="rest")
    np.testing.assert_array_equal(scene.mesh("body").deformer.weights([3.0]), [[0.5, -0.3, 0.25]])
    np.testing.assert_array_equal(scene.mesh("blink").deformer.weights([3.0]), [[0.7]])
    np.testing.assert_array_equal(scene.mesh("face").deformer.weights([3.0]), [[0, 0]])


def test_samplers_by_hand(morph_file):
    """Each sampler kind at hand-picked times, straight from the keys written above."""
    scene = load_gltf(morph_file)
    step = scene.mesh("blink").deformer.weights([-1, 0, 0.59, 0.61, 1.1, 1.21, 5])[:, 0]
    np.testing.assert_allclose(step, [0, 0, 0, 1, 1, 0.3, 0.3], atol=1e-7)
    lin = scene.mesh("body").deformer.weights([0.375, 1.375])
    np.testing.assert_allclose(lin, [[0.5, -0.25, 0.15], [0.6, 0.25, 0.65]], atol=1e-7)
    cubic = scene.mesh("face").deformer
    np.testing.assert_allclose(cubic.weights([0.25, 1.0, 9]), [[0, 0], [1, 0.5], [0.2, -0.4]],
                               atol=1e-7)


def test_velocities_match_differences(morph_file):
    """Analytic velocities (joints + morph weight rates, every sampler kind) against central
    differences of the float64 oracle, away from keys."""
    scene = load_gltf(morph_file)
    times = mid_times(scene.times)
    got = scene.skin(times, velocities=True).velocities
    oracle = MorphOracle.load(morph_file)
    h = 1e-5
    for f, t in enumerate(times):
        hi, lo = oracle.morph(t + h), oracle.morph(t - h)
        for name, v in got.items():
            want = (hi[name][0] - lo[name][0]) / (2 * h)
            np.testing.assert_allclose(v[f], want, atol=2e-4 * (1 + np.abs(want).max()),
                                       err_msg=f"{name} at {t}")
    # STEP weights are piecewise constant; CUBICSPLINE at a key: mean of both tangents
    blink = scene.mesh("blink").deformer
    np.testing.assert_array_equal(blink.weight_rates([0.3, 0.6, 0.9]), 0)
    face = scene.mesh("face").deformer
    keys, values, _ = face.channel
    np.testing.assert_allclose(face.weight_rates([1.0])[0], 0.5 * (values[3] + values[5]))
    assert np.all(face.weight_rates([0.0, 2.0]) == 0)  # outside the keys: clamped


SIMPLE_MORPH = {  # Khronos glTF Tutorial §17 "A Simple Morph Target" (SimpleMorph), verbatim data
    "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 1},
                                "targets": [{"POSITION": 2}, {"POSITION": 3}], "indices": 0}],
                "weights": [1.0, 0.5]}],
    "animations": [{"samplers": [{"input": 4, "interpolation": "LINEAR", "output": 5}],
                    "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}],
    "buffers": [
        {"uri": "data:application/gltf-buffer;base64,AAABAAIAAAAAAAAAAAAAAAAAAAAAAIA/AAAAAAAAAAAA"
                "AAA/AAAAPwAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAIC/AACAPwAAAAAAAAAAAAAAAAAAAAAAAAAA"
                "AAAAAAAAAAAAAIA/AACAPwAAAAA=", "byteLength": 116},
        {"uri": "data:application/gltf-buffer;base64,AAAAAAAAgD8AAABAAABAQAAAgEAAAAAAAAAAAAAAAAAA"
                "AIA/AACAPwAAgD8AAIA/AAAAAAAAAAAAAAAA", "byteLength": 60}],
    "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 6, "target": 34963},
                    {"buffer": 0, "byteOffset": 8, "byteLength": 108, "byteStride": 12,
                     "target": 34962},
                    {"buffer": 1, "byteOffset": 0, "byteLength": 20},
                    {"buffer": 1, "byteOffset": 20, "byteLength": 40}],
    "accessors": [
        {"bufferView": 0, "byteOffset": 0, "componentType": 5123, "count": 3, "type": "SCALAR"},
        {"bufferView": 1, "byteOffset": 0, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 1, "byteOffset": 36, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 1, "byteOffset": 72, "componentType": 5126, "count": 3, "type": "VEC3"},
        {"bufferView": 2, "byteOffset": 0, "componentType": 5126, "count": 5, "type": "SCALAR"},
        {"bufferView": 3, "byteOffset": 0, "componentType": 5126, "count": 10, "type": "SCALAR"}],
    "asset": {"version": "2.0"}}


def test_public_simple_morph(tmp_path):
    """Khronos' SimpleMorph: one triangle; the third vertex (0.5, 0.5, 0) moves by w₀·(−1, 1, 0)
    + w₁·(1, 1, 0) with weights keyed (0, 0), (0, 1), (1, 1), (1, 0), (0, 0) at t = 0 … 4 s
    (accessor min/max of the original file); the node has no skin."""
    path = tmp_path / "SimpleMorph.gltf"
    path.write_text(json.dumps(SIMPLE_MORPH))
    times = np.array([-1, 0, 0.5, 1, 2, 2.5, 3, 4, 6])
    w = np.array([[0, 0], [0, 0], [0, .5], [0, 1], [1, 1], [1, .5], [1, 0], [0, 0], [0, 0]])
    third = np.array([0.5, 0.5, 0]) + w @ np.array([[-1, 1, 0], [1, 1, 0]])
    scene, got = load_gltf(path), None
    np.testing.assert_array_equal(scene.times, [0, 1, 2, 3, 4])
    for method in ("lbs", "dqs"):
        got = scene.skin(times, method=method, velocities=True)
        np.testing.assert_allclose(got.points["node0"][:, 2], third, atol=1e-6)
        np.testing.assert_allclose(got.points["node0"][:, :2], [[[0, 0, 0], [1, 0, 0]]] * 9)
    oracle = MorphOracle.load(path)
    np.testing.assert_allclose(got.points["node0"], [oracle.morph(t)["node0"][0] for t in times],
                               atol=1e-6)
    # velocity of the third vertex: slopes of the weights, the mean of both sides at keys
    rate = {0.5: [1, 1, 0], 1: [0, 1, 0], 2.5: [-1, -1, 0], 4: [1, -1, 0], 6: [0, 0, 0]}
    for t, v in rate.items():
        np.testing.assert_allclose(got.velocities["node0"][list(times).index(t), 2], v,
                                   atol=1e-6)


def test_cli_writes_morphs(morph_file, tmp_path, capsys):
    """`dqskin skin` end to end: the .npz holds the oracle's points at every frame of the clip
    (24 fps), the frame files are numbered in frames."""
    out = tmp_path / "morph.npz"
    assert main(["skin", str(morph_file), "--out", str(out)]) == 0
    data = np.load(out)
    oracle = MorphOracle.load(morph_file)
    for i, name in enumerate(data["names"]):
        want = [oracle.morph(t)[str(name)][0] for t in data["times"]]
        np.testing.assert_allclose(data[f"points_{i}"], want, atol=2e-5)
    frames = tmp_path / "f_{:02d}.obj"
    assert main(["skin", str(morph_file), "--out", str(frames), "--frames", "18"]) == 0
    assert [p.name for p in tmp_path.glob("f_*.obj")] == ["f_18.obj"]  # 0.75 s


def corrupt(path, tmp_path, mutate):
    raw = json.loads(path.read_text())
    mutate(raw)
    bad = tmp_path / "bad.gltf"
    bad.write_text(json.dumps(raw))
    return bad


@pytest.mark.parametrize("mutate, pattern", [
    (lambda r: r["nodes"][2].update(weights=[1.0]),
     r"nodes\[2\]\.weights: 1 weights for 3 morph targets"),
    (lambda r: r["meshes"][2].update(weights=[1.0, 2.0]),
     r"meshes\[2\]\.weights: 2 weights for 1 morph targets"),
    (lambda r: r["meshes"][3]["primitives"][0].update(targets=[]),
     r"meshes\[3\]\.primitives: \[0, 1\] morph targets"),
    (lambda r: r["animations"][0]["channels"][4]["target"].update(node=0),
     r"animations\[0\]\.channels\[4\]: animates the morph weights of nodes\[0\], which has no"),
    (lambda r: r["animations"][0]["channels"][4]["target"].update(node=5),
     r"animations\[0\]\.samplers\[4\]\.output: 9 values for 3 LINEAR keys of 1 morph weights"),
    (lambda r: r["meshes"][1]["primitives"][0]["targets"][1].update(POSITION=0),
     r"mesh 1 primitive 0 targets\[1\]\.POSITION \(accessor 0\): type"),
    (lambda r: r["meshes"][1]["primitives"][0].update(targets=[{"POSITION": 999}]),
     r"meshes\[1\]\.primitives\[0\]\.targets\[0\]\.POSITION: 999 is out of range"),
])
def test_bad_morphs_rejected(morph_file, tmp_path, mutate, pattern):
    with pytest.raises(ValueError, match=r"bad\.gltf: " + pattern):
        load_gltf(corrupt(morph_file, tmp_path, mutate))


BYTE = 5120


def build_quantized(path, unflag=None):
    """Two unskinned morphing meshes with quantized data: target NORMAL as normalized BYTE,
    TANGENT as normalized SHORT, POSITION as plain SHORT (KHR_mesh_quantization's integer
    offsets); ``weights`` samplers with normalized UNSIGNED_BYTE (LINEAR) and UNSIGNED_SHORT
    (STEP) outputs. ``unflag``: "targets" or "weights" drops ``normalized`` from the NORMAL and
    TANGENT targets or from the weights: what the spec forbids."""
    rng = np.random.default_rng(8)
    d = Doc()
    g = d.g
    g.nodes = [gl.Node(name="a", mesh=0, **trs((0, 1, 0), (0, 0, 1), 0.5)),
               gl.Node(name="b", mesh=1, **trs((2, 0, 0)))]
    g.scenes = [gl.Scene(nodes=[0, 1])]
    V = 8
    flag_t, flag_w = unflag != "targets", unflag != "weights"

    def prim():
        tangents = np.concatenate([unit(rng, V), np.ones((V, 1))], 1)
        attrs = gl.Attributes(POSITION=d.acc(rng.uniform(-1, 1, (V, 3)), "VEC3"),
                              NORMAL=d.acc(unit(rng, V), "VEC3"),
                              TANGENT=d.acc(tangents, "VEC4"))
        targets = [gl.Attributes(
            POSITION=d.acc(rng.integers(-2, 3, (V, 3)), "VEC3", SHORT),
            NORMAL=d.acc(rng.integers(-127, 128, (V, 3)), "VEC3", BYTE, flag_t),
            TANGENT=d.acc(rng.integers(-20000, 20000, (V, 3)), "VEC3", SHORT, flag_t)),
            gl.Attributes(POSITION=d.acc(rng.normal(0, 0.3, (V, 3)), "VEC3"))]
        faces = rng.integers(0, V, (V, 3)).reshape(-1)
        return gl.Primitive(attributes=attrs, targets=targets,
                            indices=d.acc(faces, "SCALAR", USHORT))

    g.meshes = [gl.Mesh(primitives=[prim()]), gl.Mesh(primitives=[prim()])]
    anim = gl.Animation(name="anim")
    for node, ctype, top, interp in ((0, UBYTE, 255, "LINEAR"), (1, USHORT, 65535, "STEP")):
        values = rng.integers(0, top + 1, (3 * 2, 1))
        anim.samplers.append(gl.AnimationSampler(
            input=d.acc(np.array([[0.0], [0.8], [2.0]]), "SCALAR"),
            output=d.acc(values, "SCALAR", ctype, flag_w), interpolation=interp))
        anim.channels.append(gl.AnimationChannel(
            sampler=len(anim.samplers) - 1,
            target=gl.AnimationChannelTarget(node=node, path="weights")))
    g.animations = [anim]
    return write(d, path)


def test_quantized_morphs_match_oracle(tmp_path):
    """Normalized integer targets and weights are dequantized as the spec says (the oracle
    divides by 127, 32767, 255, 65535)."""
    path = build_quantized(tmp_path / "quantized.gltf")
    check(path, [0.0, 0.3, 0.8, 1.4, 2.0])
    scene = load_gltf(path)
    w = scene.mesh("a").deformer.weights([0.0])
    assert np.all((w >= 0) & (w <= 1)) and np.any((w > 0) & (w < 1)), w


@pytest.mark.parametrize("unflag, pattern", [
    ("targets", r"mesh 0 primitive 0 targets\[0\]\.NORMAL \(accessor \d+\): BYTE "
                r"components must be normalized"),
    ("weights", r"animations\[0\]\.samplers\[0\]\.output \(accessor \d+\): UNSIGNED_BYTE "
                r"components must be normalized"),
])
def test_non_normalized_integer_morph_data_refused(tmp_path, unflag, pattern):
    """glTF allows integer morph weights and NORMAL/TANGENT offsets only when normalized."""
    path = build_quantized(tmp_path / "bad.gltf", unflag)
    with pytest.raises(ValueError, match=r"bad\.gltf: " + pattern):
        load_gltf(path)
