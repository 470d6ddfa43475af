"""glTF 2.0 loader: skinned meshes, skins and one animation clip as a :class:`dqskin.scene.Scene`.

Reads ``.gltf`` (embedded base64 or external buffers) and ``.glb`` through pygltflib and follows
the glTF 2.0 skinning equation: skinned vertices live in world space, the skinned mesh node's own
transform is ignored, and ::

    jointMatrix[i] = globalTransform(skin.joints[i]) · inverseBindMatrices[i]
    world(v) = Σ_k w_k · jointMatrix[j_k] · v

Each skin becomes a :class:`~dqskin.skeleton.Skeleton` over its joints plus every ancestor node
(the scene-graph path up to the root, ordered parents first), with ``bind = inverse(IBM)`` for the
joints and the rest world transform for the added ancestors (no vertex references them), so
``Skeleton.skinning_transforms`` is exactly the glTF joint matrix. Morph targets and ``weights``
channels are ignored (meshes keep their base shape).
"""

import base64
import binascii
import os
from urllib.parse import unquote

import numpy as np
import pygltflib

from .. import quat
from ..animation import Animation
from ..scene import Mesh, Scene
from ..skeleton import Skeleton

__all__ = ["SUFFIXES", "GltfAnimation", "load", "load_gltf"]

SUFFIXES = (".gltf", ".glb")
"""glTF files :func:`load` reads."""

_COMPONENT_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
# Dequantization of normalized integers (glTF 2.0 §3.11): f = max(c / (2^(b-1) - 1), -1) signed,
# f = c / (2^b - 1) unsigned.
_NORMALIZE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_TYPE_SIZES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}  # the types read here
_MODES = {0: "POINTS", 1: "LINES", 2: "LINE_LOOP", 3: "LINE_STRIP", 4: "TRIANGLES",
          5: "TRIANGLE_STRIP", 6: "TRIANGLE_FAN"}
_INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
_PATH_SIZES = {"translation": 3, "rotation": 4, "scale": 3}
_UNSUPPORTED_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")
_INTEGERS = (5121, 5123, 5125)
_FLOAT_OR_NORMALIZED = (5126, 5121, 5123)


def _trs_matrices(t, r, s):
    """Compose ``T · R · S``.

    Parameters
    ----------
    t, s : (..., 3) float64
        Translation and scale.
    r : (..., 4) float64
        Rotation quaternion ``(w, x, y, z)``, normalized here.

    Returns
    -------
    (..., 4, 4) float64, column-vector convention.
    """
    m = np.zeros(t.shape[:-1] + (4, 4))
    m[..., :3, :3] = quat.to_matrix(r) * s[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


def _sample(times, keys, values, interpolation, rotation):
    """Evaluate one glTF animation sampler, clamped outside its key range.

    Parameters
    ----------
    times : (F,) float64
    keys : (K,) float64, strictly increasing
    values : (K, n) or, for CUBICSPLINE, (3K, n) float64
        Key values; CUBICSPLINE stores (in-tangent, value, out-tangent) per key.
    interpolation : {"LINEAR", "STEP", "CUBICSPLINE"}
    rotation : bool
        Values are quaternions ``(w, x, y, z)``: LINEAR slerps along the shorter arc and
        CUBICSPLINE results are normalized.

    Returns
    -------
    (F, n) float64
    """
    cubic = interpolation == "CUBICSPLINE"
    v = values[1::3] if cubic else values
    n = keys.shape[0]
    if interpolation == "STEP" or n == 1:
        return v[np.clip(np.searchsorted(keys, times, side="right") - 1, 0, n - 1)]
    i = np.clip(np.searchsorted(keys, times, side="right") - 1, 0, n - 2)
    dt = keys[i + 1] - keys[i]
    u = np.clip((times - keys[i]) / dt, 0.0, 1.0)[:, None]
    if not cubic:
        if rotation:
            return quat.slerp(v[i], v[i + 1], u[:, 0])
        return (1.0 - u) * v[i] + u * v[i + 1]
    a, b = values[0::3], values[2::3]
    u2, u3 = u * u, u * u * u
    p = ((2 * u3 - 3 * u2 + 1) * v[i] + (u3 - 2 * u2 + u) * dt[:, None] * b[i]
         + (-2 * u3 + 3 * u2) * v[i + 1] + (u3 - u2) * dt[:, None] * a[i + 1])
    if rotation:
        p = p / np.linalg.norm(p, axis=-1, keepdims=True)
    return p


class GltfAnimation(Animation):
    """One glTF animation clip driving the nodes of one skeleton.

    Parameters
    ----------
    key_times : (K,) float64
        Union of the clip's sampler input times, seconds.
    rest_trs : tuple of (J, 3), (J, 4), (J, 3) float64
        Static translation, rotation ``(w, x, y, z)`` and scale of every skeleton node.
    matrix_nodes : dict int → (4, 4) float64
        Skeleton nodes given by a static ``matrix`` (never animated), by skeleton index.
    channels : list of (joint, path, keys, values, interpolation)
        ``path`` in {"translation", "rotation", "scale"}; ``keys`` (K,) and ``values`` as in
        the sampler (rotations ``(w, x, y, z)``).
    """

    def __init__(self, key_times, rest_trs, matrix_nodes, channels):
        self.key_times = np.asarray(key_times, dtype=np.float64)
        self._rest = rest_trs
        self._matrix_nodes = matrix_nodes
        self._channels = channels

    def local_transforms(self, times):
        """Parent-relative node transforms at ``times``.

        Parameters
        ----------
        times : (F,) float
            Seconds; clamped to each sampler's key range.

        Returns
        -------
        (F, J, 4, 4) float64, column-vector convention, skeleton joint order.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        trs = {path: np.repeat(rest[None], t.shape[0], axis=0)
               for path, rest in zip(("translation", "rotation", "scale"), self._rest)}
        for joint, path, keys, values, interpolation in self._channels:
            trs[path][:, joint] = _sample(t, keys, values, interpolation, path == "rotation")
        m = _trs_matrices(trs["translation"], trs["rotation"], trs["scale"])
        for joint, matrix in self._matrix_nodes.items():
            m[:, joint] = matrix
        return m


class _Reader:
    """Checked access to one glTF document: accessors, nodes, skins, meshes, clips."""

    def __init__(self, path):
        self.path = os.fspath(path)
        self.name = os.path.basename(self.path)
        try:
            with open(self.path, "rb") as f:
                data = f.read()
        except OSError as e:
            raise self.error(f"cannot read file ({e.strerror})") from None
        try:
            if data[:4] == b"glTF":
                doc = pygltflib.GLTF2.load_from_bytes(data)
            else:
                doc = pygltflib.GLTF2.gltf_from_json(data.decode("utf-8"))
        except Exception as e:  # pygltflib raises anything from struct, json, dataclasses
            raise self.error(f"not a valid glTF or GLB file ({type(e).__name__}: {e})") from None
        if not isinstance(doc, pygltflib.GLTF2):
            raise self.error("not a valid GLB file (no JSON chunk)")
        self.doc = doc
        self._check_structure()
        version = str(getattr(doc.asset, "version", "") or "")
        if not version.startswith("2."):
            raise self.error(f"asset.version {version!r}: only glTF 2.x is supported")
        for ext in doc.extensionsRequired or ():
            if ext in _UNSUPPORTED_EXTENSIONS:
                raise self.error(f"extensionsRequired: {ext} is not supported")
        self._buffers = {}
        self.parents = self._parents()

    def _check_structure(self):
        """Arrays the loader walks hold objects; ``null`` arrays become empty ones."""
        gl = pygltflib
        top = (("nodes", gl.Node), ("accessors", gl.Accessor), ("bufferViews", gl.BufferView),
               ("buffers", gl.Buffer), ("meshes", gl.Mesh), ("skins", gl.Skin),
               ("animations", gl.Animation))
        todo = [(self.doc, name, name, cls) for name, cls in top]
        while todo:
            owner, attr, where, cls = todo.pop()
            items = getattr(owner, attr, None)
            if items is None:
                setattr(owner, attr, items := [])
            if not isinstance(items, list):
                raise self.error(f"{where}: expected an array")
            for k, item in enumerate(items):
                if not isinstance(item, cls):
                    raise self.error(f"{where}[{k}]: expected an object")
                if cls is gl.Mesh:
                    todo.append((item, "primitives", f"{where}[{k}].primitives", gl.Primitive))
                elif cls is gl.Animation:
                    todo += [(item, "channels", f"{where}[{k}].channels", gl.AnimationChannel),
                             (item, "samplers", f"{where}[{k}].samplers", gl.AnimationSampler)]

    def error(self, message):
        return ValueError(f"{self.name}: {message}")

    def item(self, kind, items, index, where):
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise self.error(f"{where}: {kind} {index!r} out of range ({len(items)} {kind}s)")
        return items[index]

    # -- binary data -------------------------------------------------------------------------

    def _buffer(self, index, where):
        if index in self._buffers:
            return self._buffers[index]
        buf = self.item("buffer", self.doc.buffers, index, where)
        uri = buf.uri
        if uri is None:
            data = self.doc.binary_blob()
            if data is None or index != 0:
                raise self.error(f"buffers[{index}]: no uri and no GLB binary chunk")
        elif uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise self.error(f"buffers[{index}].uri: data URI is not base64")
            try:
                data = base64.b64decode(payload, validate=True)
            except binascii.Error as e:
                raise self.error(f"buffers[{index}].uri: bad base64 ({e})") from None
        else:
            file = os.path.join(os.path.dirname(self.path), unquote(uri))
            try:
                with open(file, "rb") as f:
                    data = f.read()
            except OSError as e:
                raise self.error(f"buffers[{index}].uri: cannot read {uri!r} "
                                 f"({e.strerror})") from None
        if buf.byteLength is None or len(data) < buf.byteLength:
            raise self.error(f"buffers[{index}]: {len(data)} bytes, byteLength is {buf.byteLength}")
        self._buffers[index] = data
        return data

    def _view(self, index, where):
        view = self.item("bufferView", self.doc.bufferViews, index, where)
        data = self._buffer(view.buffer, f"bufferViews[{index}]")
        start, length = view.byteOffset or 0, view.byteLength or 0
        if start + length > len(data):
            raise self.error(f"bufferViews[{index}]: bytes [{start}, {start + length}) past the "
                             f"end of buffer {view.buffer} ({len(data)} bytes)")
        return memoryview(data)[start:start + length], view.byteStride

    def _strided(self, view_index, offset, count, width, dtype, where, stride=None):
        data, view_stride = self._view(view_index, where)
        size = width * dtype.itemsize
        stride = stride or view_stride or size
        need = offset + stride * (count - 1) + size if count else 0
        if need > len(data):
            raise self.error(f"{where}: needs {need} bytes, bufferView {view_index} has "
                             f"{len(data)}")
        if not count:
            return np.zeros((0, width), dtype)
        return np.ndarray((count, width), dtype, buffer=data, offset=offset,
                          strides=(stride, dtype.itemsize)).copy()

    def accessor(self, index, where, types, components, *, as_float=True):
        """Accessor data (count, n), dequantized to float64 unless ``as_float`` is False."""
        acc = self.item("accessor", self.doc.accessors, index, where)
        where = f"{where} (accessor {index})"
        if acc.type not in types:
            raise self.error(f"{where}: type {acc.type}, expected {' or '.join(types)}")
        if acc.componentType not in components:
            raise self.error(f"{where}: componentType {acc.componentType} not allowed here")
        if not isinstance(acc.count, int) or acc.count < 0:
            raise self.error(f"{where}: bad count {acc.count!r}")
        width, dtype = _TYPE_SIZES[acc.type], np.dtype(_COMPONENT_DTYPES[acc.componentType])
        if acc.bufferView is None:
            out = np.zeros((acc.count, width), dtype)
        else:
            out = self._strided(acc.bufferView, acc.byteOffset or 0, acc.count, width, dtype, where)
        if acc.sparse is not None and acc.sparse.count:
            sp = acc.sparse
            if sp.indices.componentType not in _INTEGERS:
                raise self.error(f"{where}: sparse.indices.componentType "
                                 f"{sp.indices.componentType} is not an unsigned integer")
            idx = self._strided(sp.indices.bufferView, sp.indices.byteOffset or 0, sp.count, 1,
                                np.dtype(_COMPONENT_DTYPES[sp.indices.componentType]),
                                f"{where} sparse.indices")[:, 0]
            vals = self._strided(sp.values.bufferView, sp.values.byteOffset or 0, sp.count, width,
                                 dtype, f"{where} sparse.values", stride=width * dtype.itemsize)
            if idx.size and idx.max() >= acc.count:
                raise self.error(f"{where}: sparse index {int(idx.max())} >= count {acc.count}")
            out[idx.astype(np.int64)] = vals
        if not as_float:
            return out
        f = out.astype(np.float64)
        if acc.normalized and acc.componentType in _NORMALIZE:
            f = np.maximum(f / _NORMALIZE[acc.componentType], -1.0)
        if not np.all(np.isfinite(f)):
            raise self.error(f"{where}: NaN or infinite values")
        return f

    # -- scene graph ---------------------------------------------------------------------------

    def _parents(self):
        nodes = self.doc.nodes
        parents = np.full(len(nodes), -1, dtype=np.int64)
        for i, node in enumerate(nodes):
            for c in node.children or ():
                self.item("node", nodes, c, f"nodes[{i}].children")
                if parents[c] >= 0:
                    raise self.error(f"nodes[{c}] is a child of both nodes {parents[c]} and {i}")
                parents[c] = i
        for i in range(len(nodes)):
            cur, steps = i, 0
            while cur >= 0:
                cur, steps = parents[cur], steps + 1
                if steps > len(nodes):
                    raise self.error(f"nodes[{i}]: cycle in the node hierarchy")
        return parents

    def node_name(self, index):
        return self.doc.nodes[index].name or f"node{index}"

    def node_trs(self, index):
        """Static (t, r (w, x, y, z), s, matrix or None) of a node, float64."""
        node = self.doc.nodes[index]
        where = f"nodes[{index}]"
        if node.matrix is not None:
            m = np.asarray(node.matrix, dtype=np.float64)
            if m.shape != (16,) or not np.all(np.isfinite(m)):
                raise self.error(f"{where}.matrix: expected 16 finite numbers")
            return None, None, None, m.reshape(4, 4).T  # column-major in glTF
        parts = []
        for field, default in (("translation", (0, 0, 0)), ("rotation", (0, 0, 0, 1)),
                               ("scale", (1, 1, 1))):
            value = getattr(node, field)
            v = np.asarray(default if value is None else value, dtype=np.float64)
            if v.shape != (len(default),) or not np.all(np.isfinite(v)):
                raise self.error(f"{where}.{field}: expected {len(default)} finite numbers")
            parts.append(v)
        t, r, s = parts
        if not np.any(r):
            raise self.error(f"{where}.rotation: zero quaternion")
        return t, r[[3, 0, 1, 2]], s, None

    def node_local(self, index):
        t, r, s, m = self.node_trs(index)
        return m if m is not None else _trs_matrices(t, r, s)

    def rest_pose(self, nodes):
        """Static ((J, 3) t, (J, 4) r (w, x, y, z), (J, 3) s) and {k: matrix} of ``nodes``."""
        t, r, s = np.zeros((len(nodes), 3)), np.zeros((len(nodes), 4)), np.ones((len(nodes), 3))
        r[:, 0] = 1.0
        matrices = {}
        for k, n in enumerate(nodes):
            tk, rk, sk, m = self.node_trs(n)
            if m is None:
                t[k], r[k], s[k] = tk, rk, sk
            else:
                matrices[k] = m
        return (t, r, s), matrices

    def skeleton(self, skin_index):
        """Skeleton of one skin and the map skin joint slot → skeleton joint index."""
        skin = self.doc.skins[skin_index]
        where = f"skins[{skin_index}]"
        joints = list(skin.joints or ())
        if not joints:
            raise self.error(f"{where}.joints: empty")
        for j in joints:
            self.item("node", self.doc.nodes, j, f"{where}.joints")
        if len(set(joints)) != len(joints):
            raise self.error(f"{where}.joints: a node is listed twice")
        if skin.inverseBindMatrices is None:
            ibm = np.tile(np.eye(4), (len(joints), 1, 1))
        else:
            a = self.accessor(skin.inverseBindMatrices, f"{where}.inverseBindMatrices", ("MAT4",),
                              (5126,))
            if a.shape[0] != len(joints):
                raise self.error(f"{where}.inverseBindMatrices: {a.shape[0]} matrices for "
                                 f"{len(joints)} joints")
            ibm = a.reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major in glTF
        members = set()
        for j in joints:
            while j >= 0 and j not in members:
                members.add(j)
                j = int(self.parents[j])
        children = {n: [c for c in self.doc.nodes[n].children or () if c in members]
                    for n in members}
        order, stack = [], sorted((n for n in members if self.parents[n] < 0), reverse=True)
        while stack:  # pre-order depth-first: parents first, children in glTF order
            n = stack.pop()
            order.append(n)
            stack.extend(reversed(children[n]))
        index = {n: k for k, n in enumerate(order)}
        parents = np.array([index[int(self.parents[n])] if self.parents[n] >= 0 else -1
                            for n in order], dtype=np.int32)
        local = np.stack([self.node_local(n) for n in order])
        bind = local.copy()
        for k, p in enumerate(parents):
            if p >= 0:
                bind[k] = bind[p] @ local[k]
        for slot, node in enumerate(joints):
            try:
                bind[index[node]] = np.linalg.inv(ibm[slot])
            except np.linalg.LinAlgError:
                raise self.error(f"{where}.inverseBindMatrices[{slot}]: singular matrix") from None
        skel = Skeleton([self.node_name(n) for n in order], parents, bind, local,
                        name=skin.name or f"skin{skin_index}")
        return skel, order, np.array([index[n] for n in joints], dtype=np.int32)

    # -- meshes --------------------------------------------------------------------------------

    def primitive(self, mesh_index, prim_index, skin_index, slot_to_joint):
        """(points, faces, joint_indices, joint_weights, normals, uvs) of one primitive."""
        prim = self.doc.meshes[mesh_index].primitives[prim_index]
        where = f"mesh {mesh_index} primitive {prim_index}"
        attrs = prim.attributes
        if getattr(attrs, "POSITION", None) is None:
            raise self.error(f"{where}: no POSITION attribute")
        points = self.accessor(attrs.POSITION, f"{where} POSITION", ("VEC3",),
                               tuple(_COMPONENT_DTYPES))
        V = points.shape[0]

        def attribute(name, types, components, **kw):
            index = getattr(attrs, name, None)
            if index is None:
                return None
            a = self.accessor(index, f"{where} {name}", types, components, **kw)
            if a.shape[0] != V:
                raise self.error(f"{where} {name}: {a.shape[0]} elements for {V} POSITION vertices")
            return a

        sets = []
        while True:
            n = len(sets)
            joints = attribute(f"JOINTS_{n}", ("VEC4",), _INTEGERS, as_float=False)
            weights = attribute(f"WEIGHTS_{n}", ("VEC4",), _FLOAT_OR_NORMALIZED)
            if joints is None and weights is None:
                break
            if joints is None or weights is None:
                raise self.error(f"{where}: JOINTS_{n} and WEIGHTS_{n} must come together")
            J = slot_to_joint.shape[0]
            bad = np.nonzero(joints >= J)
            if bad[0].size:
                raise self.error(f"{where} JOINTS_{n}: index {int(joints[bad][0])} out of range "
                                 f"for skin {skin_index} with {J} joints")
            if np.any(weights < 0):
                raise self.error(f"{where} WEIGHTS_{n}: negative weight {float(weights.min())}")
            sets.append((joints.astype(np.int64), weights))
        if not sets:
            raise self.error(f"{where}: skinned mesh without JOINTS_0/WEIGHTS_0")
        joints = np.concatenate([j for j, _ in sets], axis=1)
        weights = np.concatenate([w for _, w in sets], axis=1)
        total = weights.sum(axis=1)
        unweighted = total == 0
        weights[unweighted, 0] = 1.0  # like three.js: an all-zero row follows its first joint
        weights /= np.where(unweighted, 1.0, total)[:, None]

        faces = self.faces(prim, where, V)
        normals = attribute("NORMAL", ("VEC3",), (5126, 5120, 5122))
        uvs = attribute("TEXCOORD_0", ("VEC2",), (5126, 5121, 5123, 5120, 5122))
        return (points.astype(np.float32), faces, slot_to_joint[joints],
                weights.astype(np.float32),
                None if normals is None else normals.astype(np.float32),
                None if uvs is None else uvs.astype(np.float32))

    def faces(self, prim, where, vertex_count):
        mode = 4 if prim.mode is None else prim.mode
        if mode not in (4, 5, 6):
            raise self.error(f"{where}: mode {mode} ({_MODES.get(mode, 'unknown')}) is not "
                             "supported; only TRIANGLES, TRIANGLE_STRIP and TRIANGLE_FAN")
        if prim.indices is None:
            idx = np.arange(vertex_count, dtype=np.int64)
        else:
            idx = self.accessor(prim.indices, f"{where} indices", ("SCALAR",), _INTEGERS,
                                as_float=False)[:, 0].astype(np.int64)
            if idx.size and idx.max() >= vertex_count:
                raise self.error(f"{where} indices: index {int(idx.max())} out of range for "
                                 f"{vertex_count} vertices")
        if mode == 4:
            if idx.size % 3:
                raise self.error(f"{where} indices: {idx.size} indices is not a multiple of 3")
            return idx.reshape(-1, 3).astype(np.int32)
        k = np.arange(max(idx.size - 2, 0))
        if mode == 5:  # strip: (i, i + 1 + i%2, i + 2 - i%2) keeps the winding
            tri = np.stack([k, k + 1 + k % 2, k + 2 - k % 2], axis=1)
            return idx[tri].astype(np.int32)
        return np.stack([idx[k + 1], idx[k + 2], np.full_like(k, idx[0] if idx.size else 0)],
                        axis=1).astype(np.int32)

    # -- animation -----------------------------------------------------------------------------

    def clip_names(self):
        return [a.name or f"animation_{i}" for i, a in enumerate(self.doc.animations)]

    def choose_clip(self, clip):
        names = self.clip_names()
        if clip is None:
            return 0 if names else None
        if isinstance(clip, (int, np.integer)) and not isinstance(clip, bool):
            if 0 <= clip < len(names):
                return int(clip)
        elif isinstance(clip, str) and clip in names:
            return names.index(clip)
        raise self.error(f"no animation clip {clip!r}; available clips: {names}")

    def channels(self, anim_index):
        """TRS channels [(node, path, keys, values, interpolation)] and the clip's key times.

        Rotation values are ``(w, x, y, z)``; ``weights`` (morph) channels only add key times.
        """
        anim = self.doc.animations[anim_index]
        where = f"animations[{anim_index}]"
        cache, out, times = {}, [], []
        for c, ch in enumerate(anim.channels):
            target = ch.target
            if target is None or target.node is None:
                continue  # extension targets (KHR_animation_pointer)
            node = target.node
            self.item("node", self.doc.nodes, node, f"{where}.channels[{c}].target")
            path = target.path if target.path in _PATH_SIZES else None  # morph weights: keys only
            if path is not None and self.doc.nodes[node].matrix is not None:
                raise self.error(f"{where}.channels[{c}]: animates node {node}, which has a matrix "
                                 "(glTF requires TRS on animated nodes)")
            key = (ch.sampler, path)
            if key not in cache:
                cache[key] = self.sampler(anim_index, ch.sampler, path)
            keys, values, interpolation = cache[key]
            times.append(keys)
            if path is not None:
                out.append((node, path, keys, values, interpolation))
        key_times = np.unique(np.concatenate(times)) if times else np.zeros(1)
        return out, key_times

    def sampler(self, anim_index, sampler_index, path):
        """(keys (K,), values or None when ``path`` is None, interpolation) of one sampler."""
        anim = self.doc.animations[anim_index]
        sam = self.item("sampler", anim.samplers, sampler_index, f"animations[{anim_index}]")
        where = f"animations[{anim_index}].samplers[{sampler_index}]"
        interpolation = sam.interpolation or "LINEAR"
        if interpolation not in _INTERPOLATIONS:
            raise self.error(f"{where}.interpolation: {interpolation!r} is not one of "
                             f"{list(_INTERPOLATIONS)}")
        keys = self.accessor(sam.input, f"{where}.input", ("SCALAR",), (5126,))[:, 0]
        if keys.size == 0:
            raise self.error(f"{where}.input: no keys")
        if np.any(np.diff(keys) <= 0):
            raise self.error(f"{where}.input: key times are not strictly increasing")
        if path is None:
            return keys, None, interpolation
        n = _PATH_SIZES[path]
        types = ("VEC4",) if n == 4 else ("VEC3",)
        components = (5126, 5120, 5121, 5122, 5123) if n == 4 else (5126,)
        values = self.accessor(sam.output, f"{where}.output", types, components)
        per_key = 3 if interpolation == "CUBICSPLINE" else 1
        if values.shape[0] != per_key * keys.size:
            raise self.error(f"{where}.output: {values.shape[0]} values for {keys.size} "
                             f"{interpolation} keys (expected {per_key * keys.size})")
        if n == 4:
            values = values[:, [3, 0, 1, 2]]  # glTF (x, y, z, w) → (w, x, y, z)
            key_values = values[1::3] if per_key == 3 else values
            if not np.all(np.any(key_values != 0, axis=1)):
                raise self.error(f"{where}.output: zero rotation quaternion")
        return keys, values, interpolation


def load(path, *, clip=None):
    """The format's loader: :func:`load_gltf`."""
    return load_gltf(path, clip=clip)


def load_gltf(path, *, clip=None):
    """Load the skinned meshes, skins and one animation clip of a glTF 2.0 file.

    Parameters
    ----------
    path : str or os.PathLike
        ``.gltf`` (embedded base64 or external buffers) or ``.glb``.
    clip : str or int, optional
        Animation to load, by name or index; the first one by default. Unnamed animations are
        called ``animation_{i}``.

    Returns
    -------
    Scene
        ``skeletons[i]`` is ``skins[i]``: its joints plus their ancestor nodes, parents first;
        ``animations[i]`` a :class:`GltfAnimation` of the clip (None without animations).
        One :class:`~dqskin.scene.Mesh` per primitive of every node with a mesh and a skin,
        named after the node (``"node{i}"`` when unnamed; ``"#{i}"`` appended to repeated
        names), ``"{name}/primitive{k}"`` when the mesh has several primitives. Mesh points,
        normals and uvs (TEXCOORD_0, glTF's top-left origin) as stored, float32; results of
        :meth:`Scene.skin` are world space (``output_transforms`` None, geom-bind identity).
        Weights: JOINTS_n/WEIGHTS_n sets concatenated (K = 4·sets), normalized integers
        dequantized, each row divided by its sum; an all-zero row gets weight 1 on its first
        influence (as three.js). ``times`` are the clip's key times in seconds (``[0.]``
        without animation), ``time_codes_per_second`` 1, ``up_axis`` "Y", ``meters_per_unit`` 1.

    Raises
    ------
    ValueError
        Naming the file and the glTF field: unreadable, corrupt or not glTF 2.x; no skinned
        mesh; joint index out of range; negative or NaN weights; accessor count mismatch;
        non-triangle primitives; unknown clip (the message lists the clips).
    """
    r = _Reader(path)
    doc = r.doc
    if not doc.skins:
        raise r.error("no skin (skins is empty)")
    skinned = [i for i, n in enumerate(doc.nodes) if n.mesh is not None and n.skin is not None]
    if not skinned:
        raise r.error("no skinned mesh (no node has both mesh and skin)")
    clip_index = r.choose_clip(clip)

    skeletons, node_orders, slot_maps = [], [], []
    for s in range(len(doc.skins)):
        skel, order, slots = r.skeleton(s)
        skeletons.append(skel)
        node_orders.append(order)
        slot_maps.append(slots)

    meshes = []
    base_names = [r.node_name(i) for i in skinned]
    for node_index, base in zip(skinned, base_names):
        node = doc.nodes[node_index]
        r.item("mesh", doc.meshes, node.mesh, f"nodes[{node_index}].mesh")
        r.item("skin", doc.skins, node.skin, f"nodes[{node_index}].skin")
        name = base if base_names.count(base) == 1 else f"{base}#{node_index}"
        prims = doc.meshes[node.mesh].primitives
        if not prims:
            raise r.error(f"meshes[{node.mesh}].primitives: empty")
        for k in range(len(prims)):
            points, faces, ji, jw, normals, uvs = r.primitive(node.mesh, k, node.skin,
                                                              slot_maps[node.skin])
            meshes.append(Mesh(name=name if len(prims) == 1 else f"{name}/primitive{k}",
                               points=points, faces=faces, joint_indices=ji.astype(np.int32),
                               joint_weights=jw, skeleton=node.skin, skinning_method="lbs",
                               normals=normals, uvs=uvs))

    names = r.clip_names()
    if clip_index is None:
        animations, times = [None] * len(skeletons), np.zeros(1)
    else:
        channels, times = r.channels(clip_index)
        animations = []
        for order in node_orders:
            index = {n: k for k, n in enumerate(order)}
            mine = [(index[node], path, keys, values, interp)
                    for node, path, keys, values, interp in channels if node in index]
            animations.append(GltfAnimation(times, *r.rest_pose(order), mine))
    return Scene(path=os.fspath(path), meshes=meshes, skeletons=skeletons, animations=animations,
                 times=times, time_codes_per_second=1.0, up_axis="Y", meters_per_unit=1.0,
                 clips=names, clip=None if clip_index is None else names[clip_index])
