"""The one skinning path of the engine: every caller's meshes go through :func:`skin_scene`.

:meth:`dqskin.Scene.skin` (and :meth:`~dqskin.Scene.skin_chunks`, the bakes, the clip workers,
the compare report) call :func:`skin_scene`; its batches of many meshes and :class:`dqskin.Crowd`
skin through :func:`dqskin.crowd.skin_batch`, the rigidly bound USD prims through
:func:`rigid_transforms`. The steps, for given
:class:`~dqskin.options.SkinOptions`:

1. each skeleton's local transforms sampled and checked (:meth:`dqskin.Scene.local_transforms`),
   forward kinematics, and the joint motion when velocities are asked;
2. the meshes grouped into batches: every mesh of a method in one batch (one FK launch for
   every skeleton, one skinning launch per method: :class:`~dqskin.crowd.MeshBatch`) when
   :func:`one_launch` allows it, else a batch of one per mesh (its own
   :class:`~dqskin.Skinner`, the output transform applied in the kernel);
3. per batch: points, normals, tangents, velocities, and the chosen space's transform
   (:func:`space_track`).
"""

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from ._warp import resolve_device
from .animation import check_times
from .crowd import BATCH_METHODS, JointBatch, MeshBatch, skin_batch
from .errors import InputError
from .motion import moved_velocities, per_second, skinning_transforms_with_derivative
from .options import Method, SkinOptions
from .skinning import skin_points
from .spaces import space_track

if TYPE_CHECKING:
    from .readers.usd import RigidPrim
    from .scene import Mesh, Scene

__all__ = ["POSE_BLOCK_BYTES", "POSE_BLOCK_CHUNKS", "SkinnedFrames", "chunk_skinner",
           "one_launch", "rigid_transforms", "skin_scene"]


@dataclass
class SkinnedFrames:
    """What :meth:`dqskin.Scene.skin` returns, per mesh name.

    Attributes
    ----------
    times : (F,) float64
    points : dict name → (F, V, 3) float32
    normals : dict name → (F, N, 3) float32
        Unit normals (meshes with normals, when asked).
    velocities : dict name → (F, V, 3) float32
        Length units per second (when asked).
    tangents : dict name → (F, V, 3) float32
        Unit tangent directions (meshes with tangents, when asked).
    """

    times: np.ndarray
    points: dict = field(default_factory=dict)
    normals: dict = field(default_factory=dict)
    velocities: dict = field(default_factory=dict)
    tangents: dict = field(default_factory=dict)


def one_launch(scene: "Scene", options: SkinOptions) -> bool:
    """Whether ``scene``'s meshes are skinned in one launch per method: more than one mesh,
    every method batchable (:data:`~dqskin.crowd.BATCH_METHODS`), no tangents, and UsdSkel's
    sign rule (the batch layout sorts influences for it)."""
    return (len(scene.meshes) > 1 and not options.tangents
            and options.sign_reference == "largest_weight"
            and all(options.method_of(m) in BATCH_METHODS for m in scene.meshes))


def skin_scene(scene: "Scene", times: npt.ArrayLike, options: SkinOptions,
               cache: dict[Any, Any]) -> SkinnedFrames:
    """Skin every mesh of ``scene`` at ``times`` (checked) with ``options``; ``cache`` keeps
    the uploaded skinners and batches between calls (:attr:`dqskin.Scene._skinners`)."""
    t = check_times(times)
    return _skin(_Poses(scene, t, options, cache, one_launch(scene, options)))


def _skin(poses: "_Poses") -> SkinnedFrames:
    result = SkinnedFrames(poses.t)
    for batch in poses.batches():
        batch.skin(result)
    return result


POSE_BLOCK_BYTES = 16 << 20
"""Joint transforms (and rates) :func:`chunk_skinner` samples at once: the poses of up to
:data:`POSE_BLOCK_CHUNKS` chunks, as many as fit."""

POSE_BLOCK_CHUNKS = 8
"""Most chunks whose poses :func:`chunk_skinner` samples at once."""


def chunk_skinner(scene: "Scene", times: npt.ArrayLike, slices: "Sequence[slice]",
                  options: SkinOptions, cache: dict[Any, Any]
                  ) -> "Callable[[int], SkinnedFrames]":
    """A function that skins chunk ``k`` of ``times`` (checked; the frames ``times[slices[k]]``,
    consecutive slices) as :func:`skin_scene` does, with the same results: the skeletons'
    poses (animation sampled, forward kinematics, joint rates) are computed for a block of
    consecutive chunks at once (:data:`POSE_BLOCK_BYTES`, :data:`POSE_BLOCK_CHUNKS`; the first
    chunk alone, so that the first result comes as soon as it can) and sliced per chunk, so a
    stream of short chunks pays their per-call cost once a block. Call it
    from one thread at a time, in any order (a chunk outside the block held computes its
    block). ``slices`` must follow one another (each starting where the one before ends). A
    block's poses are those of the scene when its first chunk is skinned; when they cannot be
    computed (a bad pose), each of its chunks computes its own, so the error is raised by the
    chunk that holds the bad frame."""
    t = check_times(times)
    for a, b in zip(slices, slices[1:]):
        if b.start != a.stop:
            raise InputError(f"slices: {b} does not start where {a} ends")
    batched = one_launch(scene, options)
    joints = sum(scene.skeletons[s].joint_count for s in {m.skeleton for m in scene.meshes})
    # float32 transforms, float64 rates and local transforms: ~320 bytes a joint and frame
    most = max(1, POSE_BLOCK_BYTES // max(1, 320 * joints))
    block_of: list[int] = []  # each chunk's block
    spans: list[list[int]] = []  # each block's [first frame, end frame, chunks]
    for sl in slices:
        span = spans[-1] if spans else None
        if (span is None or span[1] - span[0] + sl.stop - sl.start > most
                or span[2] == (1 if len(spans) == 1 else POSE_BLOCK_CHUNKS)):
            span = [sl.start, sl.start, 0]
            spans.append(span)
        span[1], span[2] = sl.stop, span[2] + 1
        block_of.append(len(spans) - 1)
    held: dict[int, _Poses | None] = {}  # the block computed last (None: chunk by chunk)

    def skin(k: int) -> SkinnedFrames:
        b, sl = block_of[k], slices[k]
        lo, hi, chunks = spans[b]
        if b not in held:
            held.clear()  # (the previous block's memory goes first)
            try:
                held[b] = _Poses(scene, t[lo:hi], options, cache, batched)
            except Exception:
                if chunks == 1:
                    raise
                held[b] = None
        poses = held[b]
        if poses is None:
            return _skin(_Poses(scene, t[sl], options, cache, batched))
        return _skin(poses.frames(slice(sl.start - lo, sl.stop - lo)))
    return skin


class _Poses:
    """Every skeleton's skinning transforms (and their rates) at ``t``: per skeleton, or
    concatenated for one launch."""

    def __init__(self, scene, t, options, cache, batched):
        self.scene, self.t, self.options, self.cache, self.batched = (scene, t, options, cache,
                                                                      batched)
        self.device = str(resolve_device(options.device))
        interp, velocities = options.interp, options.velocities
        used = sorted({m.skeleton for m in scene.meshes}) if batched else \
            list(dict.fromkeys(m.skeleton for m in scene.meshes))
        self.xforms, self.rates = {}, {}
        if not batched:
            for s in used:
                skel = scene.skeletons[s]
                local = scene.local_transforms(t, s, interp=interp)
                self.xforms[s] = skel.skinning_transforms(local, device=options.device)
                if velocities:
                    self.rates[s] = self._rates(s, local)
            return
        key = ("joints", tuple(scene.skeletons[s] for s in used), self.device)
        joints = cache.get(key)  # one look-up: Scene.invalidate may drop it from another thread
        if joints is None:
            joints = cache[key] = JointBatch([scene.skeletons[s] for s in used], options.device)
        self.joints = joints
        self.where = dict(zip(used, self.joints.joints))
        local = [scene.local_transforms(t, s, interp=interp) for s in used]
        self.all_xforms = self.joints.skinning_transforms(local)
        self.all_rates = None
        if velocities:
            self.all_rates = np.empty((len(t), self.joints.joint_count, 4, 4), np.float64)
            for s, loc in zip(used, local):
                self.all_rates[:, self.where[s]] = self._rates(s, loc)

    def frames(self, sl: slice) -> "_Poses":
        """These poses at the frames ``sl`` of :attr:`t` (views, no copy)."""
        part = copy.copy(self)
        part.t = self.t[sl]
        part.xforms = {s: x[sl] for s, x in self.xforms.items()}
        part.rates = {s: r[sl] for s, r in self.rates.items()}
        if self.batched:
            part.all_xforms = self.all_xforms[sl]
            part.all_rates = None if self.all_rates is None else self.all_rates[sl]
        return part

    def _rates(self, s, local):
        skel = self.scene.skeletons[s]
        try:
            return skinning_transforms_with_derivative(skel, skel.animation, self.t,
                                                       self.options.interp, local=local)[1]
        except ValueError as exc:
            raise InputError(f"{self.scene.path}: {exc}") from None

    def batches(self):
        """The batches to skin, in order: one per method (one launch), else one per mesh."""
        scene, options = self.scene, self.options
        if not self.batched:
            return [_One(self, m) for m in scene.meshes]
        groups: "dict[Method, list[Mesh]]" = {}
        for m in scene.meshes:
            groups.setdefault(options.method_of(m), []).append(m)
        return [_Many(self, meth, meshes) for meth, meshes in groups.items()]


class _One:
    """A batch of one mesh: its own skinner, its output transform applied in the kernel."""

    def __init__(self, poses, mesh):
        self.poses, self.mesh = poses, mesh
        options = poses.options
        self.method = options.method_of(mesh)
        # the centers-of-rotation settings matter to "cor" only: one skinner for the others
        cor = options.cor if self.method == "cor" else None
        self.skinner = poses.scene.skinner(mesh, options.device, cor)
        self.xforms = poses.xforms[mesh.skeleton]
        self.deformer = mesh.deformer if options.blend_shapes else None

    def skin(self, result):
        p, m, t = self.poses, self.mesh, self.poses.t
        options, sk, meth, xf, deformer = (p.options, self.skinner, self.method, self.xforms,
                                           self.deformer)
        sign = options.sign_reference
        rest = None if deformer is None else deformer.points_at(t)
        track = space_track(m, options.space)
        out = rate = None
        if track is not None:
            out, rate = track.with_derivative(t) if options.velocities else (track.at(t), None)
        result.points[m.name] = sk.skin(xf, meth, points=rest, output_transforms=out,
                                        sign_reference=sign)
        if options.normals and m.normals is not None:
            rn = None if deformer is None else deformer.normals_at(t)
            rn = m.normals if rn is None else rn
            result.normals[m.name] = sk.skin_vectors(xf, rn, meth, kind="normal",
                                                     vector_vertex=m.normal_vertex,
                                                     output_transforms=out, sign_reference=sign)
        if options.tangents and m.tangents is not None:
            rt = None if deformer is None else deformer.tangents_at(t)
            rt = m.tangents[:, :3] if rt is None else rt
            result.tangents[m.name] = sk.skin_vectors(xf, rt, meth, kind="tangent",
                                                      output_transforms=out, sign_reference=sign)
        if options.velocities:
            try:
                result.velocities[m.name] = self._velocities(rest, out, rate)
            except ValueError as exc:  # per-second rates beyond float32
                raise InputError(f"{p.scene.path}: {m.name}: velocities: {exc}") from None

    def _velocities(self, rest, out, out_rate):
        """(F, V, 3) float32 velocities per second, the chain rule through every time-varying
        input: joints, the deformer's rest points, the output transform."""
        p, sk, meth, xf = self.poses, self.skinner, self.method, self.xforms
        sign = p.options.sign_reference
        tcps = float(p.scene.time_codes_per_second)
        rest_dot = None if self.deformer is None else self.deformer.point_velocities_at(p.t)
        rates, rest_dot = per_second(tcps, p.rates[self.mesh.skeleton], rest_dot)
        v = sk.skin_velocities(xf, rates, meth, points=rest, point_velocities=rest_dot,
                               sign_reference=sign)
        if out is None:
            return v
        return moved_velocities(v, out, out_rate, tcps,
                                lambda: sk.skin(xf, meth, points=rest, sign_reference=sign))


class _Many:
    """A batch of every mesh of one method: one :class:`~dqskin.crowd.MeshBatch` launch in bind
    space, then each mesh's output transform applied to its rows."""

    def __init__(self, poses, method, meshes):
        self.poses, self.method, self.meshes = poses, method, meshes
        scene, cache = poses.scene, poses.cache
        key = ("meshes", tuple(m.name for m in meshes), poses.device)
        batch = cache.get(key)  # one look-up: Scene.invalidate may drop it from another thread
        if batch is None:
            batch = cache[key] = MeshBatch(
                meshes, [poses.where[m.skeleton].start for m in meshes],
                [scene.skeletons[m.skeleton].joint_count for m in meshes], poses.options.device)
        self.batch = batch
        self.deformers = {i: m.deformer for i, m in enumerate(meshes)
                          if poses.options.blend_shapes and m.deformer is not None}

    def skin(self, result):
        p, batch, meth, meshes = self.poses, self.batch, self.method, self.meshes
        options, t, F, xf = p.options, p.t, len(p.t), p.all_xforms
        rest = {i: d.points_at(t) for i, d in self.deformers.items()}
        bind_rest = batch.bind_points({i: r for i, r in rest.items() if r is not None}, F)
        skel = skin_batch(batch, xf, meth, options, points=bind_rest)
        outs = {}
        for i, m in enumerate(meshes):
            track = space_track(m, options.space)
            if track is not None:
                outs[i] = track.with_derivative(t) if options.velocities else (track.at(t), None)
        for i, m in enumerate(meshes):
            pts = skel[:, batch.vertices[i]]
            result.points[m.name] = _apply_points(pts, outs[i][0]) if i in outs else pts
        if options.normals:
            self._normals(result, outs)
        if options.velocities:
            self._velocities(result, outs, skel, bind_rest)

    def _normals(self, result, outs):
        p, batch, meshes = self.poses, self.batch, self.meshes
        with_normals = [i for i, m in enumerate(meshes) if m.normals is not None]
        if not with_normals:
            return
        rn = {i: self.deformers[i].normals_at(p.t) for i in with_normals if i in self.deformers}
        vectors, vv, slices = batch.bind_normals(
            with_normals, {i: n for i, n in rn.items() if n is not None}, len(p.t))
        skinned = batch.skinner.skin_vectors(p.all_xforms, vectors, self.method, kind="normal",
                                             vector_vertex=vv,
                                             sign_reference=p.options.sign_reference)
        if skinned.ndim == 2:
            skinned = skinned[None]
        for i, sl in zip(with_normals, slices):
            n = skinned[:, sl]
            result.normals[meshes[i].name] = _apply_normals(n, outs[i][0]) if i in outs else n

    def _velocities(self, result, outs, skel, bind_rest):
        p, batch, meshes, F = self.poses, self.batch, self.meshes, len(self.poses.t)
        rest_dot = {i: d.point_velocities_at(p.t) for i, d in self.deformers.items()}
        rest_dot = {i: v for i, v in rest_dot.items() if v is not None}
        tcps = float(p.scene.time_codes_per_second)
        rates_s, rest_dot_s = per_second(tcps, p.all_rates, batch.bind_velocities(rest_dot, F))
        try:
            v_all = batch.skinner.skin_velocities(p.all_xforms, rates_s, self.method,
                                                  points=bind_rest, point_velocities=rest_dot_s,
                                                  sign_reference=p.options.sign_reference)
        except ValueError as exc:  # per-second rates beyond float32
            more = f" and {len(meshes) - 1} more" if len(meshes) > 1 else ""
            raise InputError(f"{p.scene.path}: {meshes[0].name}{more}: velocities: "
                             f"{exc}") from None
        for i, m in enumerate(meshes):
            v = v_all[:, batch.vertices[i]]
            if i in outs:
                out, out_rate = outs[i]
                columns = batch.vertices[i]
                v = moved_velocities(v, out, out_rate, tcps, lambda: skel[:, columns])
            result.velocities[m.name] = v


def _apply_points(p, xf):
    """``xf (F, 4, 4) · [p, 1]`` for (F, N, 3) points, float32."""
    a = xf[:, :3, :3].astype(np.float32)
    return np.einsum("fij,fvj->fvi", a, p) + xf[:, None, :3, 3].astype(np.float32)


def _apply_normals(n, xf):
    lin = np.linalg.inv(xf[:, :3, :3]).transpose(0, 2, 1).astype(np.float32)
    y = np.einsum("fij,fvj->fvi", lin, n)
    return y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-30)


def rigid_transforms(scene: "Scene", prim: "RigidPrim", times: npt.ArrayLike,
                     options: SkinOptions) -> np.ndarray:
    """Local transforms of a rigidly skinned prim without points
    (:class:`dqskin.readers.usd.RigidPrim`), skinned by the engine.

    The skinned transform is recovered exactly from four skinned points (origin and the three
    unit axes of the prim's space): with one set of influences for every point, LBS and DQS
    (scale/shear residual included) are affine maps. ``options.method`` None uses the prim's
    own; "blend" mixes half and half; "cor" is DQS here (a rigid prim has no triangles to find
    a center of rotation from: COR's fallback). ``options.interp``, ``sign_reference`` and
    ``device`` as for the meshes.

    Returns
    -------
    (F, 4, 4) float64
        Prim space → parent space, column-vector convention (``xformOp:transform``, transposed).
    """
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    x = scene.skinning_transforms(t, prim.skeleton, device=options.device, interp=options.interp)
    frame = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    idx = np.tile(prim.joint_indices, (4, 1))
    wts = np.tile(prim.joint_weights, (4, 1))
    meth = options.method_of(prim)
    meth = "dqs" if meth == "cor" else meth
    q = skin_points(frame, idx, wts, x, meth, geom_bind_transform=prim.geom_bind_transform,
                    blend_weights=np.full(4, 0.5) if meth == "blend" else None,
                    sign_reference=options.sign_reference, device=options.device)
    q = q.astype(np.float64).reshape(t.shape[0], 4, 3)
    m = np.tile(np.eye(4), (t.shape[0], 1, 1))
    m[:, :3, 3] = q[:, 0]
    m[:, :3, :3] = (q[:, 1:] - q[:, :1]).transpose(0, 2, 1)
    return m if prim.parent_transforms is None else prim.parent_transforms.at(t) @ m
