"""glTF 2.0 loader: skinned meshes, skins and one animation clip as a :class:`dqskin.scene.Scene`.

Reads ``.gltf`` (embedded base64 or external buffers) and ``.glb`` through pygltflib and follows
the glTF 2.0 skinning equation: skinned vertices live in world space, the skinned mesh node's own
transform is ignored, and ::

    jointMatrix[i] = globalTransform(skin.joints[i]) · inverseBindMatrices[i]
    world(v) = Σ_k w_k · jointMatrix[j_k] · v

Each skin becomes a :class:`~dqskin.skeleton.Skeleton` over its joints plus every ancestor node
(the scene-graph path up to the root, ordered parents first), with ``bind = inverse(IBM)`` for the
joints and the rest world transform for the added ancestors (no vertex references them), so
``Skeleton.skinning_transforms`` is exactly the glTF joint matrix.

Morph targets (POSITION, NORMAL, TANGENT) are applied before skinning, as glTF 2.0 §3.7.2.2 says,
by a :class:`GltfMorph` deformer per primitive (``Mesh.deformer``, used by
:meth:`~dqskin.scene.Scene.skin` like USD blend shapes): the clip's ``weights`` channel on the
node (LINEAR, STEP or CUBICSPLINE), else the node's or the mesh's default ``weights``. A mesh node
with morph targets but no skin is loaded too, as a skeleton of its own: the node and its
ancestors, every vertex bound to the node with an identity inverse bind matrix, so its points
follow the node's animated world transform as a glTF viewer draws them.

Files are untrusted input. Before anything is read, the GLB container is checked chunk by chunk,
every JSON member the loader uses is type-checked against the glTF 2.0 schema (references
included), and every accessor's byte range (offset, stride, count, alignment) is checked against
its bufferView and buffer. External buffers must stay inside the asset's folder (``data:`` URIs
are fine). Whatever is wrong surfaces as one :class:`~dqskin.errors.InputError` (a
``ValueError``) "file: glTF field: what is wrong"; pygltflib only ever sees the checked members,
with its warnings silenced.
"""

import base64
import binascii
import json
import math
import os
import re
import struct
import warnings
from collections import Counter
from collections.abc import Sequence
from urllib.parse import unquote, urlsplit

import numpy as np
import numpy.typing as npt

from .. import quat
from ..animation import Animation, Deformer, check_times
from ..errors import InputError
from ..files.inputs import open_input
from ..limits import MAX_INPUT_GIB, check_bytes
from ..scene import Mesh, Scene
from ..skeleton import Skeleton
from ..times import DEFAULT_FPS
from ..validation import FLOAT32_MAX, within_float32
from . import LOADER_SUFFIXES

__all__ = ["SUFFIXES", "GltfAnimation", "GltfMorph", "load", "load_gltf"]

SUFFIXES = LOADER_SUFFIXES["gltf"]
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
_COMPONENT_NAMES = {5120: "BYTE", 5121: "UNSIGNED_BYTE", 5122: "SHORT", 5123: "UNSIGNED_SHORT",
                    5125: "UNSIGNED_INT", 5126: "FLOAT"}
_ACCESSOR_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_GLB_JSON, _GLB_BIN = 0x4E4F534A, 0x004E4942
_READ_ATTRIBUTES = re.compile(r"POSITION|NORMAL|TANGENT|TEXCOORD_0|(JOINTS|WEIGHTS)_[0-9]+")
_MORPH_ATTRIBUTES = ("POSITION", "NORMAL", "TANGENT")
"""Morph-target attributes glTF 2.0 defines (others, e.g. TEXCOORD_n of extensions, are ignored)."""
_WEIGHT_COMPONENTS = (5126, 5120, 5121, 5122, 5123)  # float, or normalized integers


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


def _sample_rate(times, keys, values, interpolation):
    """Time derivative of :func:`_sample` (not for rotations): (F, n) float64.

    LINEAR: the slope of the key interval; CUBICSPLINE: the Hermite polynomial's derivative; STEP:
    zero. At a key the mean of the two sides (one-sided at the first and last key: the clamped
    side is constant); zero outside the key range or with a single key.
    """
    cubic = interpolation == "CUBICSPLINE"
    v = values[1::3] if cubic else values
    n = keys.shape[0]
    out = np.zeros((times.shape[0], v.shape[1]))
    if interpolation == "STEP" or n == 1:
        return out
    for side in ("left", "right"):  # away from keys both sides pick the same interval
        i = np.clip(np.searchsorted(keys, times, side=side) - 1, 0, n - 2)
        dt = (keys[i + 1] - keys[i])[:, None]
        if not cubic:
            out += 0.5 * (v[i + 1] - v[i]) / dt
            continue
        a, b = values[0::3], values[2::3]
        u = np.clip((times[:, None] - keys[i][:, None]) / dt, 0.0, 1.0)
        u2 = u * u
        out += 0.5 * ((6 * u2 - 6 * u) * v[i] / dt + (3 * u2 - 4 * u + 1) * b[i]
                      + (6 * u - 6 * u2) * v[i + 1] / dt + (3 * u2 - 2 * u) * a[i + 1])
    out[(times < keys[0]) | (times > keys[-1])] = 0.0
    return out


Channel = tuple[int, str, np.ndarray, np.ndarray, str]
"""One animated node property: (joint, path, keys (K,), values, interpolation)."""


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

    def __init__(self, key_times: npt.ArrayLike,
                 rest_trs: tuple[np.ndarray, np.ndarray, np.ndarray],
                 matrix_nodes: dict[int, np.ndarray], channels: list[Channel]) -> None:
        self.key_times = np.asarray(key_times, dtype=np.float64)
        self._rest = rest_trs
        self._matrix_nodes = matrix_nodes
        self._channels = channels
        self.linear_trs = all(c[4] == "LINEAR" for c in channels)

    def local_transforms(self, times: npt.ArrayLike) -> np.ndarray:
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


class GltfMorph(Deformer):
    """The morph targets of one glTF primitive, applied before skinning (glTF 2.0 §3.7.2.2)::

        points(t)   = POSITION + Σᵢ wᵢ(t) · targets[i].POSITION
        normals(t)  = NORMAL   + Σᵢ wᵢ(t) · targets[i].NORMAL     (renormalized by the skinner)
        tangents(t) = TANGENT.xyz + Σᵢ wᵢ(t) · targets[i].TANGENT (TANGENT.w, the handedness, kept)

    ``w(t)`` is the clip's ``weights`` channel on the mesh's node, sampled as glTF says (LINEAR,
    STEP, CUBICSPLINE; clamped outside its keys), or the default weights (the node's
    ``weights``, else the mesh's, else zeros) when the clip does not animate them. Velocities are
    exact: ``Σᵢ ẇᵢ(t) · targets[i].POSITION`` with the sampler's own derivative.

    Parameters
    ----------
    points : (V, 3) float32
        Base POSITION, mesh space.
    normals : (V, 3) float32 or None
    tangents : (V, 4) float32 or None
        Base TANGENT ``(x, y, z, w)``.
    offsets : dict str → (T, V, 3) float64
        Per attribute ("POSITION", "NORMAL", "TANGENT") the offsets of the T targets (zeros
        where a target lacks the attribute); attributes no target has are absent.
    default_weights : (T,) float64
    channel : (keys (K,), values (K or 3K, T), interpolation) or None
        The ``weights`` sampler; CUBICSPLINE values are (in-tangent, value, out-tangent) per key.
    name : str
        Names the file and mesh in errors: morphed values beyond float32 range raise
        InputError (a ValueError) naming it, the attribute and the time.

    Attributes
    ----------
    target_count : int
    """

    def __init__(self, points: npt.ArrayLike, normals: np.ndarray | None,
                 tangents: np.ndarray | None, offsets: dict[str, np.ndarray],
                 default_weights: npt.ArrayLike,
                 channel: tuple[np.ndarray, np.ndarray, str] | None = None,
                 name: str = "morph targets") -> None:
        self.name = name
        self.points = np.asarray(points, dtype=np.float32)
        self.normals = normals
        self.tangents = tangents
        self.offsets = offsets
        self.default_weights = np.asarray(default_weights, dtype=np.float64)
        self.channel = channel
        self.target_count = self.default_weights.shape[0]

    def weights(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, T) float64 morph weights at ``times`` (seconds)."""
        t = check_times(times)
        if self.channel is None:
            return np.broadcast_to(self.default_weights, (t.shape[0], self.target_count))
        keys, values, interpolation = self.channel
        return _sample(t, keys, values, interpolation, rotation=False)

    def weight_rates(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, T) float64 ``d weights / dt`` per second (see :func:`_sample_rate`)."""
        t = check_times(times)
        if self.channel is None:
            return np.zeros((t.shape[0], self.target_count))
        return _sample_rate(t, *self.channel)

    def _combine(self, weights: np.ndarray, attribute: str) -> np.ndarray | None:
        """(F, V, 3) float64 ``Σ wᵢ·offsetᵢ`` of one attribute (one matrix product over the
        targets whose weight is not zero at every time), or None when nothing moves."""
        offsets = self.offsets.get(attribute)
        if offsets is None:
            return None
        used = np.nonzero(np.any(weights != 0, axis=0))[0]
        if used.size == 0:
            return None
        flat = offsets[used].reshape(used.size, -1)
        return (weights[:, used] @ flat).reshape((weights.shape[0],) + offsets.shape[1:])

    def _morph(self, base: np.ndarray, attribute: str, times: npt.ArrayLike) -> np.ndarray:
        """(F, V, 3) float32 ``base + Σ wᵢ·offsetᵢ`` of one attribute at ``times``; InputError
        when a value is beyond float32 range."""
        weights = self.weights(times)
        out = np.broadcast_to(np.asarray(base, np.float64), (weights.shape[0],) + base.shape)
        delta = self._combine(weights, attribute)
        if delta is None:
            return out.astype(np.float32)
        out = out + delta
        bad = within_float32(out)
        if bad is not None:
            f = int(np.argmax(~(np.abs(out) <= FLOAT32_MAX).all(axis=(1, 2))))
            raise InputError(f"{self.name}: {attribute} morphed by weights "
                             f"{np.round(weights[f], 6).tolist()} at time "
                             f"{float(check_times(times)[f]):g} is {bad}")
        return out.astype(np.float32)

    def points_at(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, V, 3) float32 morphed points, mesh space."""
        return self._morph(self.points, "POSITION", times)

    def point_velocities_at(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, V, 3) float64 ``d points / dt`` per second."""
        rates = self.weight_rates(times)
        delta = self._combine(rates, "POSITION")
        return np.zeros((rates.shape[0],) + self.points.shape) if delta is None else delta

    def normals_at(self, times: npt.ArrayLike) -> np.ndarray | None:
        """(F, V, 3) float32 morphed normals (not normalized), or None without NORMAL targets."""
        if self.normals is None or "NORMAL" not in self.offsets:
            return None
        return self._morph(self.normals, "NORMAL", times)

    def tangents_at(self, times: npt.ArrayLike) -> np.ndarray | None:
        """(F, V, 3) float32 morphed tangent directions (not normalized), or None without TANGENT
        targets."""
        if self.tangents is None or "TANGENT" not in self.offsets:
            return None
        return self._morph(self.tangents[:, :3], "TANGENT", times)


# -- validation of untrusted files ---------------------------------------------------------------
# Checks raise _Invalid("field: what is wrong"); _Reader prefixes the file name. Each schema
# check is a function (value, field, sizes) -> the value the loader keeps, where ``sizes`` gives
# the length of every array a reference may point into.


class _Invalid(InputError):
    """A glTF file fails validation; the message is ``"field: what is wrong"``."""


def _shown(value):
    """A decoded JSON value as messages show it: scalars verbatim (cut when long), else its kind."""
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return f"an array of {len(value)}"
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _member(field, name):
    return f"{field}.{name}" if field else name


def _integer(minimum=0):
    """Check: an integer ``>= minimum`` (integral numbers such as ``2.0`` count; booleans don't)."""
    def check(value, field, sizes):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Invalid(f"{field}: expected an integer, got {_shown(value)}")
        if value < minimum:
            raise _Invalid(f"{field}: expected an integer >= {minimum}, got {value}")
        return value
    return check


def _ref(array):
    """Check: an index into the document's (or the animation's) ``array``."""
    def check(value, field, sizes):
        index = _integer()(value, field, sizes)
        if index >= sizes[array]:
            raise _Invalid(f"{field}: {index} is out of range ({array} has {sizes[array]} "
                           "entries)")
        return index
    return check


def _one_of(allowed):
    """Check: one of the ``allowed`` constants (returned as spelled there: ``5126.0`` → 5126)."""
    def check(value, field, sizes):
        if isinstance(value, bool) or value not in allowed:
            raise _Invalid(f"{field}: expected one of {list(allowed)}, got {_shown(value)}")
        return allowed[allowed.index(value)]
    return check


def _string(value, field, sizes):
    if not isinstance(value, str):
        raise _Invalid(f"{field}: expected a string, got {_shown(value)}")
    return value


def _boolean(value, field, sizes):
    if not isinstance(value, bool):
        raise _Invalid(f"{field}: expected true or false, got {_shown(value)}")
    return value


def _numbers(n=None):
    """Check: an array of ``n`` (any number when None) finite numbers, returned as floats."""
    def check(value, field, sizes):
        if not isinstance(value, list) or (n is not None and len(value) != n):
            raise _Invalid(f"{field}: expected an array of {'' if n is None else f'{n} '}numbers, "
                           f"got {_shown(value)}")
        out = []
        for k, x in enumerate(value):
            try:
                f = float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) else None
            except OverflowError:  # an integer beyond float range
                f = None
            if f is None or not math.isfinite(f):
                raise _Invalid(f"{field}[{k}]: expected a finite number, got {_shown(x)}")
            out.append(f)
        return out
    return check


def _array(item):
    def check(value, field, sizes):
        if not isinstance(value, list):
            raise _Invalid(f"{field}: expected an array, got {_shown(value)}")
        return [item(v, f"{field}[{k}]", sizes) for k, v in enumerate(value)]
    return check


def _object(fields, required=()):
    """Check an object's ``fields`` (absent or null: left out); other members are dropped."""
    def check(value, field, sizes):
        if not isinstance(value, dict):
            raise _Invalid(f"{field or 'top level'}: expected an object, got {_shown(value)}")
        for name in required:
            if value.get(name) is None:
                raise _Invalid(f"{_member(field, name)}: missing (required by glTF 2.0)")
        return {name: sub(value[name], _member(field, name), sizes)
                for name, sub in fields.items() if value.get(name) is not None}
    return check


def _attributes(value, field, sizes):
    """Check a primitive's attributes (accessor indices); keep those the loader reads."""
    if not isinstance(value, dict):
        raise _Invalid(f"{field}: expected an object, got {_shown(value)}")
    accessor = _ref("accessors")
    checked = {name: accessor(index, f"{field}.{name}", sizes) for name, index in value.items()}
    return {name: index for name, index in checked.items() if _READ_ATTRIBUTES.fullmatch(name)}


def _target(value, field, sizes):
    """Check a morph target (attribute → accessor index); keep POSITION, NORMAL, TANGENT."""
    if not isinstance(value, dict):
        raise _Invalid(f"{field}: expected an object, got {_shown(value)}")
    accessor = _ref("accessors")
    checked = {name: accessor(index, f"{field}.{name}", sizes) for name, index in value.items()}
    return {name: index for name, index in checked.items() if name in _MORPH_ATTRIBUTES}


_SIZE, _POSITIVE = _integer(0), _integer(1)
_SKIN = _object({"joints": _array(_ref("nodes")), "inverseBindMatrices": _ref("accessors"),
                 "name": _string}, required=("joints",))
_NODE = _object({"children": _array(_ref("nodes")), "mesh": _ref("meshes"), "skin": _ref("skins"),
                 "matrix": _numbers(16), "translation": _numbers(3), "rotation": _numbers(4),
                 "scale": _numbers(3), "weights": _numbers(), "name": _string})
_PRIMITIVE = _object({"attributes": _attributes, "indices": _ref("accessors"), "mode": _SIZE,
                      "targets": _array(_target)}, required=("attributes",))
_MESH = _object({"primitives": _array(_PRIMITIVE), "weights": _numbers(), "name": _string},
                required=("primitives",))
_SPARSE = _object({
    "count": _POSITIVE,
    "indices": _object({"bufferView": _ref("bufferViews"), "byteOffset": _SIZE,
                        "componentType": _one_of(_INTEGERS)},
                       required=("bufferView", "componentType")),
    "values": _object({"bufferView": _ref("bufferViews"), "byteOffset": _SIZE},
                      required=("bufferView",))}, required=("count", "indices", "values"))
_ACCESSOR = _object({"bufferView": _ref("bufferViews"), "byteOffset": _SIZE,
                     "componentType": _one_of(tuple(_COMPONENT_DTYPES)), "normalized": _boolean,
                     "count": _POSITIVE, "type": _one_of(tuple(_ACCESSOR_WIDTHS)),
                     "sparse": _SPARSE}, required=("componentType", "count", "type"))
_BUFFER_VIEW = _object({"buffer": _ref("buffers"), "byteOffset": _SIZE, "byteLength": _POSITIVE,
                        "byteStride": _SIZE}, required=("buffer", "byteLength"))
_BUFFER = _object({"uri": _string, "byteLength": _POSITIVE}, required=("byteLength",))
_CHANNEL = _object({"sampler": _ref("samplers"),
                    "target": _object({"node": _ref("nodes"), "path": _string},
                                      required=("path",))}, required=("sampler", "target"))
_SAMPLER = _object({"input": _ref("accessors"), "output": _ref("accessors"),
                    "interpolation": _string}, required=("input", "output"))
_ANIMATION = _object({"channels": _array(_CHANNEL), "samplers": _array(_SAMPLER),
                      "name": _string}, required=("channels", "samplers"))


def _animation(value, field, sizes):
    """An animation's channels index its own samplers."""
    samplers = value.get("samplers") if isinstance(value, dict) else None
    own = dict(sizes, samplers=len(samplers) if isinstance(samplers, list) else 0)
    return _ANIMATION(value, field, own)


_ARRAYS = {"nodes": _NODE, "skins": _SKIN, "meshes": _MESH, "accessors": _ACCESSOR,
           "bufferViews": _BUFFER_VIEW, "buffers": _BUFFER, "animations": _animation}
_DOCUMENT = _object({"asset": _object({"version": _string}, required=("version",)),
                     "extensionsRequired": _array(_string),
                     **{name: _array(item) for name, item in _ARRAYS.items()}},
                    required=("asset",))


def _element_size(kind, component_type):
    """Bytes of one accessor element (matrix columns of 1- and 2-byte components are 4-aligned)."""
    size = np.dtype(_COMPONENT_DTYPES[component_type]).itemsize
    if kind in ("MAT2", "MAT3") and size < 4:
        rows = 2 if kind == "MAT2" else 3
        return rows * (-(-rows * size // 4) * 4)
    return _ACCESSOR_WIDTHS[kind] * size


def _check_view_ranges(doc):
    """Every bufferView lies inside its buffer's byteLength."""
    buffers = doc.get("buffers", [])
    for i, view in enumerate(doc.get("bufferViews", [])):
        start = view.get("byteOffset", 0)
        end, size = start + view["byteLength"], buffers[view["buffer"]]["byteLength"]
        if end > size:
            raise _Invalid(f"bufferViews[{i}]: byteOffset {start} + byteLength "
                           f"{view['byteLength']} = {end} runs past the end of "
                           f"buffers[{view['buffer']}] (byteLength {size})")


def _check_span(field, count_field, views, index, offset, count, layout, strided):
    """``count`` elements from ``offset`` in ``bufferViews[index]`` are aligned and inside it.

    Parameters
    ----------
    field : str
        The object holding ``bufferView`` and ``byteOffset`` (an accessor, a sparse part).
    count_field : str
        The field giving ``count``.
    views : list of dict
        The checked bufferViews.
    index, offset, count : int
    layout : tuple of (str, int, int)
        Element description for messages ("VEC4 of FLOAT"), element size, component size.
    strided : bool
        The bufferView's byteStride applies (accessor data; sparse data is tightly packed).
    """
    what, size, component = layout
    view = views[index]
    start = view.get("byteOffset", 0) + offset
    if start % component:
        raise _Invalid(f"{field}.byteOffset: {offset} puts the data at byte {start} of "
                       f"buffers[{view['buffer']}], not a multiple of the {component}-byte "
                       f"components of {what}")
    stride = (view.get("byteStride") or size) if strided else size
    if stride < size:
        raise _Invalid(f"{field}.bufferView: bufferViews[{index}].byteStride {stride} is smaller "
                       f"than one {what} element ({size} bytes)")
    if stride % component:
        raise _Invalid(f"{field}.bufferView: bufferViews[{index}].byteStride {stride} is not a "
                       f"multiple of the {component}-byte components of {what}")
    length = view["byteLength"]
    if offset >= length:
        raise _Invalid(f"{field}.byteOffset: {offset} is past the end of bufferViews[{index}] "
                       f"({length} bytes)")
    need = offset + stride * (count - 1) + size
    if need > length:
        raise _Invalid(f"{count_field}: {count} elements ({what}, {size} bytes every {stride}) "
                       f"from byteOffset {offset} need {need} bytes; bufferViews[{index}] has "
                       f"{length}")


def _check_accessor_ranges(doc):
    """Every accessor's data (and sparse data) is aligned and inside its bufferView."""
    views = doc.get("bufferViews", [])
    for i, acc in enumerate(doc.get("accessors", [])):
        field, count = f"accessors[{i}]", acc["count"]
        component = np.dtype(_COMPONENT_DTYPES[acc["componentType"]]).itemsize
        layout = (f"{acc['type']} of {_COMPONENT_NAMES[acc['componentType']]}",
                  _element_size(acc["type"], acc["componentType"]), component)
        if "bufferView" in acc:
            _check_span(field, f"{field}.count", views, acc["bufferView"],
                        acc.get("byteOffset", 0), count, layout, strided=True)
        sparse = acc.get("sparse")
        if sparse is None:
            continue
        if sparse["count"] > count:
            raise _Invalid(f"{field}.sparse.count: {sparse['count']} is more than the accessor's "
                           f"count {count}")
        indices, values = sparse["indices"], sparse["values"]
        isize = np.dtype(_COMPONENT_DTYPES[indices["componentType"]]).itemsize
        _check_span(f"{field}.sparse.indices", f"{field}.sparse.count", views,
                    indices["bufferView"], indices.get("byteOffset", 0), sparse["count"],
                    (_COMPONENT_NAMES[indices["componentType"]], isize, isize), strided=False)
        _check_span(f"{field}.sparse.values", f"{field}.sparse.count", views,
                    values["bufferView"], values.get("byteOffset", 0), sparse["count"], layout,
                    strided=False)


def _checked_document(raw):
    """The members of a parsed glTF document that the loader reads, checked against glTF 2.0.

    Parameters
    ----------
    raw : object
        ``json.loads`` of the glTF JSON.

    Returns
    -------
    dict
        Only the checked members (unknown and unused ones dropped, nulls left out), every
        reference in range and every accessor's bytes inside its bufferView and buffer.

    Raises
    ------
    _Invalid
    """
    if not isinstance(raw, dict):
        raise _Invalid(f"top level: expected an object, got {_shown(raw)}")
    sizes = {}
    for name in _ARRAYS:  # arrays first, so that no reference blames a broken array
        items = raw.get(name)
        if items is not None and not isinstance(items, list):
            raise _Invalid(f"{name}: expected an array, got {_shown(items)}")
        sizes[name] = len(items or ())
    doc = _DOCUMENT(raw, "", sizes)
    _check_view_ranges(doc)
    _check_accessor_ranges(doc)
    return doc


def _glb_chunks(data: bytes) -> tuple[bytes, bytes | None]:
    """(JSON chunk, BIN chunk or None) of a GLB container, checked chunk by chunk."""
    if len(data) < 12:
        raise _Invalid(f"GLB header: the file has {len(data)} bytes, fewer than the 12-byte header")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise _Invalid(f"GLB header: container version {version}; only version 2 (glTF 2.0) is "
                       "supported")
    if length > len(data):
        raise _Invalid(f"GLB header: declares {length} bytes but the file has {len(data)} "
                       "(truncated?)")
    chunks: list[tuple[int, bytes]] = []
    offset = 12
    while offset < length:
        if offset + 8 > length:
            raise _Invalid(f"GLB chunk {len(chunks)}: its 8-byte header at byte {offset} runs "
                           f"past the end ({length} bytes)")
        size, kind = struct.unpack_from("<II", data, offset)
        start, offset = offset + 8, offset + 8 + size
        if offset > length:
            raise _Invalid(f"GLB chunk {len(chunks)}: {size} bytes from byte {start} run past the "
                           f"end ({length} bytes)")
        chunks.append((kind, data[start:offset]))
    if not chunks or chunks[0][0] != _GLB_JSON:
        raise _Invalid("GLB chunk 0: the first chunk must be the JSON chunk")
    bins = [k for k, (kind, _) in enumerate(chunks) if kind == _GLB_BIN]
    if bins not in ([], [1]):
        raise _Invalid(f"GLB chunk {bins[-1]}: one BIN chunk is allowed, right after the JSON "
                       "chunk")  # other chunk types are ignored, as the GLB spec asks
    return chunks[0][1], chunks[1][1] if bins else None


def _parse_json(text):
    """``json.loads`` of UTF-8 bytes, every failure as :class:`_Invalid`."""
    try:
        return json.loads(text.rstrip(b"\0").decode("utf-8"))
    except UnicodeDecodeError as e:
        raise _Invalid(f"JSON: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except RecursionError:
        raise _Invalid("JSON: nested too deeply") from None
    except ValueError as e:
        raise _Invalid(f"JSON: not valid JSON ({e})") from None


class _Reader:
    """Checked access to one glTF document: accessors, nodes, skins, meshes, clips."""

    def __init__(self, path, max_input_gib=MAX_INPUT_GIB):
        self.path = os.fspath(path)
        self.name = os.path.basename(self.path)
        self.max_input_gib = max_input_gib
        try:
            with open_input(self.path) as f:
                data = f.read()
        except (OSError, ValueError) as e:  # ValueError: a NUL in the path
            raise self.error(f"cannot read file ({getattr(e, 'strerror', None) or e})") from None
        try:
            text, blob = _glb_chunks(data) if data[:4] == b"glTF" else (data, None)
            self.raw = _parse_json(text)  # the whole document (materials: readers.materials)
            checked = _checked_document(self.raw)
        except _Invalid as e:
            raise self.error(str(e)) from None
        self.doc = self._document(checked, blob)
        self.checked = checked  # the members pygltflib drops (node weights) are read from here
        version = self.doc.asset.version
        if not version.startswith("2."):
            raise self.error(f"asset.version {version!r}: only glTF 2.x is supported")
        for ext in self.doc.extensionsRequired or ():
            if ext in _UNSUPPORTED_EXTENSIONS:
                raise self.error(f"extensionsRequired: {ext} is not supported")
        self._buffers = {}
        self.parents = self._parents()

    def _document(self, checked, blob):
        """pygltflib's objects for the checked members, its warnings kept from the user.

        Everything pygltflib warns about in the file (GLB container version, odd chunks, bad
        members) was checked before, so on this input its warnings carry nothing to report.
        (Imported here: a USD bake never pays for it.)
        """
        import pygltflib

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                doc = pygltflib.GLTF2.from_json(json.dumps(checked), infer_missing=True)
            except Exception as e:  # not expected on checked members; still the file's fault
                raise self.error(f"pygltflib cannot decode the document ({type(e).__name__}: "
                                 f"{e})") from None
        doc.set_binary_blob(blob)
        return doc

    def error(self, message):
        """``InputError("file: message")`` (a ValueError), on one line."""
        return InputError(f"{self.name}: {message}".replace("\n", " "))

    def item(self, kind, items, index, where):
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise self.error(f"{where}: {kind} {index!r} out of range ({len(items)} {kind}s)")
        return items[index]

    # -- binary data -------------------------------------------------------------------------

    def _buffer(self, index):
        """Bytes of ``buffers[index]``, at least byteLength of them (read once)."""
        if index not in self._buffers:
            buf = self.doc.buffers[index]
            data = self._buffer_bytes(index, buf.uri)
            if len(data) < buf.byteLength:
                raise self.error(f"buffers[{index}]: {len(data)} bytes of data, byteLength is "
                                 f"{buf.byteLength}")
            self._buffers[index] = data
        return self._buffers[index]

    def _buffer_bytes(self, index, uri):
        if uri is None:
            data = self.doc.binary_blob()
            if data is None or index != 0:
                raise self.error(f"buffers[{index}]: no uri and no GLB binary chunk")
            return data
        field = f"buffers[{index}].uri"
        if uri.startswith("data:"):
            head, _, payload = uri.partition(",")
            if not head.endswith(";base64"):
                raise self.error(f"{field}: data URI is not base64")
            try:
                return base64.b64decode(payload, validate=True)
            except (binascii.Error, ValueError) as e:
                raise self.error(f"{field}: bad base64 ({e})") from None
        return self._read_external(field, uri)

    def _external_path(self, field, uri):
        """Local file a buffer's ``uri`` names, refused when it leaves the asset's folder.

        Relative paths (percent-encoded, as glTF asks) and ``file:`` URIs are resolved lexically
        against the folder of the glTF file, as a viewer resolves URLs; ``..``, absolute paths
        and ``file:`` URIs leading elsewhere are refused, and other schemes are not fetched.
        """
        try:
            parts = urlsplit(uri)
        except ValueError:
            parts = None
        if (parts is None or parts.scheme.lower() not in ("", "file")
                or parts.netloc not in ("", "localhost")):
            raise self.error(f"{field}: {uri!r} is neither a relative file path nor a data: URI")
        folder = os.path.abspath(os.path.dirname(self.path))
        file = os.path.normpath(os.path.join(folder, unquote(parts.path if parts.scheme else uri)))
        try:
            inside = os.path.commonpath([folder, file]) == folder
        except ValueError:  # another drive
            inside = False
        if not inside:
            raise self.error(f"{field}: {uri!r} resolves outside the asset's folder; buffers must "
                             "be files next to the glTF file or in folders below it")
        return file

    def _read_external(self, field, uri):
        file = self._external_path(field, uri)
        try:
            os.stat(file)
            with open_input(file) as f:
                return f.read()
        except InputError as e:  # not a regular file
            reason = str(e).removeprefix(f"{file}: ")
            raise self.error(f"{field}: {uri!r} is {reason}") from None
        except (OSError, ValueError) as e:  # ValueError: a NUL in the name
            raise self.error(f"{field}: {uri!r} cannot be read "
                             f"({getattr(e, 'strerror', None) or e})") from None

    def _elements(self, view_index, offset, count, width, dtype, strided=True):
        """(count, width) elements of ``dtype`` at ``offset`` in a bufferView, copied.

        The byte range was checked against the bufferView and buffer on load; ``strided``
        applies the bufferView's byteStride (sparse data is tightly packed).
        """
        view = self.doc.bufferViews[view_index]
        data = self._buffer(view.buffer)
        size = width * dtype.itemsize
        stride = (view.byteStride or size) if strided else size
        start = (view.byteOffset or 0) + offset
        return np.ndarray((count, width), dtype, buffer=data, offset=start,
                          strides=(stride, dtype.itemsize)).copy()

    def accessor(self, index, where, types, components, *, as_float=True, normalized=False):
        """Accessor data (count, n), dequantized to float64 unless ``as_float`` is False.
        ``normalized``: integer components must have ``normalized: true`` (the spec allows only
        normalized integers there)."""
        acc = self.item("accessor", self.doc.accessors, index, where)
        where = f"{where} (accessor {index})"
        if acc.type not in types:
            raise self.error(f"{where}: type {acc.type}, expected {' or '.join(types)}")
        if acc.componentType not in components:
            raise self.error(f"{where}: componentType {acc.componentType} not allowed here")
        if normalized and acc.componentType != 5126 and not acc.normalized:
            name = _COMPONENT_NAMES.get(acc.componentType, acc.componentType)
            raise self.error(f"{where}: {name} components must be normalized here (glTF allows "
                             "only FLOAT or normalized integers; set \"normalized\": true)")
        width, dtype = _TYPE_SIZES[acc.type], np.dtype(_COMPONENT_DTYPES[acc.componentType])
        if acc.bufferView is None:  # zeros (and sparse values): as many as the count asks
            check_bytes(acc.count * width * 8, f"{self.name}: {where}: count {acc.count}",
                        self.max_input_gib)
            out = np.zeros((acc.count, width), dtype)
        else:
            out = self._elements(acc.bufferView, acc.byteOffset or 0, acc.count, width, dtype)
        sp = acc.sparse
        if sp is not None:
            idx = self._elements(sp.indices.bufferView, sp.indices.byteOffset or 0, sp.count, 1,
                                 np.dtype(_COMPONENT_DTYPES[sp.indices.componentType]),
                                 strided=False)[:, 0]
            vals = self._elements(sp.values.bufferView, sp.values.byteOffset or 0, sp.count,
                                  width, dtype, strided=False)
            if idx.max() >= acc.count:
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
        """(N,) parent node of every node, -1 for roots; one parent each, no cycles (O(N))."""
        nodes = self.doc.nodes
        parents = [-1] * len(nodes)
        for i, node in enumerate(nodes):
            for c in node.children or ():
                self.item("node", nodes, c, f"nodes[{i}].children")
                if parents[c] >= 0:
                    raise self.error(f"nodes[{c}] is a child of both nodes {parents[c]} and {i}")
                parents[c] = i
        state = [0] * len(nodes)  # 0: not seen, 1: on the current walk up, 2: reaches a root
        for i in range(len(nodes)):
            walk, cur = [], i
            while cur >= 0 and state[cur] == 0:
                state[cur] = 1
                walk.append(cur)
                cur = parents[cur]
            if cur >= 0 and state[cur] == 1:
                raise self.error(f"nodes[{i}]: cycle in the node hierarchy")
            for n in walk:
                state[n] = 2
        return np.array(parents, dtype=np.int64)

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
        if not np.sum(r * r) > 0:  # zero, or so small that its squared norm underflows
            raise self.error(f"{where}.rotation: zero quaternion")
        return t, r[[3, 0, 1, 2]], s, None

    def node_local(self, index):
        t, r, s, m = self.node_trs(index)
        m = m if m is not None else _trs_matrices(t, r, s)
        if not np.all(np.isfinite(m)):
            raise self.error(f"nodes[{index}]: translation, rotation or scale out of range "
                             "(the transform overflows)")
        return m

    def rest_pose(self,
                  nodes: Sequence[int]
                  ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], dict[int, np.ndarray]]:
        """Static ((J, 3) t, (J, 4) r (w, x, y, z), (J, 3) s) and {k: matrix} of ``nodes``."""
        t, r, s = np.zeros((len(nodes), 3)), np.zeros((len(nodes), 4)), np.ones((len(nodes), 3))
        r[:, 0] = 1.0
        matrices: dict[int, np.ndarray] = {}
        for k, n in enumerate(nodes):
            tk, rk, sk, m = self.node_trs(n)
            if m is None:
                t[k], r[k], s[k] = tk, rk, sk
            else:
                matrices[k] = m
        return (t, r, s), matrices

    def skeleton(self, skin_index, clip=None):
        """Skeleton of one skin, driven by ``clip`` (``(channels, key_times)`` of
        :meth:`channels`, or None for the rest pose), and the map skin joint slot → skeleton
        joint index."""
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
        return self.node_skeleton(joints, ibm, where, skin.name or f"skin{skin_index}", clip)

    def node_skeleton(self, joints, ibm, where, name, clip):
        """Skeleton over the nodes ``joints`` (binds ``inverse(ibm)``) and their ancestors, and
        the map joint slot → skeleton joint index (see :meth:`skeleton`). An unskinned mesh node
        is ``joints=[node]`` with ``ibm`` identity: its points then follow the node's world
        transform, as glTF renders a mesh without a skin."""
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
            if not np.all(np.isfinite(bind[index[node]])):
                raise self.error(f"{where}.inverseBindMatrices[{slot}]: singular matrix")
        overflow = np.nonzero(~np.all(np.isfinite(bind), axis=(1, 2)))[0]
        if overflow.size:
            raise self.error(f"{where}: the rest world transform of nodes[{order[overflow[0]]}] "
                             "overflows (translations or scales out of range)")
        names = [self.node_name(n) for n in order]
        repeated = Counter(names)  # glTF allows repeated node names; joint names are unique
        names = [m if repeated[m] == 1 else f"{m}#{n}" for m, n in zip(names, order)]
        try:
            skel = Skeleton(names, parents, bind, local, name=name,
                            animation=None if clip is None else self.animation(order, *clip))
        except ValueError as e:  # what Skeleton rejects (singular binds, float32 overflow)
            raise self.error(f"{where}: {e}") from None
        return skel, order, np.array([index[n] for n in joints], dtype=np.int32)

    def animation(self, order, channels, key_times):
        """The :class:`GltfAnimation` of the channels that drive the nodes of ``order``."""
        index = {n: k for k, n in enumerate(order)}
        mine = [(index[node], path, keys, values, interp)
                for node, path, keys, values, interp in channels if node in index]
        return GltfAnimation(key_times, *self.rest_pose(order), mine)

    # -- meshes --------------------------------------------------------------------------------

    def primitive(self, mesh_index, prim_index, skin_index, slot_to_joint):
        """:class:`Mesh` fields of one primitive: points, faces, joint_indices, joint_weights,
        normals, tangents, uvs. ``skin_index`` None: an unskinned mesh, every vertex bound to
        the single joint ``slot_to_joint[0]`` (JOINTS_n/WEIGHTS_n not read)."""
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

        sets = [] if skin_index is not None else [(np.zeros((V, 1), np.int64), np.ones((V, 1)))]
        while skin_index is not None:
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
        tangents = attribute("TANGENT", ("VEC4",), (5126, 5120, 5122))
        uvs = attribute("TEXCOORD_0", ("VEC2",), (5126, 5121, 5123, 5120, 5122))
        return dict(points=points.astype(np.float32), faces=faces,
                    joint_indices=slot_to_joint[joints].astype(np.int32),
                    joint_weights=weights.astype(np.float32),
                    normals=None if normals is None else normals.astype(np.float32),
                    tangents=None if tangents is None else tangents.astype(np.float32),
                    uvs=None if uvs is None else uvs.astype(np.float32))

    # -- morph targets -------------------------------------------------------------------------

    def target_count(self, mesh_index):
        """Number of morph targets of ``meshes[mesh_index]`` (the same in every primitive)."""
        prims = self.checked["meshes"][mesh_index]["primitives"]
        counts = sorted({len(p.get("targets", ())) for p in prims})
        if len(counts) > 1:
            raise self.error(f"meshes[{mesh_index}].primitives: {counts} morph targets; glTF "
                             "requires the same number in every primitive")
        return counts[0] if counts else 0

    def default_weights(self, node_index, mesh_index, count):
        """(T,) float64 morph weights without animation: the node's, else the mesh's, else 0."""
        for field, obj in ((f"nodes[{node_index}].weights", self.checked["nodes"][node_index]),
                           (f"meshes[{mesh_index}].weights", self.checked["meshes"][mesh_index])):
            w = obj.get("weights")
            if w is not None:
                if len(w) != count:
                    raise self.error(f"{field}: {len(w)} weights for {count} morph targets")
                big = [k for k, x in enumerate(w) if not abs(x) <= FLOAT32_MAX]
                if big:
                    raise self.error(f"{field}[{big[0]}]: {w[big[0]]:g} is beyond float32 range")
                return np.asarray(w, dtype=np.float64)
        return np.zeros(count)

    def morph_offsets(self, mesh_index, prim_index, vertex_count):
        """{attribute: (T, V, 3) float64 offsets} of one primitive's morph targets, for the
        attributes (POSITION, NORMAL, TANGENT) some target has; zeros where a target lacks it."""
        targets = self.checked["meshes"][mesh_index]["primitives"][prim_index].get("targets", [])
        where = f"mesh {mesh_index} primitive {prim_index}"
        out = {}
        for name in _MORPH_ATTRIBUTES:
            if not any(name in t for t in targets):
                continue
            check_bytes(len(targets) * vertex_count * 3 * 8,
                        f"{self.name}: meshes[{mesh_index}].primitives[{prim_index}].targets: "
                        f"{len(targets)} {name} targets × {vertex_count} vertices",
                        self.max_input_gib)
            offsets = np.zeros((len(targets), vertex_count, 3))
            for k, target in enumerate(targets):
                if name not in target:
                    continue
                a = self.accessor(target[name], f"{where} targets[{k}].{name}", ("VEC3",),
                                  (5126, 5120, 5122), normalized=name != "POSITION")
                if a.shape[0] != vertex_count:
                    raise self.error(f"{where} targets[{k}].{name}: {a.shape[0]} elements for "
                                     f"{vertex_count} POSITION vertices")
                offsets[k] = a
            out[name] = offsets
        return out

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
        """TRS channels [(node, path, keys, values, interpolation)], the clip's key times and its
        morph-weight channels {node: (keys, values (K or 3K, T), interpolation)}.

        Rotation values are ``(w, x, y, z)``; channels of other paths only add key times.
        """
        anim = self.doc.animations[anim_index]
        where = f"animations[{anim_index}]"
        cache, out, times, weights = {}, [], [], {}
        for c, ch in enumerate(anim.channels):
            target = ch.target
            if target is None or target.node is None:
                continue  # extension targets (KHR_animation_pointer)
            node = target.node
            self.item("node", self.doc.nodes, node, f"{where}.channels[{c}].target")
            path = target.path if target.path in _PATH_SIZES or target.path == "weights" else None
            if path in _PATH_SIZES and self.doc.nodes[node].matrix is not None:
                raise self.error(f"{where}.channels[{c}]: animates node {node}, which has a matrix "
                                 "(glTF requires TRS on animated nodes)")
            count = 0
            if path == "weights":
                mesh = self.doc.nodes[node].mesh
                count = 0 if mesh is None else self.target_count(mesh)
                if count == 0:
                    raise self.error(f"{where}.channels[{c}]: animates the morph weights of "
                                     f"nodes[{node}], which has no mesh with morph targets")
            key = (ch.sampler, path, count)
            if key not in cache:
                cache[key] = self.sampler(anim_index, ch.sampler, path, count)
            keys, values, interpolation = cache[key]
            times.append(keys)
            if path == "weights":
                weights[node] = (keys, values, interpolation)
            elif path is not None:
                out.append((node, path, keys, values, interpolation))
        key_times = np.unique(np.concatenate(times)) if times else np.zeros(1)
        return out, key_times, weights

    def sampler(self, anim_index, sampler_index, path, targets=0):
        """(keys (K,), values or None when ``path`` is None, interpolation) of one sampler;
        ``"weights"`` values are (K or 3K, ``targets``)."""
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
        per_key = 3 if interpolation == "CUBICSPLINE" else 1
        if path == "weights":
            values = self.accessor(sam.output, f"{where}.output", ("SCALAR",), _WEIGHT_COMPONENTS,
                                   normalized=True)
            if values.shape[0] != per_key * keys.size * targets:
                raise self.error(f"{where}.output: {values.shape[0]} values for {keys.size} "
                                 f"{interpolation} keys of {targets} morph weights (expected "
                                 f"{per_key * keys.size * targets})")
            return keys, values.reshape(-1, targets), interpolation
        n = _PATH_SIZES[path]
        types = ("VEC4",) if n == 4 else ("VEC3",)
        components = (5126, 5120, 5121, 5122, 5123) if n == 4 else (5126,)
        values = self.accessor(sam.output, f"{where}.output", types, components,
                               normalized=True)
        if values.shape[0] != per_key * keys.size:
            raise self.error(f"{where}.output: {values.shape[0]} values for {keys.size} "
                             f"{interpolation} keys (expected {per_key * keys.size})")
        if n == 4:
            values = values[:, [3, 0, 1, 2]]  # glTF (x, y, z, w) → (w, x, y, z)
            key_values = values[1::3] if per_key == 3 else values
            if not np.all(np.any(key_values != 0, axis=1)):
                raise self.error(f"{where}.output: zero rotation quaternion")
        return keys, values, interpolation


def load(path: str | os.PathLike, *, clip: str | int | None = None,
         max_input_gib: float = MAX_INPUT_GIB) -> Scene:
    """The format's loader: :func:`load_gltf`."""
    return load_gltf(path, clip=clip, max_input_gib=max_input_gib)


def load_gltf(path: str | os.PathLike, *, clip: str | int | None = None,
              max_input_gib: float = MAX_INPUT_GIB) -> Scene:
    """Load the skinned meshes, skins and one animation clip of a glTF 2.0 file.

    Parameters
    ----------
    path : str or os.PathLike
        ``.gltf`` (embedded base64 or external buffers) or ``.glb``.
    clip : str or int, optional
        Animation to load, by name or index; the first one by default. Unnamed animations are
        called ``animation_{i}``.
    max_input_gib : float
        Largest array the file may ask for (:func:`dqskin.limits.check_bytes`): a primitive's
        morph targets, held as (targets, V, 3) float64 offsets; an accessor without a
        bufferView (its count of zeros, read as float64).

    Returns
    -------
    Scene
        ``skeletons[i]`` is ``skins[i]``: its joints plus their ancestor nodes, parents first,
        named after the nodes (``"node{i}"`` when unnamed; ``"#{i}"`` appended to names repeated
        within the skeleton);
        ``animations[i]`` a :class:`GltfAnimation` of the clip (None without animations).
        Then, for every unskinned node whose mesh has morph targets, one more skeleton: the
        node and its ancestors, named after the node, binding the node with an identity matrix.
        One :class:`~dqskin.scene.Mesh` per primitive of every node with a mesh and a skin or
        morph targets, named after the node (``"node{i}"`` when unnamed; ``"#{i}"`` appended to
        repeated names), ``"{name}/primitive{k}"`` when the mesh has several primitives. Mesh
        points, normals, tangents (TANGENT, ``(x, y, z, w)``) and uvs (TEXCOORD_0, glTF's
        top-left origin) as stored, float32 (the base shape: morph targets are the mesh's
        ``deformer``, a :class:`GltfMorph`); results of :meth:`Scene.skin` are world space
        in every space but "skeleton", which is the world too (``output_transforms`` and
        ``world_transforms`` None, geom-bind identity).
        Weights: JOINTS_n/WEIGHTS_n sets concatenated (K = 4·sets), normalized integers
        dequantized, each row divided by its sum; an all-zero row gets weight 1 on its first
        influence (as three.js). ``times`` are the clip's key times in seconds (``[0.]``
        without animation), ``time_codes_per_second`` 1, ``up_axis`` "Y", ``meters_per_unit`` 1,
        ``frame_rate`` 24 (:data:`dqskin.times.DEFAULT_FPS`).

    Raises
    ------
    InputError
        (a ValueError) The only exception a bad file raises, on one line naming the file and the
        glTF field: unreadable, corrupt GLB container or JSON, not glTF 2.x; a member of the wrong
        type, missing or out of range; accessor data misaligned, overlapping (byteStride smaller
        than an element) or past its bufferView or buffer; a buffer URI outside the asset's folder
        or unreadable; no skinned or morphing mesh; joint index out of range; negative or NaN
        weights; accessor count mismatch (morph targets included); primitives of one mesh with
        different numbers of morph targets; default or animated morph weights not one per target; a
        ``weights`` channel on a node without morph targets; non-triangle primitives; unknown clip
        (the message lists the clips).
    LimitError
        Morph targets, or an accessor without a bufferView (zeros, sparse), beyond
        ``max_input_gib``.
    """
    with np.errstate(all="ignore"):  # overflow is checked where it matters, as ValueError
        return _load(path, clip, max_input_gib)


def _loaded_nodes(r: "_Reader") -> tuple[list[int], list[str], list[int]]:
    """The nodes :func:`load_gltf` loads (a mesh with a skin or morph targets), their names
    (``Mesh.name`` before a ``/primitive{k}`` suffix) and each glTF mesh's morph target count."""
    doc = r.doc
    targets = [r.target_count(m) for m in range(len(doc.meshes))]
    loaded = [i for i, n in enumerate(doc.nodes)
              if n.mesh is not None and (n.skin is not None or targets[n.mesh])]
    base_names = [r.node_name(i) for i in loaded]
    repeated = Counter(base_names)
    names = [b if repeated[b] == 1 else f"{b}#{i}" for i, b in zip(loaded, base_names)]
    return loaded, names, targets


def _primitive_name(name: str, k: int, count: int) -> str:
    return name if count == 1 else f"{name}/primitive{k}"


def mesh_primitives(r: "_Reader") -> list[tuple[str, int, int]]:
    """``(Mesh.name, glTF mesh index, primitive index)`` of every mesh :func:`load_gltf`
    loads from the document of ``r``."""
    loaded, names, _ = _loaded_nodes(r)
    out = []
    for node_index, name in zip(loaded, names):
        mesh = r.doc.nodes[node_index].mesh
        count = len(r.doc.meshes[mesh].primitives)
        out += [(_primitive_name(name, k, count), mesh, k) for k in range(count)]
    return out


def _load(path: str | os.PathLike, clip: str | int | None, max_input_gib: float) -> Scene:
    """:func:`load_gltf` without its floating-point error state."""
    r = _Reader(path, max_input_gib)
    doc = r.doc
    loaded, names, targets = _loaded_nodes(r)
    if not loaded:
        raise r.error("no skinned mesh (no node has both mesh and skin) and no mesh with morph "
                      "targets")
    clip_index = r.choose_clip(clip)
    channels = weight_channels = None
    if clip_index is not None:
        *channels, weight_channels = r.channels(clip_index)

    skeletons, slot_maps = [], []
    for s in range(len(doc.skins)):
        skel, _, slots = r.skeleton(s, channels)
        skeletons.append(skel)
        slot_maps.append(slots)

    meshes = []
    for node_index, name in zip(loaded, names):
        node = doc.nodes[node_index]
        skeleton = node.skin
        if skeleton is None:  # unskinned morphing mesh: rigid on its node, a skeleton of its own
            skel, _, slots = r.node_skeleton([node_index], np.eye(4)[None],
                                             f"nodes[{node_index}]", name, channels)
            skeleton = len(skeletons)
            skeletons.append(skel)
            slot_maps.append(slots)
        prims = doc.meshes[node.mesh].primitives
        if not prims:
            raise r.error(f"meshes[{node.mesh}].primitives: empty")
        count = targets[node.mesh]
        default = r.default_weights(node_index, node.mesh, count) if count else np.zeros(0)
        channel = (weight_channels or {}).get(node_index)
        for k in range(len(prims)):
            fields = r.primitive(node.mesh, k, node.skin, slot_maps[skeleton])
            deformer = None
            if count:
                deformer = GltfMorph(fields["points"], fields["normals"], fields["tangents"],
                                     r.morph_offsets(node.mesh, k, len(fields["points"])),
                                     default, channel,
                                     name=f"{r.name}: meshes[{node.mesh}].primitives[{k}]")
            try:
                meshes.append(Mesh(name=_primitive_name(name, k, len(prims)),
                                   skeleton=skeleton, skinning_method="lbs", deformer=deformer,
                                   **fields))
            except ValueError as e:
                raise r.error(f"mesh {node.mesh} primitive {k}: {e}") from None

    clips = r.clip_names()
    times = np.zeros(1) if channels is None else channels[1]
    return Scene(path=os.fspath(path), meshes=meshes, skeletons=skeletons, times=times,
                 time_codes_per_second=1.0, up_axis="Y", meters_per_unit=1.0, clips=clips,
                 frame_rate=DEFAULT_FPS,
                 clip=None if clip_index is None else clips[clip_index])
