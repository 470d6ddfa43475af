"""Load UsdSkel skinned prims from ``.usd``/``.usda``/``.usdc``/``.usdz`` into a :class:`Scene`.

UsdSkel resolves the bindings (``UsdSkel.Cache`` over every ``SkelRoot``, instance proxies
included); dqskin does the rest: forward kinematics, skinning and the move to each prim's space
all run on the engine. Conventions at this boundary: USD's row-vector ``Gf`` matrices are
transposed to the column-vector convention, ``primvars:skel:skinningMethod`` maps
``"classicLinear"`` → ``"lbs"`` and ``"dualQuaternion"`` → ``"dqs"``.

What a loaded :class:`~dqskin.scene.Mesh` holds for a skinned ``UsdGeom.PointBased`` prim:

- ``points``: rest points (the default value, else the earliest time sample), prim space.
- ``faces``: polygons fan-triangulated (holes dropped, ``leftHanded`` winding flipped so every
  triangle is counter-clockwise); the original ``faceVertexCounts``/``faceVertexIndices`` are
  kept. Curves and points have no faces.
- ``joint_indices``/``joint_weights``: ``(V, K)`` with ``K = elementSize``, indices remapped from
  the prim's ``skel:joints`` order to its skeleton's order, constant (rigid) influences repeated
  on every point; weights as authored (UsdSkel never renormalizes).
- ``normals``: ``primvars:normals`` or ``normals``, vertex/varying (one per point) or
  faceVarying (``normal_vertex`` = ``faceVertexIndices``); constant/uniform normals are not
  skinned (None).
- ``output_transforms``: skeleton space → prim space, ``inverse(gprimLocalToWorld) @
  skelLocalToWorld`` (what ``UsdSkel.BakeSkinning`` applies) as a
  :class:`~dqskin.animation.TransformTrack` keyed at every time sample of the transforms above
  the two prims (exact there; between samples interpolated as joints are, which is USD's own
  interpolation for translate, orient and scale ops); None when identity.
- ``deformer``: blend shapes (offsets, normalOffsets, pointIndices, inbetweens) driven by the
  skeleton's ``SkelAnimation.blendShapeWeights``, and time-sampled rest points, with their
  analytic time derivative; None when there are neither.

Skinned prims that are not point-based (``Sphere``, ``Cube``, …, bound with constant
influences) have no points for a :class:`Scene`; :func:`load_rigid_prims` returns them and
:func:`rigid_transforms` computes their per-time local transform with the engine, as
``UsdSkel.BakeSkinning`` bakes them into ``xformOp:transform``.
"""

import os
import re
from dataclasses import dataclass

import numpy as np
from pxr import Tf, Usd, UsdGeom, UsdSkel, Vt

from ..animation import Animation, Deformer, TransformTrack, segment_rates
from ..scene import Mesh, Scene
from ..skeleton import Skeleton
from ..skinning import skin_points
from .usd_xform import XformChain, read_local_to_world

__all__ = ["SKINNING_METHODS", "SUFFIXES", "load", "RigidPrim", "UsdSkelAnimation",
           "load_rigid_prims", "load_usd", "rigid_transforms"]

SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
"""USD files :func:`load` reads."""
"""File extensions :func:`load_usd` reads."""

SKINNING_METHODS = {"classicLinear": "lbs", "dualQuaternion": "dqs"}
"""``primvars:skel:skinningMethod`` tokens → dqskin method names."""


def _tf_message(exc):
    """The first diagnostic text of a ``Tf.ErrorException``, on one line."""
    for block in re.split(r"\n\s*Error in ", str(exc)):
        if " : '" in block:
            text = block.split(" : '", 1)[1].rstrip().rstrip("'")
            return " ".join(text.split())
    return " ".join(str(exc).split())


def _matrices(gf_matrices):
    """Row-vector ``Gf.Matrix4d`` array → ``(N, 4, 4)`` float64, column-vector convention."""
    return np.array(gf_matrices, dtype=np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)


def _rest_value(attr):
    """The value USD resolves before any animation: the earliest time sample when there are
    samples (they win over the default at every time), else the default (None if unauthored)."""
    if not attr or not attr.HasAuthoredValue():
        return None
    if attr.GetNumTimeSamples() > 0:
        return attr.Get(Usd.TimeCode.EarliestTime())
    return attr.Get(Usd.TimeCode.Default())


class UsdSkelAnimation(Animation):
    """Joint transforms (and blend-shape weights) of one skeleton, sampled through UsdSkel.

    ``UsdSkel.SkeletonQuery.ComputeJointLocalTransforms`` samples the ``SkelAnimation``
    (translations, rotations, scales; interpolated between time samples as USD does) and maps the
    animation's joint order onto the skeleton's, giving undriven joints their rest transform.

    Parameters
    ----------
    skel_query : UsdSkel.SkeletonQuery
        A valid query whose skeleton has an animation source.
    stage : Usd.Stage
        Kept alive as long as the animation is.

    Attributes
    ----------
    key_times : (K,) float64
        Time codes of the joint-transform and blend-shape-weight samples.
    name : str
        The ``SkelAnimation`` prim path.
    blend_shape_names : list of str
        The animation's ``blendShapes`` tokens (order of :meth:`blend_shape_weights`).
    """

    def __init__(self, skel_query, stage):
        self._stage = stage
        self._query = skel_query
        self._anim = skel_query.GetAnimQuery()
        self.name = str(self._anim.GetPrim().GetPath())
        self.joint_count = len(skel_query.GetJointOrder())
        self.blend_shape_names = [str(n) for n in self._anim.GetBlendShapeOrder()]
        keys = set(self._anim.GetJointTransformTimeSamples())
        keys.update(self._anim.GetBlendShapeWeightTimeSamples())
        self.key_times = np.array(sorted(keys), dtype=np.float64)

    def local_transforms(self, times):
        """Parent-relative joint transforms, skeleton joint order.

        Parameters
        ----------
        times : (F,) float
            USD time codes.

        Returns
        -------
        (F, J, 4, 4) float64, column-vector convention.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        out = np.empty((t.shape[0], self.joint_count, 4, 4))
        for i, ti in enumerate(t):
            xf = self._query.ComputeJointLocalTransforms(Usd.TimeCode(float(ti)))
            if xf is None or len(xf) != self.joint_count:
                raise ValueError(f"{self.name}: cannot compute joint transforms at time {ti}")
            out[i] = _matrices(xf)
        return out

    def blend_shape_weight_rates(self, times):
        """``(F, S)`` float64 time derivatives of :meth:`blend_shape_weights` (USD interpolates
        the weights linearly between time samples)."""
        attr = UsdSkel.Animation(self._anim.GetPrim()).GetBlendShapeWeightsAttr()
        keys = np.asarray(attr.GetTimeSamples() if attr else [], dtype=np.float64)
        S = len(self.blend_shape_names)
        if keys.size < 2 or S == 0:
            return np.zeros((np.atleast_1d(times).shape[0], S))
        return np.stack(segment_rates(keys, lambda k: self.blend_shape_weights([keys[k]])[0],
                                      times))

    def blend_shape_weights(self, times):
        """``(F, S)`` float32 weights of :attr:`blend_shape_names` at ``times`` (0 when unset)."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        out = np.zeros((t.shape[0], len(self.blend_shape_names)), dtype=np.float32)
        for i, ti in enumerate(t):
            w = self._anim.ComputeBlendShapeWeights(Usd.TimeCode(float(ti)))
            if w is not None and len(w) == out.shape[1]:
                out[i] = np.asarray(w, dtype=np.float32)
        return out


@dataclass
class RigidPrim:
    """A skinned prim without points, which UsdSkel moves rigidly (constant influences).

    Attributes
    ----------
    name : str
        Prim path.
    skeleton : int
        Index into ``scene.skeletons``.
    joint_indices, joint_weights : (K,) int32, float32
        The prim's influences, skeleton joint order.
    geom_bind_transform : (4, 4) float64
        Prim (geometry) space → skeleton bind space, column-vector convention.
    skinning_method : {"lbs", "dqs"}
    parent_transforms : dqskin.animation.TransformTrack or None
        Skeleton space → the parent prim's space; identity when None.
    """

    name: str
    skeleton: int
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    geom_bind_transform: np.ndarray
    skinning_method: str
    parent_transforms: TransformTrack | None = None


class _Loader:
    """One file's loading state; every error names the file and the prim."""

    def __init__(self, path):
        self.path = os.fspath(path)
        self.stage = self._open()
        self.skeleton_index = {}  # skeleton prim path -> index into skeletons
        self.skeletons, self.animations = [], []
        self.meshes, self.rigid = [], []

    def fail(self, where, what):
        raise ValueError(f"{self.path}: {where}: {what}")

    def _open(self):
        if not os.path.isfile(self.path):
            raise ValueError(f"{self.path}: no such file")
        ext = os.path.splitext(self.path)[1].lower()
        if ext not in SUFFIXES:
            raise ValueError(f"{self.path}: not a USD file (extension {ext!r}, expected one of "
                             f"{', '.join(SUFFIXES)})")
        try:
            stage = Usd.Stage.Open(self.path, Usd.Stage.LoadAll)
        except Tf.ErrorException as exc:
            raise ValueError(f"{self.path}: cannot open as USD: {_tf_message(exc)}") from None
        if stage is None:
            raise ValueError(f"{self.path}: cannot open as USD")
        return stage

    # -- skeletons -------------------------------------------------------------------------

    def skeleton(self, cache, skel):
        """Index of ``skel`` (a UsdSkel.Skeleton) in the scene, loading it the first time."""
        key = str(skel.GetPrim().GetPath())
        if key in self.skeleton_index:
            return self.skeleton_index[key]
        joints = skel.GetJointsAttr().Get() or []
        ok, reason = UsdSkel.Topology(joints).Validate()
        if not ok:
            self.fail(key, f"invalid joint topology: {reason}")
        query = cache.GetSkelQuery(skel)
        if not query:
            self.fail(key, "UsdSkel cannot build a skeleton query (check joints, bindTransforms "
                           "and restTransforms sizes)")
        J = len(joints)
        bind = skel.GetBindTransformsAttr().Get()
        if J and (bind is None or len(bind) != J):
            self.fail(key, f"bindTransforms has {0 if bind is None else len(bind)} matrices for "
                           f"{J} joints")
        rest = query.ComputeJointLocalTransforms(Usd.TimeCode.Default(), True)
        world = _matrices(UsdGeom.Imageable(skel.GetPrim())
                          .ComputeLocalToWorldTransform(Usd.TimeCode.Default()))[0]
        try:
            skeleton = Skeleton([str(j) for j in joints], query.GetTopology().GetParentIndices(),
                                _matrices(bind) if J else None,
                                _matrices(rest) if rest is not None and len(rest) == J else None,
                                name=key, world_transform=world)
        except ValueError as exc:
            raise ValueError(f"{self.path}: {exc}") from None
        anim = query.GetAnimQuery()
        self.skeleton_index[key] = len(self.skeletons)
        self.skeletons.append(skeleton)
        self.animations.append(UsdSkelAnimation(query, self.stage) if anim else None)
        return self.skeleton_index[key]

    # -- skinned prims ---------------------------------------------------------------------

    def check_influences(self, where, q):
        """Check jointIndices/jointWeights agree in interpolation, element size and count."""
        ipv, wpv = q.GetJointIndicesPrimvar(), q.GetJointWeightsPrimvar()
        interp = (ipv.GetInterpolation(), wpv.GetInterpolation())
        if interp[0] != interp[1]:
            self.fail(where, f"jointIndices interpolation {interp[0]!r} != jointWeights "
                             f"interpolation {interp[1]!r}")
        if interp[0] not in ("constant", "vertex"):
            self.fail(where, f"joint influence interpolation {interp[0]!r}: must be 'constant' "
                             "or 'vertex'")
        size = (ipv.GetElementSize(), wpv.GetElementSize())
        if size[0] != size[1]:
            self.fail(where, f"jointIndices elementSize {size[0]} != jointWeights elementSize "
                             f"{size[1]}")
        if size[0] < 1:
            self.fail(where, f"joint influence elementSize {size[0]}: must be positive")
        idx_raw, wts_raw = ipv.Get(Usd.TimeCode.Default()), wpv.Get(Usd.TimeCode.Default())
        n_idx = 0 if idx_raw is None else len(idx_raw)
        n_wts = 0 if wts_raw is None else len(wts_raw)
        if n_idx != n_wts:
            self.fail(where, f"{n_idx} jointIndices but {n_wts} jointWeights")
        if interp[0] == "constant" and n_idx != size[0]:
            self.fail(where, f"{n_idx} constant joint influences for elementSize {size[0]}")
        if n_idx % size[0]:
            self.fail(where, f"{n_idx} joint influences is not a multiple of elementSize "
                             f"{size[0]}")

    def influences(self, where, q, point_count, skeleton):
        """``(V, K)`` int32 joint indices in skeleton order and float32 weights."""
        ipv = q.GetJointIndicesPrimvar()
        interp, K = ipv.GetInterpolation(), ipv.GetElementSize()
        n_idx = len(ipv.Get(Usd.TimeCode.Default()) or [])
        rigid = interp == "constant"
        expect = K if rigid else K * point_count
        if n_idx != expect:
            self.fail(where, f"{n_idx} joint influences, expected {expect} ({interp} "
                             f"interpolation, elementSize {K}, {point_count} points)")
        result = q.ComputeJointInfluences(Usd.TimeCode.Default())
        if not result:
            self.fail(where, "UsdSkel cannot compute the joint influences")
        idx = np.asarray(result[0], dtype=np.int64).reshape(-1, K)
        wts = np.asarray(result[1], dtype=np.float32).reshape(-1, K)
        if not np.all(np.isfinite(wts)):
            self.fail(where, "jointWeights has NaN or infinite weights")
        if wts.size and wts.min() < 0:
            self.fail(where, f"jointWeights has a negative weight {float(wts.min())}")
        skel = self.skeletons[skeleton]
        local_order = q.GetJointOrder()
        if local_order is not None:
            names = [str(n) for n in local_order]
            index = {n: i for i, n in enumerate(skel.joint_names)}
            missing = [n for n in names if n not in index]
            if missing:
                self.fail(where, f"skel:joints names {missing[0]!r}, not a joint of "
                                 f"{skel.name}")
            to_skel = np.array([index[n] for n in names], dtype=np.int64)
            limit, what = len(names), "skel:joints"
        else:
            to_skel, limit, what = None, skel.joint_count, f"skeleton {skel.name}"
        if idx.size and (idx.min() < 0 or idx.max() >= limit):
            bad = int(idx.min()) if idx.min() < 0 else int(idx.max())
            self.fail(where, f"joint index {bad} out of range for the {limit} joints of {what}")
        if to_skel is not None:
            idx = to_skel[idx]
        if rigid:
            idx = np.repeat(idx, point_count, axis=0)
            wts = np.repeat(wts, point_count, axis=0)
        return idx.astype(np.int32), wts

    def faces(self, where, mesh, point_count):
        """Fan triangles, and the original counts and indices (None for non-meshes)."""
        if not mesh:
            return np.zeros((0, 3), np.int32), None, None
        counts = _rest_value(mesh.GetFaceVertexCountsAttr())
        indices = _rest_value(mesh.GetFaceVertexIndicesAttr())
        counts = np.zeros(0, np.int64) if counts is None else np.asarray(counts, np.int64)
        indices = np.zeros(0, np.int64) if indices is None else np.asarray(indices, np.int64)
        if counts.size and counts.min() < 0:
            self.fail(where, "faceVertexCounts has a negative count")
        if counts.sum() != indices.size:
            self.fail(where, f"faceVertexCounts sum to {int(counts.sum())} but there are "
                             f"{indices.size} faceVertexIndices")
        if indices.size and (indices.min() < 0 or indices.max() >= point_count):
            bad = int(indices.min()) if indices.min() < 0 else int(indices.max())
            self.fail(where, f"faceVertexIndices has index {bad} out of range for "
                             f"{point_count} points")
        keep = counts >= 3
        holes = _rest_value(mesh.GetHoleIndicesAttr())
        if holes is not None and len(holes):
            h = np.asarray(holes, np.int64)
            keep[h[(h >= 0) & (h < counts.size)]] = False
        ntri = np.where(keep, counts - 2, 0)
        start = np.cumsum(counts) - counts
        face = np.repeat(np.arange(counts.size), ntri)
        k = np.arange(face.size) - np.repeat(np.cumsum(ntri) - ntri, ntri)
        first = start[face]
        tris = np.stack([indices[first], indices[first + k + 1], indices[first + k + 2]], axis=1)
        if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
            tris = tris[:, ::-1]
        return (np.ascontiguousarray(tris, dtype=np.int32), counts.astype(np.int32),
                indices.astype(np.int32))

    def normals(self, where, prim, point_count, face_vertex_indices):
        """Rest normals and their vertex map, or (None, None)."""
        pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
        if pv and pv.HasAuthoredValue():
            values, interp = pv.ComputeFlattened(Usd.TimeCode.Default()), pv.GetInterpolation()
            if values is None:
                values = pv.ComputeFlattened(Usd.TimeCode.EarliestTime())
        else:
            pb = UsdGeom.PointBased(prim)
            values, interp = _rest_value(pb.GetNormalsAttr()), pb.GetNormalsInterpolation()
        if values is None or len(values) == 0:
            return None, None
        n = np.asarray(values, dtype=np.float32).reshape(-1, 3)
        if interp in ("vertex", "varying") and n.shape[0] == point_count:
            return n, None
        if interp == "faceVarying" and face_vertex_indices is not None:
            if n.shape[0] != face_vertex_indices.size:
                self.fail(where, f"{n.shape[0]} faceVarying normals for "
                                 f"{face_vertex_indices.size} face vertices")
            return n, face_vertex_indices.copy()
        if interp in ("vertex", "varying", "faceVarying"):
            self.fail(where, f"{n.shape[0]} {interp} normals for {point_count} points")
        return None, None

    def method(self, where, q):
        """The dqskin name of the prim's ``primvars:skel:skinningMethod``."""
        method = str(q.GetSkinningMethod())
        if method not in SKINNING_METHODS:
            self.fail(where, f"unknown primvars:skel:skinningMethod {method!r} (expected "
                             f"{' or '.join(map(repr, SKINNING_METHODS))})")
        return SKINNING_METHODS[method]

    def load_prim(self, q, skeleton, skel_prim):
        """A skinned point-based prim → :class:`Mesh`."""
        prim = q.GetPrim()
        where = str(prim.GetPath())
        self.check_influences(where, q)
        method = self.method(where, q)
        points_attr = UsdGeom.PointBased(prim).GetPointsAttr()
        rest = _rest_value(points_attr)
        if rest is None or len(rest) == 0:
            self.fail(where, "no points")
        points = np.asarray(rest, dtype=np.float32).reshape(-1, 3)
        if not np.all(np.isfinite(points)):
            self.fail(where, "points has NaN or infinite coordinates")
        V = points.shape[0]
        idx, wts = self.influences(where, q, V, skeleton)
        mesh = UsdGeom.Mesh(prim)
        tris, counts, fvi = self.faces(where, mesh, V)
        normals, normal_vertex = self.normals(where, prim, V, fvi)
        st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
        uvs = None
        if st and st.HasAuthoredValue():
            flat = st.ComputeFlattened(Usd.TimeCode.Default())
            if flat is not None and len(flat):
                uvs = np.asarray(flat, dtype=np.float32).reshape(-1, 2)
        geom_bind = _matrices(q.GetGeomBindTransform(Usd.TimeCode.Default()))[0]
        if not np.all(np.isfinite(geom_bind)):
            self.fail(where, "primvars:skel:geomBindTransform has NaN or infinite entries")
        deform = _RestDeformer.build(self, where, q, skeleton, points_attr, points, normals,
                                     normal_vertex)
        self.meshes.append(Mesh(
            name=where, points=points, faces=tris, joint_indices=idx, joint_weights=wts,
            skeleton=skeleton, geom_bind_transform=geom_bind,
            skinning_method=method, normals=normals,
            normal_vertex=normal_vertex,
            output_transforms=_output_transforms(self, where, skel_prim, prim),
            deformer=deform,
            face_vertex_counts=counts, face_vertex_indices=fvi, uvs=uvs))

    def load_rigid(self, q, skeleton, skel_prim):
        """A skinned prim without points (Sphere, Cube, ...): moved as a whole by UsdSkel."""
        prim = q.GetPrim()
        where = str(prim.GetPath())
        self.check_influences(where, q)
        if not q.IsRigidlyDeformed():
            self.fail(where, "vertex joint influences on a prim without points")
        method = self.method(where, q)
        idx, wts = self.influences(where, q, 1, skeleton)
        geom_bind = _matrices(q.GetGeomBindTransform(Usd.TimeCode.Default()))[0]
        parent = prim.GetParent()
        self.rigid.append(RigidPrim(
            name=where, skeleton=skeleton, joint_indices=idx[0], joint_weights=wts[0],
            geom_bind_transform=geom_bind, skinning_method=method,
            parent_transforms=_output_transforms(self, where, skel_prim, parent)))

    # -- the whole file --------------------------------------------------------------------

    def load(self):
        predicate = Usd.TraverseInstanceProxies()
        roots = [UsdSkel.Root(p) for p in self.stage.Traverse(predicate) if p.IsA(UsdSkel.Root)]
        if not roots:
            raise ValueError(f"{self.path}: no SkelRoot prim")
        cache = UsdSkel.Cache()
        seen = set()
        for root in roots:
            cache.Populate(root, predicate)
            for binding in cache.ComputeSkelBindings(root, predicate):
                skel = binding.GetSkeleton()
                targets = [q for q in binding.GetSkinningTargets()
                           if str(q.GetPrim().GetPath()) not in seen]
                if not skel or not targets:
                    continue
                skel_index = self.skeleton(cache, skel)
                for q in targets:
                    seen.add(str(q.GetPrim().GetPath()))
                    if UsdGeom.PointBased(q.GetPrim()):
                        self.load_prim(q, skel_index, skel.GetPrim())
                    else:
                        self.load_rigid(q, skel_index, skel.GetPrim())
        if not self.meshes:
            raise ValueError(f"{self.path}: no skinned point-based prim under "
                             f"{', '.join(str(r.GetPrim().GetPath()) for r in roots)}")
        return Scene(path=self.path, meshes=self.meshes, skeletons=self.skeletons,
                     animations=self.animations, times=self.times(),
                     time_codes_per_second=float(self.stage.GetTimeCodesPerSecond()),
                     up_axis=str(UsdGeom.GetStageUpAxis(self.stage)),
                     meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(self.stage)))

    def times(self):
        """The stage's start..end time codes, else every sample that drives the skinning."""
        st = self.stage
        if st.HasAuthoredTimeCodeRange():
            start, end = st.GetStartTimeCode(), st.GetEndTimeCode()
            return np.arange(start, max(start, end) + 0.5, 1.0, dtype=np.float64)
        keys = set()
        for anim in self.animations:
            if anim is not None:
                keys.update(anim.key_times.tolist())
        for m in self.meshes:
            keys.update(st.GetPrimAtPath(m.name).GetAttribute("points").GetTimeSamples())
        return np.array(sorted(keys) or [0.0], dtype=np.float64)


def _output_transforms(loader, where, skel_prim, gprim):
    """Skeleton space → gprim space as an :class:`XformChain`, or None when it is the identity
    at every time."""
    track = XformChain(read_local_to_world(skel_prim), read_local_to_world(gprim),
                       name=f"{loader.path}: {where}")
    try:
        m = track.at(track.key_times)
    except ValueError as exc:
        loader.fail(where, str(exc).split(": ")[-1])
    if np.allclose(m, np.eye(4), rtol=0, atol=1e-12) and track.key_times.shape[0] == 1:
        return None
    return track


def _add_at(dst, idx, delta):
    """``dst[:, idx] += delta`` over a frame axis, repeated indices adding up (as UsdSkel)."""
    if idx is None:
        dst += delta
    elif np.unique(idx).size == idx.size:
        dst[:, idx] += delta
    else:
        np.add.at(dst, (slice(None), idx), delta)


class _RestDeformer(Deformer):
    """Per-time rest points/normals: time-sampled points, then blend shapes (UsdSkel order).

    Sub-shape weights (primary and inbetweens, extrapolation included) come from
    ``UsdSkel.BlendShapeQuery.ComputeSubShapeWeights``; offsets are added with NumPy, vectorized
    over frames. ``normalOffsets`` use the same ``pointIndices``; face-varying normals take the
    offset of their vertex.

    Velocities are exact: USD interpolates points and blend-shape weights linearly between time
    samples (:func:`~dqskin.animation.segment_rates`), and each blend shape's sub-shape weights are
    piecewise linear in its weight, between the sub-shapes' own weights (the zero shape at 0,
    inbetweens, the primary at 1).
    """

    def __init__(self, points_attr, points, normals, normal_vertex):
        self.points_attr = points_attr
        self.animated_points = points_attr.GetNumTimeSamples() > 0
        self.points = points
        self.normals = normals
        self.normal_vertex = normal_vertex
        self.animation = None
        self.shape_from_anim = None  # prim blend shape → animation weight column (-1: none)
        self.query = None
        # per sub-shape: (point indices or None, offsets (n, 3), normal offsets or None), or None
        # for the zero shape UsdSkel puts at weight 0
        self.sub_shapes = []
        # per prim blend shape: (sub-shape indices, their weights), sorted by weight
        self.knots = []

    @classmethod
    def build(cls, loader, where, q, skeleton, points_attr, points, normals, normal_vertex):
        """The deformer of one prim, or None when its rest points never change."""
        d = cls(points_attr, points, normals, normal_vertex)
        anim = loader.animations[skeleton]
        if q.HasBlendShapes() and anim is not None and anim.blend_shape_names:
            d.setup_blend_shapes(loader, where, q, anim)
        return d if d.animated_points or any(d.sub_shapes) else None

    def setup_blend_shapes(self, loader, where, q, anim):
        """Read the prim's blend shapes; weights will come from ``anim``."""
        prim = q.GetPrim()
        order = [str(n) for n in q.GetBlendShapeOrder()]
        column = {n: i for i, n in enumerate(anim.blend_shape_names)}
        self.shape_from_anim = np.array([column.get(n, -1) for n in order], dtype=np.int64)
        if np.all(self.shape_from_anim < 0):
            return
        bsq = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim))
        if not bsq or bsq.GetNumBlendShapes() != len(order):
            loader.fail(where, f"skel:blendShapes names {len(order)} shapes but "
                               f"skel:blendShapeTargets resolves to "
                               f"{bsq.GetNumBlendShapes() if bsq else 0}")
        V = self.points.shape[0]
        point_indices = bsq.ComputeBlendShapePointIndices()
        offsets = bsq.ComputeSubShapePointOffsets()
        for s in range(bsq.GetNumSubShapes()):
            shape = bsq.GetBlendShapeIndex(s)
            target = bsq.GetBlendShape(shape)
            name = str(target.GetPrim().GetPath())
            idx = np.asarray(point_indices[shape], dtype=np.int64)
            off = np.asarray(offsets[s], dtype=np.float32).reshape(-1, 3)
            if off.shape[0] == 0:  # the implicit rest shape at weight 0
                self.sub_shapes.append(None)
                self._add_knot(shape, s, 0.0)
                continue
            count = idx.size if idx.size else V
            if off.shape[0] != count:
                loader.fail(name, f"{off.shape[0]} offsets for {count} points")
            if idx.size and (idx.min() < 0 or idx.max() >= V):
                loader.fail(name, f"pointIndices out of range for the {V} points of {where}")
            inbetween = bsq.GetInbetween(s)
            self._add_knot(shape, s, inbetween.GetWeight() if inbetween else 1.0)
            nrm = (inbetween.GetNormalOffsets() if inbetween
                   else _rest_value(target.GetNormalOffsetsAttr()))
            nrm = None if nrm is None or len(nrm) == 0 else np.asarray(nrm, np.float32)
            if nrm is not None and nrm.shape[0] != count:
                loader.fail(name, f"{nrm.shape[0]} normalOffsets for {count} points")
            self.sub_shapes.append((idx if idx.size else None, off, nrm))
        self.query = bsq
        self.animation = anim

    def _add_knot(self, shape, sub, weight):
        while len(self.knots) <= shape:
            self.knots.append(([], []))
        subs, weights = self.knots[shape]
        k = int(np.searchsorted(weights, weight))
        subs.insert(k, sub)
        weights.insert(k, float(weight))

    def sub_shape_rates(self, times):
        """``(F, S_sub)`` float64 time derivatives of :meth:`sub_shape_weights`."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        anim_w = self.animation.blend_shape_weights(t)
        anim_rate = self.animation.blend_shape_weight_rates(t)
        out = np.zeros((t.shape[0], len(self.sub_shapes)))
        for shape, (subs, knots) in enumerate(self.knots):
            col = self.shape_from_anim[shape]
            if col < 0:
                continue
            w, rate = anim_w[:, col], anim_rate[:, col]
            if len(subs) == 1:  # no inbetweens: the primary's weight is the shape's weight
                out[:, subs[0]] = rate
                continue
            k = np.clip(np.searchsorted(knots, w, side="right") - 1, 0, len(knots) - 2)
            span = np.diff(knots)[k]
            rows = np.arange(t.shape[0])
            out[rows, np.asarray(subs)[k + 1]] += rate / span
            out[rows, np.asarray(subs)[k]] -= rate / span
        return out

    def point_velocities_at(self, times):
        """``(F, V, 3)`` float64 ``d points / dt`` per time code, prim space."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        V = self.points.shape[0]
        vel = np.zeros((t.shape[0], V, 3))
        if self.animated_points:
            keys = np.asarray(self.points_attr.GetTimeSamples(), dtype=np.float64)
            vel += np.stack(segment_rates(keys, lambda k: np.asarray(
                self.points_attr.Get(Usd.TimeCode(float(keys[k]))), np.float64).reshape(V, 3), t))
        if self.sub_shapes:
            rate = self.sub_shape_rates(t)
            for s, sub in enumerate(self.sub_shapes):
                if sub is not None:
                    _add_at(vel, sub[0], rate[:, s, None, None] * sub[1][None])
        return vel

    def sub_shape_weights(self, times):
        """``(F, S_sub)`` float32 sub-shape weights at ``times``."""
        F = times.shape[0]
        out = np.zeros((F, len(self.sub_shapes)), dtype=np.float32)
        anim_w = self.animation.blend_shape_weights(times)
        cols = self.shape_from_anim
        for f in range(F):
            w = np.where(cols >= 0, anim_w[f][np.maximum(cols, 0)], 0.0).astype(np.float32)
            sub_w, _, sub_idx = self.query.ComputeSubShapeWeights(Vt.FloatArray.FromNumpy(w))
            sub = np.asarray(sub_idx, dtype=np.int64)
            np.add.at(out[f], sub, np.asarray(sub_w, dtype=np.float32))
        return out

    def points_at(self, times):
        """``(F, V, 3)`` float32 rest points with blend shapes applied, prim space."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if self.animated_points:
            pts = np.stack([np.asarray(self.points_attr.Get(Usd.TimeCode(float(ti))),
                                       dtype=np.float32).reshape(-1, 3) for ti in t])
            if pts.shape[1] != self.points.shape[0]:
                raise ValueError(f"{self.points_attr.GetPath()}: point count changes over time")
        else:
            pts = np.broadcast_to(self.points, (t.shape[0],) + self.points.shape).copy()
        if self.sub_shapes:
            w = self.sub_shape_weights(t)
            for s, sub in enumerate(self.sub_shapes):
                if sub is None:
                    continue
                idx, off, _ = sub
                _add_at(pts, idx, w[:, s, None, None] * off[None])
        return pts

    def normals_at(self, times):
        """``(F, N, 3)`` float32 rest normals with blend-shape normal offsets (not normalized), or
        None without normals."""
        if self.normals is None:
            return None
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        V = self.points.shape[0]
        nrm = np.broadcast_to(self.normals, (t.shape[0],) + self.normals.shape).copy()
        if any(s is not None and s[2] is not None for s in self.sub_shapes):
            w = self.sub_shape_weights(t)
            per_vertex = np.zeros((t.shape[0], V, 3), dtype=np.float32)
            for s, sub in enumerate(self.sub_shapes):
                if sub is None or sub[2] is None:
                    continue
                idx, _, noff = sub
                _add_at(per_vertex, idx, w[:, s, None, None] * noff[None])
            nrm += per_vertex if self.normal_vertex is None else per_vertex[:, self.normal_vertex]
        return nrm


def load_usd(path):
    """Load every skinned point-based prim of a USD file.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.usd``, ``.usda``, ``.usdc`` or ``.usdz`` file with one or more ``SkelRoot`` prims.

    Returns
    -------
    Scene
        One :class:`~dqskin.scene.Mesh` per skinned ``UsdGeom.PointBased`` prim (named by prim
        path), one :class:`~dqskin.skeleton.Skeleton` per bound ``Skeleton`` prim (joint names
        are the ``joints`` tokens, bind transforms world-space, rest transforms local), one
        :class:`UsdSkelAnimation` or None per skeleton; ``times`` are the stage's start..end time
        codes (step 1), else every animation/points sample, else ``[0.]``; the stage's
        ``timeCodesPerSecond``, ``upAxis`` and ``metersPerUnit``.

    Raises
    ------
    ValueError
        Missing, unreadable or non-USD file; no ``SkelRoot`` or no skinned point-based prim;
        invalid joint topology or bind transforms; joint influences with mismatched
        interpolation, element size or count, out-of-range indices, NaN or negative weights;
        invalid face topology; normals whose count fits no interpolation. The message names the
        file and the prim.
    """
    return _Loader(path).load()


def load(path, *, clip=None):
    """:func:`load_usd` with the signature every format's loader has (USD has one animation per
    skeleton, so ``clip`` must be None)."""
    if clip is not None:
        raise ValueError(f"{path}: --clip applies to glTF files; USD has one animation per "
                         "skeleton")
    return load_usd(path)


def load_rigid_prims(scene):
    """The rigidly skinned prims without points of a scene loaded by :func:`load_usd`.

    Parameters
    ----------
    scene : Scene
        Its ``path`` is read again; skeleton indices refer to ``scene.skeletons``.

    Returns
    -------
    list of RigidPrim
    """
    loader = _Loader(scene.path)
    loader.load()
    index = {s.name: i for i, s in enumerate(scene.skeletons)}
    out = []
    for r in loader.rigid:
        name = loader.skeletons[r.skeleton].name
        if name not in index:
            raise ValueError(f"{scene.path}: {r.name}: skeleton {name} is not in the scene")
        r.skeleton = index[name]
        out.append(r)
    return out


def rigid_transforms(scene, prim, times, method=None, *, device=None, interp="trs"):
    """Local transforms of a rigidly skinned prim, skinned by the engine.

    The skinned transform is recovered exactly from four skinned points (origin and the three
    unit axes of the prim's space): with one set of influences for every point, LBS and DQS
    (scale/shear residual included) are affine maps.

    Parameters
    ----------
    scene : Scene
    prim : RigidPrim
    times : (F,) float
    method : {"lbs", "dqs", "blend"} or None
        None uses the prim's own ``skinning_method``; "blend" mixes half and half.
    interp : str
        Joint interpolation (:data:`dqskin.motion.INTERPOLATIONS`), as for the meshes.

    Returns
    -------
    (F, 4, 4) float64
        Prim space → parent space, column-vector convention (``xformOp:transform``, transposed).
    """
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    x = scene.skinning_transforms(t, prim.skeleton, device=device, interp=interp)
    frame = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    idx = np.tile(prim.joint_indices, (4, 1))
    wts = np.tile(prim.joint_weights, (4, 1))
    meth = method or prim.skinning_method
    q = skin_points(frame, idx, wts, x, meth, geom_bind_transform=prim.geom_bind_transform,
                    blend_weights=np.full(4, 0.5) if meth == "blend" else None, device=device)
    q = q.astype(np.float64).reshape(t.shape[0], 4, 3)
    m = np.tile(np.eye(4), (t.shape[0], 1, 1))
    m[:, :3, 3] = q[:, 0]
    m[:, :3, :3] = (q[:, 1:] - q[:, :1]).transpose(0, 2, 1)
    return m if prim.parent_transforms is None else prim.parent_transforms.at(t) @ m
