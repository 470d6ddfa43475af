"""Differentiable skinning and forward kinematics for PyTorch, on dqskin's Warp kernels.

Each function is a ``torch.autograd.Function`` whose forward and backward both run in Warp
(:mod:`dqskin.kernels.grad`; the backward is the adjoint Warp generates from the forward kernel,
except for DQS points: :mod:`dqskin.kernels.grad_dqs`, the closed-form derivative of the
normalized blend, one pass over the vertices).
Tensors pass to Warp without a copy (``wp.from_torch``) and stay on their device (CPU or CUDA);
the kernels run float32.

* :func:`fk`: local joint matrices → world (or skinning) matrices.
* :func:`local_transforms`: joint rotations (quaternions or rotation vectors), translations and
  scales → local matrices.
* :func:`skin`: rest points, influences and skinning matrices → skinned points (and normals), by
  LBS, DQS (both sign rules), the per-vertex blend or optimized centers of rotation.
* :func:`skin_pose`: the three chained, the call of a pose-fitting loop.

Where the functions are not differentiable:

* The sign of each joint's dual quaternion in a DQS blend is a step function (of the dot product
  with the pivot's or the running sum's real part). Its derivative, zero, is what is propagated:
  exact everywhere except on the tie itself, a dot product of exactly 0 (a joint rotated by
  180° against the pivot), where the blend jumps and one side's derivative is given.
* The pivot (the vertex's largest weight, first on ties) switches where two weights are equal;
  the blend is continuous there (the two joints' quaternions then get the same sign unless they
  are antipodal), and the derivative of the pivot chosen is given.
* One-hot influences (one weight 1, the others 0) are ordinary points: the derivative with
  respect to every weight, the zero ones included, is given (LBS is linear in the weights; a DQS
  blend has the derivative of the normalized sum). Only a vertex whose weights are all 0 is
  degenerate: its DQS blend is the zero dual quaternion, which leaves the point where it is, and
  the derivative is that of the guarded normalization (finite, not meaningful).
* DQS always blends the scale/shear residuals, ``p_s = Σ wᵢ·Sᵢ·p``: dqskin's and UsdSkel's value
  wherever the weights sum to 1 or a joint of the frame has scale or shear (UsdSkel skips that
  blend on rigid frames, where a shear of a transform would make the value jump if the weights
  did not sum to 1).
* A singular joint matrix (``|det| < 1e-10``) adds nothing to a DQS blend, as in UsdSkel; its
  derivative there is zero.

Importing this module imports PyTorch; ``import dqskin`` does not.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

try:
    import torch
except ModuleNotFoundError as exc:  # the optional extra
    raise ModuleNotFoundError("dqskin.autograd needs PyTorch: pip install 'dqskin[torch]'",
                              name="torch") from exc

import warp as wp

from ._warp import init_warp
from .errors import InputError, Param
from .kernels import grad as KG
from .kernels.dqmath import vec8
from .kernels.grad_dqs import dqs_points_adjoint_kernel
from .options import METHOD_NAMES, SIGN_REFERENCES, Method, SignReference

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["Rig", "fk", "local_transforms", "skin", "skin_pose"]

_METHOD_CODES = {"lbs": KG.LBS, "dqs": KG.DQS, "blend": KG.BLEND, "cor": KG.COR}


# ---------------------------------------------------------------------------------------------
# tensors ↔ Warp arrays


def _device(t: torch.Tensor) -> wp.Device:
    init_warp()
    return wp.device_from_torch(t.device)


@contextlib.contextmanager
def _stream(device: wp.Device) -> Iterator[None]:
    """Warp launches on PyTorch's current stream (CUDA), so no synchronization is needed."""
    if device.is_cuda:
        with wp.ScopedStream(wp.stream_from_torch(torch.cuda.current_stream(device.ordinal))):
            yield
    else:
        yield


_EMPTY: dict[tuple[Any, str], wp.array] = {}


def _wp(t: torch.Tensor | None, dtype: Any, device: wp.Device) -> wp.array:
    """A 1-D Warp array of ``dtype`` over contiguous tensor ``t`` (no copy); empty for None (one
    per dtype and device, shared)."""
    if t is None or t.numel() == 0:
        empty = _EMPTY.get((dtype, str(device)))
        if empty is None:
            empty = _EMPTY[(dtype, str(device))] = wp.empty(0, dtype=dtype, device=device)
        return empty
    shape = getattr(dtype, "_shape_", ())
    flat = t.contiguous().reshape(-1, *shape)
    return cast(wp.array, wp.from_torch(flat, dtype=dtype, requires_grad=False))


def _wp2(t: torch.Tensor, dtype: Any) -> wp.array:
    """A 2-D Warp array over contiguous (V, K) tensor ``t``."""
    return cast(wp.array, wp.from_torch(t.contiguous(), dtype=dtype, requires_grad=False))


def _is_tensor(t: object) -> bool:
    """Whether ``t`` is a tensor (arguments are checked whatever their annotation says)."""
    return isinstance(t, torch.Tensor)


def _float(name: str, t: Any, tail: tuple[int, ...], lead_max: int | None = None
           ) -> torch.Tensor:
    """``t`` checked: a float32 tensor of shape ``(..., *tail)`` (at most ``lead_max`` leading
    dimensions)."""
    if not isinstance(t, torch.Tensor):
        raise InputError(Param(name), f": expected a torch.Tensor, got {type(t).__name__}")
    if t.dtype != torch.float32:
        raise InputError(Param(name), f": expected float32 (the kernels' type), got {t.dtype}")
    n = len(tail)
    if t.dim() < n or tuple(t.shape[t.dim() - n:]) != tail or (
            lead_max is not None and t.dim() - n > lead_max):
        want = "(..., " if lead_max is None else "(" + "B, " * lead_max
        raise InputError(Param(name), f": expected shape {want}"
                         f"{', '.join(map(str, tail))}), got {tuple(t.shape)}")
    return t


def _same_device(tensors: dict[str, torch.Tensor | None], device: torch.device) -> None:
    for name, t in tensors.items():
        if t is not None and t.device != device:
            raise InputError(Param(name), f": on {t.device}, the transforms on {device}")


def _indices(indices: torch.Tensor, joints: int) -> torch.Tensor:
    """``indices`` as a contiguous int32 tensor, each checked to be in ``0 .. joints - 1``
    (:class:`InputError` otherwise). Converted and checked by Warp on every call (int32 and
    int64 tensors: no PyTorch operation, which would start PyTorch's OpenMP threads), so
    changes made in place by any means are read."""
    d = _device(indices)
    if indices.dtype not in (torch.int32, torch.int64):
        indices = indices.to(torch.int32)
    src = indices.contiguous().reshape(-1)
    idx = src if src.dtype == torch.int32 else torch.empty(src.shape, dtype=torch.int32,
                                                           device=src.device)
    with _stream(d):  # on PyTorch's stream, as its tensors were made
        bad = wp.zeros(1, dtype=wp.int32, device=d)
        if src.numel():
            kernel = (KG.index_check_kernel if src.dtype == torch.int32
                      else KG.index_narrow_kernel)
            KG.launch_joints(kernel, src.numel(),
                             [wp.from_torch(src, requires_grad=False), joints],
                             [wp.from_torch(idx, requires_grad=False), bad], d)
        count = int(bad.numpy()[0])  # (waits for the stream on CUDA)
    if count:
        raise InputError(Param("indices"), f": joint indices {int(indices.min())}.."
                         f"{int(indices.max())} outside 0..{joints - 1}")
    return idx.reshape(indices.shape)


def _parents(parents: Any, joint_count: int, device: torch.device) -> torch.Tensor:
    """(J,) int32 parents on ``device``, each −1 or an earlier joint."""
    p = torch.as_tensor(parents).to(device=device, dtype=torch.int32).reshape(-1)
    if p.numel() != joint_count:
        raise InputError(Param("parents"), f": {p.numel()} entries for {joint_count} joints")
    cpu = p.cpu()
    if bool(((cpu < -1) | (cpu >= torch.arange(joint_count, dtype=torch.int32))).any()):
        raise InputError(Param("parents"), ": each parent must be -1 or an earlier joint")
    return p


# ---------------------------------------------------------------------------------------------
# autograd functions


class _Local(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, rotations: torch.Tensor, translations: torch.Tensor,
                scales: torch.Tensor | None, root: torch.Tensor | None,
                parents: torch.Tensor) -> torch.Tensor:
        frames, joints = rotations.shape[0], rotations.shape[1]
        axis_angle = rotations.shape[2] == 3
        d = _device(rotations)
        out = torch.empty((frames, joints, 4, 4), dtype=torch.float32, device=rotations.device)
        ctx.axis_angle = axis_angle
        ctx.save_for_backward(rotations, translations, scales, root, parents, out)
        with _stream(d):
            KG.launch_joints(KG.local_kernel(axis_angle), frames * joints,
                             *_local_args(rotations, translations, scales, root, parents, out, d),
                             d)
        return out

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        rotations, translations, scales, root, parents, out = ctx.saved_tensors
        d = _device(rotations)
        adj = [torch.zeros_like(rotations), torch.zeros_like(translations),
               None if scales is None else torch.zeros_like(scales),
               None if root is None else torch.zeros_like(root)]
        inputs, outputs = _local_args(rotations, translations, scales, root, parents, out, d)
        rot_t = wp.vec3 if ctx.axis_angle else wp.vec4
        adj_inputs = [_wp(adj[0], rot_t, d), _wp(adj[1], wp.vec3, d), 0,
                      _wp(adj[2], wp.vec3, d), 0, _wp(adj[3], wp.vec3, d), None]
        with _stream(d):
            KG.launch_joints(KG.local_kernel(ctx.axis_angle), out.shape[0] * out.shape[1],
                             inputs, outputs, d, adj_inputs, [_wp(grad, wp.mat44, d)])
        return adj[0], adj[1], adj[2], adj[3], None


def _local_args(rotations: torch.Tensor, translations: torch.Tensor, scales: torch.Tensor | None,
                root: torch.Tensor | None, parents: torch.Tensor, out: torch.Tensor,
                d: wp.Device) -> tuple[list[Any], list[Any]]:
    joints = rotations.shape[1]
    rot_t = wp.vec3 if rotations.shape[2] == 3 else wp.vec4
    t_stride = joints if translations.shape[0] > 1 else 0
    s_stride = joints if scales is not None and scales.shape[0] > 1 else 0
    return ([_wp(rotations, rot_t, d), _wp(translations, wp.vec3, d), t_stride,
             _wp(scales, wp.vec3, d), s_stride, _wp(root, wp.vec3, d),
             _wp(parents, wp.int32, d)], [_wp(out, wp.mat44, d)])


class _FK(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, local: torch.Tensor, parents: torch.Tensor,
                inverse_bind: torch.Tensor | None) -> torch.Tensor:
        frames = local.shape[0]
        d = _device(local)
        world = torch.empty_like(local)
        skinning = world if inverse_bind is None else torch.empty_like(local)
        ctx.save_for_backward(local, parents, inverse_bind, world, skinning)
        with _stream(d):
            KG.launch_joints(KG.fk_kernel, frames, *_fk_args(local, parents, inverse_bind, world,
                                                             skinning, d), d)
        return skinning

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        local, parents, inverse_bind, world, skinning = ctx.saved_tensors
        d = _device(local)
        adj_local = torch.zeros_like(local)
        adj_bind = None if inverse_bind is None else torch.zeros_like(inverse_bind)
        # the adjoint accumulates into the world matrices' adjoints: a buffer of its own
        adj_world = grad.clone() if inverse_bind is None else torch.zeros_like(world)
        adj_skin = None if inverse_bind is None else grad.contiguous()
        inputs, outputs = _fk_args(local, parents, inverse_bind, world, skinning, d)
        with _stream(d):
            KG.launch_joints(KG.fk_kernel, local.shape[0], inputs, outputs, d,
                             [_wp(adj_local, wp.mat44, d), None, _wp(adj_bind, wp.mat44, d)],
                             [_wp(adj_world, wp.mat44, d), _wp(adj_skin, wp.mat44, d)])
        return adj_local, None, adj_bind


def _fk_args(local: torch.Tensor, parents: torch.Tensor, inverse_bind: torch.Tensor | None,
             world: torch.Tensor, skinning: torch.Tensor, d: wp.Device
             ) -> tuple[list[Any], list[Any]]:
    return ([_wp(local, wp.mat44, d), _wp(parents, wp.int32, d),
             _wp(inverse_bind, wp.mat44, d)],
            [_wp(world, wp.mat44, d),
             _wp(None if inverse_bind is None else skinning, wp.mat44, d)])


class _Skin(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor,
                blend: torch.Tensor | None, centers: torch.Tensor | None,
                normals: torch.Tensor | None, indices: torch.Tensor,
                has_center: torch.Tensor | None, method: int, running_sum: bool
                ) -> tuple[torch.Tensor, torch.Tensor]:
        frames, joints = transforms.shape[0], transforms.shape[1]
        verts, k = weights.shape
        d = _device(transforms)
        dev = transforms.device
        out = torch.empty((frames, verts, 3), dtype=torch.float32, device=dev)
        out_n = torch.empty((frames if normals is not None else 0, verts, 3), dtype=torch.float32,
                            device=dev)
        dqs = torch.empty((frames * joints, 8) if method != KG.LBS else (0, 8),
                          dtype=torch.float32, device=dev)
        res = torch.empty((dqs.shape[0], 3, 3), dtype=torch.float32, device=dev)
        nl = torch.empty((frames * joints if normals is not None else 0, 3, 3),
                         dtype=torch.float32, device=dev)
        nq = torch.empty((nl.shape[0], 4), dtype=torch.float32, device=dev)
        ns = torch.empty_like(nl)
        chunks = KG.vertex_chunks(verts, frames, d, frames * joints)
        ctx.method, ctx.running_sum, ctx.chunks = method, running_sum, chunks
        ctx.set_materialize_grads(False)  # no zero tensor made for an output not used
        saved = (points, weights, transforms, blend, centers, normals, indices, has_center, out,
                 out_n, dqs, res, nl, nq, ns)
        ctx.save_for_backward(*saved)
        a = _SkinArrays(saved, d)
        with _stream(d):
            if method != KG.LBS:
                KG.launch_joints(KG.prepare_kernel, frames * joints, *a.prepare(), d)
            kernel = KG.points_kernel(method, k, running_sum)
            KG.launch_vertices(kernel, chunks, frames, lambda c: a.point_inputs(),
                               lambda c: a.point_out, d)
            if normals is not None:
                KG.launch_joints(KG.prepare_normals_kernel, frames * joints,
                                 *a.prepare_normals(), d)
                KG.launch_vertices(KG.normals_kernel(method, k, running_sum), chunks, frames,
                                   lambda c: a.normal_inputs(), lambda c: a.normal_out, d)
        if normals is None:
            ctx.mark_non_differentiable(out_n)
        return out, out_n

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor | None, grad_n: torch.Tensor | None
                 ) -> tuple[torch.Tensor | None, ...]:
        (points, weights, transforms, blend, centers, normals, indices, has_center, out, out_n,
         dqs, res, nl, nq, ns) = ctx.saved_tensors
        d = _device(transforms)
        method, chunks = ctx.method, ctx.chunks
        frames, joints = transforms.shape[0], transforms.shape[1]
        k = weights.shape[1]
        a = _SkinArrays(ctx.saved_tensors, d)
        n = len(chunks)
        fj = frames * joints
        # no PyTorch operation here that could start its OpenMP threads (they would spin on
        # the cores the kernels run on): buffers zeroed and per-chunk adjoints summed in Warp
        # the DQS adjoint kernel writes the per-vertex adjoints (of every vertex: not with no
        # frames, where it launches nothing and they are zero)
        written = method == KG.DQS and frames > 0
        with _stream(d):
            zeros = _Zeros(d)
            empty = torch.empty_like
            adj_points = empty(points) if written else zeros.like(points)
            adj_weights = empty(weights) if written else zeros.like(weights)
            adj_blend = None if blend is None else zeros.like(blend)
            adj_centers = None if centers is None else zeros.like(centers)
            adj_normals = None if normals is None else zeros.like(normals)
            adj_x = zeros.new((fj, 4, 4))
            # per-joint adjoints: a buffer per chunk (the chunks run at once), summed after
            cq = zeros.new((n, dqs.shape[0], 8))
            cs = zeros.new((n, dqs.shape[0], 3, 3))
            g = _wp(zeros.like(out) if grad is None else grad, wp.vec3, d)
            if written:
                args = [*(a.point_inputs()[i] for i in (0, 1, 2, 3, 5, 6)), g, joints, frames]
                per_vertex = [_wp(adj_points, wp.vec3, d), _wp2(adj_weights, wp.float32)]
                results = [[*per_vertex, _wp(cq[c], vec8, d), _wp(cs[c], wp.mat33, d)]
                           for c in range(n)]
                KG.launch_vertices(dqs_points_adjoint_kernel(k, ctx.running_sum), chunks, frames,
                                   lambda c: args, results.__getitem__, d, frame_loop=True)
            else:
                cx = zeros.new((n, fj, 4, 4))

                def point_adj(c: int) -> list[Any]:
                    return [_wp(adj_points, wp.vec3, d), 0, None, _wp2(adj_weights, wp.float32),
                            _wp(cx[c], wp.mat44, d), _wp(cq[c], vec8, d),
                            _wp(cs[c], wp.mat33, d), _wp(adj_blend, wp.float32, d),
                            _wp(adj_centers, wp.vec3, d), None, 0]

                KG.launch_vertices(KG.points_kernel(method, k, ctx.running_sum), chunks, frames,
                                   lambda c: a.point_inputs(), lambda c: a.point_out, d,
                                   point_adj, [g])
                _sum_chunks(cx, adj_x, d)
            if method != KG.LBS:
                inputs, outputs = a.prepare()
                KG.launch_joints(KG.prepare_kernel, fj, inputs, outputs, d,
                                 [_wp(adj_x, wp.mat44, d)],
                                 [_wp(_sum_chunks(cq, None, d), vec8, d),
                                  _wp(_sum_chunks(cs, None, d), wp.mat33, d)])
            if normals is not None and grad_n is not None:
                cl = zeros.new((n, fj, 3, 3))
                cr = zeros.new((n, fj, 4))
                cn = zeros.new((n, fj, 3, 3))

                def normal_adj(c: int) -> list[Any]:
                    return [_wp(adj_normals, wp.vec3, d), 0, None, _wp2(adj_weights, wp.float32),
                            _wp(cl[c], wp.mat33, d), _wp(cr[c], wp.quat, d),
                            _wp(cn[c], wp.mat33, d), _wp(adj_blend, wp.float32, d), 0]

                KG.launch_vertices(KG.normals_kernel(method, k, ctx.running_sum), chunks, frames,
                                   lambda c: a.normal_inputs(), lambda c: a.normal_out, d,
                                   normal_adj, [_wp(grad_n, wp.vec3, d)])
                inputs, outputs = a.prepare_normals()
                KG.launch_joints(KG.prepare_normals_kernel, fj, inputs, outputs, d,
                                 [_wp(adj_x, wp.mat44, d)],
                                 [_wp(_sum_chunks(cl, None, d), wp.mat33, d),
                                  _wp(_sum_chunks(cr, None, d), wp.quat, d),
                                  _wp(_sum_chunks(cn, None, d), wp.mat33, d)])
        return (adj_points, adj_weights, adj_x.reshape(transforms.shape), adj_blend, adj_centers,
                adj_normals, None, None,
                None, None)


class _Zeros:
    """Zeroed float32 tensors on a Warp device, zeroed by Warp (a PyTorch fill of a large
    tensor would start PyTorch's OpenMP threads)."""

    def __init__(self, d: wp.Device) -> None:
        self.d = d
        self.device = wp.device_to_torch(d)

    def new(self, shape: tuple[int, ...]) -> torch.Tensor:
        t = torch.empty(shape, dtype=torch.float32, device=self.device)
        _wp(t, wp.float32, self.d).zero_()
        return t

    def like(self, t: torch.Tensor) -> torch.Tensor:
        return self.new(tuple(t.shape))


def _sum_chunks(parts: torch.Tensor, total: torch.Tensor | None, d: wp.Device) -> torch.Tensor:
    """``parts.sum(0)`` by Warp (:func:`~dqskin.kernels.grad.sum_chunks_kernel`), into
    ``total`` (a new tensor when None)."""
    if total is None:
        total = torch.empty(parts.shape[1:], dtype=torch.float32, device=parts.device)
    flat = parts.reshape(parts.shape[0], math.prod(parts.shape[1:]))  # (0, n) too
    KG.launch_joints(KG.sum_chunks_kernel, flat.shape[1], [_wp2(flat, wp.float32)],
                     [_wp(total, wp.float32, d)], d)
    return total


class _SkinArrays:
    """The Warp views of a :class:`_Skin` call's saved tensors, as the kernels take them."""

    def __init__(self, saved: tuple[Any, ...], d: wp.Device) -> None:
        (points, weights, transforms, blend, centers, normals, indices, has_center, out, out_n,
         dqs, res, nl, nq, ns) = saved
        verts = weights.shape[0]
        joints = transforms.shape[1]
        self.xforms = _wp(transforms, wp.mat44, d)
        self.dqs, self.res = _wp(dqs, vec8, d), _wp(res, wp.mat33, d)
        self.indices, self.weights = _wp2(indices, wp.int32), _wp2(weights, wp.float32)
        self.blend = _wp(blend, wp.float32, d)
        self._points = [_wp(points, wp.vec3, d), verts if points.shape[0] > 1 else 0,
                        self.indices, self.weights, self.xforms, self.dqs, self.res, self.blend,
                        _wp(centers, wp.vec3, d), _wp(has_center, wp.int32, d), joints]
        self.point_out = [_wp(out, wp.vec3, d)]
        self.nl, self.nq, self.ns = _wp(nl, wp.mat33, d), _wp(nq, wp.quat, d), _wp(ns, wp.mat33, d)
        self._normals = ([] if normals is None else
                         [_wp(normals, wp.vec3, d), verts if normals.shape[0] > 1 else 0,
                          self.indices, self.weights, self.nl, self.nq, self.ns, self.blend,
                          joints])
        self.normal_out = [_wp(out_n, wp.vec3, d)]

    def point_inputs(self) -> list[Any]:
        return self._points

    def normal_inputs(self) -> list[Any]:
        return self._normals

    def prepare(self) -> tuple[list[Any], list[Any]]:
        return [self.xforms], [self.dqs, self.res]

    def prepare_normals(self) -> tuple[list[Any], list[Any]]:
        return [self.xforms], [self.nl, self.nq, self.ns]


# ---------------------------------------------------------------------------------------------
# public API


def _lead(t: torch.Tensor, tail: int) -> tuple[int, ...]:
    """The leading (batch) dimensions of ``t`` before its last ``tail``."""
    return tuple(t.shape[:t.dim() - tail])


def fk(local: torch.Tensor, parents: Sequence[int] | torch.Tensor, *,
       inverse_bind: torch.Tensor | None = None) -> torch.Tensor:
    """World (or skinning) transforms of local joint transforms, differentiable.

    Parameters
    ----------
    local : (..., J, 4, 4) float32 tensor
        Parent-relative joint transforms, column-vector convention; any leading (batch)
        dimensions.
    parents : (J,) int sequence or tensor
        Parent of each joint, ``-1`` for roots, parents before children. Several skeletons are
        one concatenated joint axis (each parent index global).
    inverse_bind : (J, 4, 4) float32 tensor, optional
        Inverse bind transforms: the result is then ``world · inverse_bind``, the skinning
        transforms :func:`skin` takes.

    Returns
    -------
    (..., J, 4, 4) float32 tensor
        ``world[j] = world[parents[j]] · local[j]`` (skeleton space), times ``inverse_bind[j]``
        when given; on ``local``'s device. Differentiable with respect to ``local`` and
        ``inverse_bind``.

    Raises
    ------
    dqskin.InputError
        Wrong types, shapes or dtypes; parents out of order; tensors on different devices.
    """
    local = _float("local", local, (4, 4))
    if local.dim() < 3:
        raise InputError(Param("local"), f": expected shape (..., J, 4, 4), got "
                         f"{tuple(local.shape)}")
    lead, joints = _lead(local, 3), local.shape[-3]
    p = _parents(parents, joints, local.device)
    if inverse_bind is not None:
        inverse_bind = _float("inverse_bind", inverse_bind, (joints, 4, 4), 0)
        _same_device({"inverse_bind": inverse_bind}, local.device)
    flat = local.reshape(-1, joints, 4, 4).contiguous()
    ib = None if inverse_bind is None else inverse_bind.contiguous()
    out = _FK.apply(flat, p, ib)
    return out.reshape(*lead, joints, 4, 4)


def local_transforms(rotations: torch.Tensor, translations: torch.Tensor, *,
                     scales: torch.Tensor | None = None,
                     root_translation: torch.Tensor | None = None,
                     parents: Sequence[int] | torch.Tensor | None = None) -> torch.Tensor:
    """Local joint matrices ``T·R·S`` of joint rotations, translations and scales,
    differentiable.

    Parameters
    ----------
    rotations : (..., J, 4) or (..., J, 3) float32 tensor
        Quaternions ``(w, x, y, z)`` of any nonzero length (normalized), or rotation vectors
        (axis times angle in radians).
    translations : (J, 3) or (..., J, 3) float32 tensor
        Parent-relative translations, shared by every pose or one set per pose.
    scales : (J, 3) or (..., J, 3) float32 tensor, optional
        Scale along the joint's axes; 1 by default.
    root_translation : (..., 3) float32 tensor, optional
        Added to the translation of every root joint (``parents[j] == -1``): the placement of
        a fitted body.
    parents : (J,) int sequence or tensor, optional
        Required with ``root_translation``.

    Returns
    -------
    (..., J, 4, 4) float32 tensor
        Column-vector convention, on ``rotations``' device; differentiable with respect to
        every tensor argument.

    Raises
    ------
    dqskin.InputError
        Wrong types, shapes or dtypes; ``root_translation`` without ``parents``.
    """
    if not _is_tensor(rotations) or rotations.dim() < 2 or \
            rotations.shape[-1] not in (3, 4):
        raise InputError(Param("rotations"), ": expected a tensor of shape "
                         "(..., J, 4) (quaternions) or (..., J, 3) (rotation vectors)")
    rotations = _float("rotations", rotations, tuple(rotations.shape[-2:]))
    lead, joints = _lead(rotations, 2), rotations.shape[-2]
    frames = math.prod(lead)
    dev = rotations.device

    def per_pose(name: str, t: torch.Tensor | None) -> torch.Tensor | None:
        if t is None:
            return None
        t = _float(name, t, (joints, 3))
        _same_device({name: t}, dev)
        if t.dim() == 2:
            return t.reshape(1, joints, 3).contiguous()
        if _lead(t, 2) != lead:
            raise InputError(Param(name), f": leading shape {tuple(t.shape[:-2])}, the "
                             f"rotations' {lead}")
        return t.reshape(frames, joints, 3).contiguous()

    trans = per_pose("translations", translations)
    assert trans is not None
    sc = per_pose("scales", scales)
    root = None
    if root_translation is not None:
        root = _float("root_translation", root_translation, (3,))
        if _lead(root, 1) != lead:
            raise InputError(Param("root_translation"), f": expected shape "
                             f"{(*lead, 3)}, got {tuple(root.shape)}")
        _same_device({"root_translation": root}, dev)
        if parents is None:
            raise InputError(Param("parents"), ": required with root_translation")
        root = root.reshape(frames, 3).contiguous()
    p = (torch.full((joints,), -1, dtype=torch.int32, device=dev) if parents is None
         else _parents(parents, joints, dev))
    rot = rotations.reshape(frames, joints, rotations.shape[-1]).contiguous()
    out = _Local.apply(rot, trans, sc, root, p)
    return out.reshape(*lead, joints, 4, 4)


def skin(points: torch.Tensor, indices: torch.Tensor, weights: torch.Tensor,
         transforms: torch.Tensor, method: Method = "dqs", *,
         sign_reference: SignReference = "largest_weight",
         blend_weights: torch.Tensor | None = None, centers: torch.Tensor | None = None,
         normals: torch.Tensor | None = None
         ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Skin points (and normals) with LBS, DQS, their per-vertex blend or optimized centers of
    rotation, differentiable.

    Parameters
    ----------
    points : (V, 3) or (B, V, 3) float32 tensor
        Rest points in bind space, shared by every pose or one set per pose.
    indices : (V, K) int tensor
        Joint of each influence, ``0 <= index < J``. Its int32 copy and range are kept
        between calls for the same tensor until it changes (its ``_version``).
    weights : (V, K) float32 tensor
        Influence weights, used as given (not renormalized; UsdSkel's semantics).
    transforms : (J, 4, 4) or (B, J, 4, 4) float32 tensor
        Skinning transforms (world · inverse bind), column-vector convention.
    method : {"dqs", "lbs", "blend", "cor"}
    sign_reference : {"largest_weight", "running_sum"}
        Sign rule of the rotation blends (:data:`~dqskin.options.SignReference`): against the
        vertex's largest-weight joint (UsdSkel) or the running sum in input order (Blender).
    blend_weights : (V,) float32 tensor, optional
        DQS fraction per vertex, required by ``"blend"``.
    centers : (V, 3) float32 tensor, optional
        Centers of rotation in bind space, required by ``"cor"`` (e.g. from
        :meth:`dqskin.Skinner.rotation_centers`); a NaN row: no center, the vertex is skinned
        by DQS.
    normals : (V, 3) or (B, V, 3) float32 tensor, optional
        Rest normals: skinned too (unit length; DQS and COR rotate them, LBS uses the inverse
        transposes).

    Returns
    -------
    (V, 3) or (B, V, 3) float32 tensor, or a pair of them
        Skinned points (B when the transforms or the points have a batch axis), and the skinned
        normals when ``normals`` is given; on the transforms' device. Differentiable with
        respect to ``points``, ``weights``, ``transforms``, ``blend_weights``, ``centers`` and
        ``normals``.

    Raises
    ------
    dqskin.InputError
        Unknown method or sign rule, wrong types, shapes or dtypes, indices out of range, a
        missing ``blend_weights`` or ``centers``, tensors on different devices.
    """
    if method not in METHOD_NAMES:
        raise InputError(Param("method", method), f": expected one of {', '.join(METHOD_NAMES)}")
    if sign_reference not in SIGN_REFERENCES:
        raise InputError(Param("sign_reference", sign_reference),
                         f": expected one of {', '.join(SIGN_REFERENCES)}")
    transforms = _float("transforms", transforms, tuple(transforms.shape[-3:])
                        if _is_tensor(transforms) and transforms.dim() >= 3
                        else (0, 4, 4), 1)
    if transforms.shape[-2:] != (4, 4):
        raise InputError(Param("transforms"), f": expected shape (B, J, 4, 4) or "
                         f"(J, 4, 4), got {tuple(transforms.shape)}")
    batched = transforms.dim() == 4
    joints = transforms.shape[-3]
    weights = _float("weights", weights, tuple(weights.shape) if _is_tensor(
        weights) and weights.dim() == 2 else (0, 0), 0)
    verts, k = weights.shape
    if k < 1:
        raise InputError(Param("weights"), ": expected at least one influence")
    points = _float("points", points, (verts, 3), 1)
    dev = transforms.device
    if not _is_tensor(indices) or indices.shape != weights.shape or \
            indices.dtype.is_floating_point or indices.dtype.is_complex:
        raise InputError(Param("indices"), f": expected an int tensor of the weights' "
                         f"shape {tuple(weights.shape)}")
    _same_device({"points": points, "indices": indices, "weights": weights}, dev)
    idx = _indices(indices, joints)
    frames = transforms.shape[0] if batched else 1
    if points.dim() == 3:
        if not batched:
            transforms = transforms.expand(points.shape[0], joints, 4, 4)
            frames, batched = points.shape[0], True
        elif points.shape[0] not in (frames,):
            raise InputError(Param("points"), f": {points.shape[0]} point sets for "
                             f"{frames} transform sets")
    code = _METHOD_CODES[method]
    blend = None
    if code == KG.BLEND:
        if blend_weights is None:
            raise InputError(Param("blend_weights"), ': required by method "blend"')
        blend = _float("blend_weights", blend_weights, (verts,), 0).contiguous()
        _same_device({"blend_weights": blend}, dev)
    cen = has = None
    if code == KG.COR:
        if centers is None:
            raise InputError(Param("centers"), ': required by method "cor"')
        centers = _float("centers", centers, (verts, 3), 0)
        _same_device({"centers": centers}, dev)
        ok = ~torch.isnan(centers).any(dim=1)
        has = ok.to(torch.int32).contiguous()
        cen = torch.where(ok[:, None], centers, torch.zeros_like(centers)).contiguous()
    nrm = None
    if normals is not None:
        nrm = _float("normals", normals, (verts, 3), 1)
        _same_device({"normals": nrm}, dev)
        nrm = nrm.reshape(-1, verts, 3).contiguous()
    running = sign_reference == "running_sum" and code != KG.LBS
    xf = transforms.reshape(frames, joints, 4, 4).contiguous()
    pts = points.reshape(-1, verts, 3).contiguous()
    out, out_n = _Skin.apply(pts, weights.contiguous(), xf, blend, cen, nrm, idx, has, code,
                             running)
    if not batched:
        # squeeze, not out[0]: its backward is a view, not a zeroed (B, V, 3) copy
        out, out_n = out.squeeze(0), out_n.squeeze(0) if nrm is not None else out_n
    return out if normals is None else (out, out_n)


def skin_pose(points: torch.Tensor, indices: torch.Tensor, weights: torch.Tensor,
              rotations: torch.Tensor, *, parents: Sequence[int] | torch.Tensor,
              translations: torch.Tensor, inverse_bind: torch.Tensor,
              root_translation: torch.Tensor | None = None, scales: torch.Tensor | None = None,
              method: Method = "dqs", sign_reference: SignReference = "largest_weight",
              blend_weights: torch.Tensor | None = None, centers: torch.Tensor | None = None,
              normals: torch.Tensor | None = None
              ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Skinned points of a pose given as joint rotations and a root translation, differentiable:
    :func:`local_transforms`, then :func:`fk` with the inverse binds, then :func:`skin`.

    Parameters
    ----------
    points, indices, weights
        As :func:`skin` (rest points in bind space).
    rotations : (J, 4), (J, 3), (B, J, 4) or (B, J, 3) float32 tensor
        Local joint rotations: quaternions ``(w, x, y, z)`` or rotation vectors.
    parents : (J,) int sequence or tensor
    translations : (J, 3) or (B, J, 3) float32 tensor
        Local joint translations (usually the rest pose's).
    inverse_bind : (J, 4, 4) float32 tensor
        Inverse bind transforms.
    root_translation : (3,) or (B, 3) float32 tensor, optional
        Added to the root joints' translations.
    scales : (J, 3) or (B, J, 3) float32 tensor, optional
        Local joint scales (1 by default).
    method, sign_reference, blend_weights, centers, normals
        As :func:`skin`.

    Returns
    -------
    (V, 3) or (B, V, 3) float32 tensor, or a pair with the normals
        As :func:`skin`; differentiable with respect to every float tensor argument.

    Raises
    ------
    dqskin.InputError
        As :func:`local_transforms`, :func:`fk` and :func:`skin`.
    """
    local = local_transforms(rotations, translations, scales=scales,
                             root_translation=root_translation, parents=parents)
    xf = fk(local, parents, inverse_bind=inverse_bind)
    return skin(points, indices, weights, xf, method, sign_reference=sign_reference,
                blend_weights=blend_weights, centers=centers, normals=normals)


_SHEAR_TOLERANCE = 1e-5


@dataclass(frozen=True)
class Rig:
    """A skinned mesh and its skeleton as tensors: what :func:`skin_pose` takes besides the pose.

    Attributes
    ----------
    points : (V, 3) float32 tensor
        Rest points in bind (skeleton) space.
    indices : (V, K) int32 tensor
    weights : (V, K) float32 tensor
    parents : (J,) int32 tensor
        ``-1`` for roots, parents first.
    translations, rotations, scales : (J, 3), (J, 4), (J, 3) float32 tensors
        The rest pose, parent-relative: translation, unit quaternion ``(w, x, y, z)`` and scale.
    inverse_bind : (J, 4, 4) float32 tensor
    """

    points: torch.Tensor
    indices: torch.Tensor
    weights: torch.Tensor
    parents: torch.Tensor
    translations: torch.Tensor
    rotations: torch.Tensor
    scales: torch.Tensor
    inverse_bind: torch.Tensor

    @classmethod
    def from_scene(cls, scene: Scene, mesh: int | str = 0, *,
                   device: str | torch.device = "cpu") -> Rig:
        """The rig of one mesh of a loaded scene (:func:`dqskin.load`), on ``device``.

        Raises
        ------
        dqskin.InputError
            No such mesh; a rest transform with shear (no translation, rotation and scale).
        """
        from . import quat

        m = scene.mesh(mesh) if isinstance(mesh, str) else scene.meshes[mesh]
        skel = scene.skeletons[m.skeleton]
        g = np.asarray(m.geom_bind_transform, np.float64)
        points = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
        rest = np.asarray(skel.rest_transforms, np.float64)
        u, _, vt = np.linalg.svd(rest[:, :3, :3])
        r = u @ vt
        r[np.linalg.det(r) < 0] *= -1.0
        s = np.swapaxes(r, 1, 2) @ rest[:, :3, :3]
        off = np.abs(s - s * np.eye(3)).max(axis=(1, 2))
        sheared = np.flatnonzero(off > _SHEAR_TOLERANCE * np.abs(s).max(axis=(1, 2)))
        if sheared.size:
            names = ", ".join(repr(skel.joint_names[j]) for j in sheared[:5])
            raise InputError(f"{scene.path}: rest transforms of joints {names} have shear: "
                             "give dqskin.autograd.fk the local matrices instead")

        def tensor(a: Any, dtype: torch.dtype = torch.float32) -> torch.Tensor:
            return torch.tensor(np.array(a)).to(device=device, dtype=dtype)

        return cls(points=tensor(points), indices=tensor(m.joint_indices, torch.int32),
                   weights=tensor(m.joint_weights), parents=tensor(skel.parents, torch.int32),
                   translations=tensor(rest[:, :3, 3]), rotations=tensor(quat.from_matrix(r)),
                   scales=tensor(np.diagonal(s, axis1=1, axis2=2)),
                   inverse_bind=tensor(skel.inverse_bind_transforms))

    def pose(self, rotations: torch.Tensor | None = None,
             root_translation: torch.Tensor | None = None, *,
             weights: torch.Tensor | None = None, method: Method = "dqs",
             sign_reference: SignReference = "largest_weight") -> torch.Tensor:
        """Skinned points of a pose (:func:`skin_pose` with this rig's rest pose and binds).

        Parameters
        ----------
        rotations : (J, 4), (J, 3), (B, J, 4) or (B, J, 3) float32 tensor, optional
            Local joint rotations (quaternions or rotation vectors); the rest pose's when
            omitted.
        root_translation : (3,) or (B, 3) float32 tensor, optional
            Added to the root joints' rest translations.
        weights : (V, K) float32 tensor, optional
            Influence weights replacing the rig's (for fitting them).
        method, sign_reference
            As :func:`skin`.

        Returns
        -------
        (V, 3) or (B, V, 3) float32 tensor
        """
        out = skin_pose(self.points, self.indices,
                        self.weights if weights is None else weights,
                        self.rotations if rotations is None else rotations,
                        parents=self.parents, translations=self.translations,
                        inverse_bind=self.inverse_bind, scales=self.scales,
                        root_translation=root_translation, method=method,
                        sign_reference=sign_reference)
        assert isinstance(out, torch.Tensor)
        return out
