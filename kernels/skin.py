"""Per-vertex skinning kernels: LBS, DQS, the per-vertex LBS↔DQS blend and optimized centers of
rotation (COR), batched over frames.

Semantics follow UsdSkel (``UsdSkelSkinPointsLBS/DQS``):

* LBS: ``p' = Σ wᵢ·Mᵢ·p`` -- weights used as given, never renormalized.
* DQS: each skinning matrix is split by the polar decomposition ``A = R·S`` into a unit dual
  quaternion ``η`` (``R``, ``t``) and a residual ``S``. If any joint of the frame has ``S ≠ I``, the
  point is first blended linearly through the residuals, ``p_s = Σ wᵢ·Sᵢ·p``; then
  ``p' = normalize(Σ ±wᵢ·ηᵢ)(p_s)``, each ``ηᵢ`` sign-flipped onto the hemisphere of the vertex's
  largest-weight joint (antipodality). Normalization (Montgomery-Smith eq. 14) is folded into the
  transform: for a blend ``b = r + ε·d``, ``p' = (r·p·r* + 2·(d·r*)_vec) / |r|²``; the Plücker
  correction of eq. 14 only changes the scalar part of ``d·r*`` and so drops out.
* blend: ``p' = (1 − b)·LBS + b·DQS`` with a per-vertex ``b`` (Maya's "weight blended").
* COR (Le & Hodgins 2016): ``p' = R·(p − c) + Σ wᵢ·Aᵢ·[c, 1]`` with the vertex's precomputed
  center ``c`` (:mod:`dqskin.cor`), ``R`` the rotation of the DQS blend's real part (the same
  sign rule), ``Σ wᵢ·Sᵢ`` applied to ``p − c`` on frames with a residual; DQS where the vertex has
  no center.
* Sign rule (``InfluenceLayout.running_sum``): 0, each joint's sign is taken against the pivot
  in slot 0 (UsdSkel); otherwise against the running sum of the blend so far, the influences in
  their input order (Blender's Preserve Volume; the layout is then unsorted).

Normals use the inverse transpose of each linear part; tangents the linear part itself; both are
normalized after blending.

Influence layout: one :class:`~.layout.InfluenceLayout` argument (built once per mesh by
:class:`dqskin.influences.Influences`): flat ``indices`` (V·C,) ``wp.vec4i`` and ``weights``
(V·C,) ``wp.vec4`` -- ``K`` influences in ``C = ceil(K/4)`` groups of four, sorted by descending
weight and zero-padded, so slot 0 is the antipodality pivot (the largest weight, first on ties, as
UsdSkel); or, ``unsorted``, in input order with the pivot searched per vertex (a one-shot call
whose ``(V, 4k)`` int32/float32 arrays are read in place: no layout pass); the per-vertex
``blend`` and ``centers`` and the sign rule beside them. Per-(frame, joint) data is a
:class:`Joints` (from :func:`prepare_points`). A kernel reads the layout's arrays into locals once
and hands them to the blends (:func:`gather`, :func:`dq_gather` and
:func:`~.blend.affine_gather`, which the velocity kernels share): one thread per vertex of a
single frame, or per (frame block, vertex), a block of frames read with the vertex's influences
once (:func:`frame_rows`). A 1-D launch over 1-D arrays is what Warp compiles with constant
strides and an inlined task loop on the CPU (2-D arrays are slower on one thread). The point
kernels are specialized at compile time for the method, rigid frames, a
single frame (a kernel of its own, with no frame-block code) and, for DQS, the sorted layout's
sign rule (no running-sum or pivot-search code): code a launch does not run still slows it. On
the CPU, LBS and DQS (each sign rule) of one group of four influences launch
packet kernels instead: a thread skins eight vertices in the lanes of clang vectors
(:mod:`.packets`; faster than the one-vertex kernels on one thread).
Dual quaternions are packed :data:`vec8` in the public order ``(rw, rx, ry, rz, dw, dx, dy, dz)``.
"""

import threading
import weakref
from collections.abc import Sequence
from typing import Any

import warp as wp

from .._warp import Device
from ..errors import InputError
from . import packet_normals, packets
from .blend import affine_gather
from .dqmath import (
    FACTOR_EPSILON,
    RESIDUAL_TOLERANCE,
    dq_blend_add,
    dq_from_rt,
    dq_real_dot,
    dq_sign,
    is_identity33,
    mat34,
    mat44_affine,
    mat44_linear,
    orthonormalize_columns,
    polar_rotation,
    quat_from_rotation,
    vec8,
)
from .grid import (
    FRAME_BLOCK,
    MIN_WORK,
    is_cpu,
    launch,
    launch_rows,
)
from .layout import InfluenceLayout, contiguous_float, contiguous_vec4, contiguous_vec4i

wp.set_module_options({"enable_backward": False})  # forward-only kernels


LBS = wp.constant(0)
DQS = wp.constant(1)
BLEND = wp.constant(2)
COR = wp.constant(3)

POINT_FRAME_BLOCK = wp.constant(FRAME_BLOCK)
"""Frames a point-kernel thread skins (one vertex, :data:`~dqskin.kernels.grid.FRAME_BLOCK`)."""


class Joints:
    """Per (frame, joint) data of the skinning transforms, from :func:`prepare_points_kernel`;
    after :func:`prepare_affines_kernel` (LBS points) only ``affines`` is current, the rest is
    what the previous full preparation left (every call prepares before it reads)."""

    __slots__ = ("affines", "dqs", "residuals", "has_residual")

    affines: wp.array2d(dtype=mat34)
    """(F, J) top rows of the 4×4 transforms (LBS)."""
    dqs: wp.array2d(dtype=vec8)
    """(F, J) unit dual quaternions of their polar rotation and translation (DQS)."""
    residuals: wp.array2d(dtype=wp.mat33)
    """(F, J) scale/shear residuals ``S = Rᵀ·A``."""
    has_residual: wp.array(dtype=wp.int32)
    """(F,) nonzero on frames where some ``S ≠ I``."""


def _prepare_points_kernel(affines_only, name):
    """The per-(frame, joint) preparation, with (False) or without (True, all LBS needs) the
    polar split, fixed at compile time."""

    def kernel(
        xforms: wp.array2d(dtype=wp.mat44),
        row_offset: int,
        # outputs
        affines: wp.array2d(dtype=mat34),
        dqs: wp.array2d(dtype=vec8),
        residuals: wp.array2d(dtype=wp.mat33),
        has_residual: wp.array(dtype=wp.int32),
    ):
        r = wp.tid() + row_offset  # one row per (frame, joint), frame-major
        f = r // xforms.shape[1]
        j = r - f * xforms.shape[1]
        m = xforms[f, j]
        affines[f, j] = mat44_affine(m)
        if wp.static(not affines_only):
            prepare_split(f, j, m, dqs, residuals, has_residual)

    kernel.__doc__ = (_PREPARE_DOC if not affines_only else
                      "Per (frame, joint): the 3×4 affines only (what LBS reads); ``dqs``, "
                      "``residuals`` and ``has_residual`` are left as they were.")
    return wp.kernel(kernel, name=name)


_PREPARE_DOC = """Per (frame, joint): 3×4 affine for LBS; polar split ``A = R·S`` into a unit dual
quaternion and the residual ``S`` for DQS. ``has_residual`` must be zeroed before the launch; it
is set for frames where some ``S ≠ I`` (1e-6, as UsdSkel). A (near-)singular ``A`` (``|det A| <``
:data:`FACTOR_EPSILON`) gets a zero dual quaternion and ``S = I``, as UsdSkel's DQS; a non-finite
one NaN, so it propagates in every method. One thread per (frame, joint), frame-major rows, so a
crowd's frames × joints are split across the CPU threads."""


@wp.func
def prepare_split(f: int, j: int, m: wp.mat44, dqs: wp.array2d(dtype=vec8),
                  residuals: wp.array2d(dtype=wp.mat33), has_residual: wp.array(dtype=wp.int32)):
    """The DQS part of the preparation (see :data:`_PREPARE_DOC`)."""
    a = mat44_linear(m)
    if not wp.isfinite(m):  # device input is not checked on the host: NaN in every method
        dqs[f, j] = vec8(wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan)
        residuals[f, j] = a
        wp.atomic_max(has_residual, f, 1)
        return
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:
        dqs[f, j] = vec8()
        residuals[f, j] = wp.identity(n=3, dtype=float)
        return
    r = polar_rotation(a)
    s = wp.transpose(r) * a
    q = quat_from_rotation(r)
    dqs[f, j] = dq_from_rt(q, wp.vec3(m[0, 3], m[1, 3], m[2, 3]))
    residuals[f, j] = s
    if not is_identity33(s, RESIDUAL_TOLERANCE):
        wp.atomic_max(has_residual, f, 1)


prepare_points_kernel = _prepare_points_kernel(False, "prepare_points_kernel")
prepare_affines_kernel = _prepare_points_kernel(True, "prepare_affines_kernel")


def _prepare_vectors_kernel(linears_only, name):
    """The per-(frame, joint) matrices for directions, with (False) or without (True, all LBS
    reads: ``A`` and ``A⁻ᵀ``) the rotations, fixed at compile time."""

    def kernel(
        xforms: wp.array2d(dtype=wp.mat44),
        # outputs
        linears: wp.array2d(dtype=wp.mat33),
        rotations: wp.array2d(dtype=wp.quat),
        normal_linears: wp.array2d(dtype=wp.mat33),
        normal_residuals: wp.array2d(dtype=wp.mat33),
        normal_rotations: wp.array2d(dtype=wp.quat),
    ):
        f, j = wp.tid()
        a = mat44_linear(xforms[f, j])
        linears[f, j] = a
        if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:  # no inverse: adds nothing, as points
            normal_linears[f, j] = wp.mat33()
            if wp.static(not linears_only):
                rotations[f, j] = wp.quat(0.0, 0.0, 0.0, 0.0)
                normal_residuals[f, j] = wp.identity(n=3, dtype=float)
                normal_rotations[f, j] = wp.quat(0.0, 0.0, 0.0, 0.0)
            return
        n = wp.transpose(wp.inverse(a))
        normal_linears[f, j] = n
        if wp.static(not linears_only):
            rotations[f, j] = quat_from_rotation(polar_rotation(a))
            rn = orthonormalize_columns(n)
            normal_residuals[f, j] = wp.transpose(rn) * n
            normal_rotations[f, j] = quat_from_rotation(rn)

    kernel.__doc__ = ("""Per (frame, joint) matrices for directions. Tangents: the linear part
    ``A`` and its polar rotation (Warp quaternion). Normals: ``N = A⁻ᵀ`` split as UsdSkel does,
    ``N = Rn·(Rnᵀ·N)`` with ``Rn`` from :func:`orthonormalize_columns`.""" if not linears_only
                      else "Per (frame, joint): ``A`` and ``N = A⁻ᵀ`` only (what LBS reads); the "
                      "rotations and normal residuals are left as they were.")
    return wp.kernel(kernel, name=name)


prepare_vectors_kernel = _prepare_vectors_kernel(False, "prepare_vectors_kernel")
prepare_linears_kernel = _prepare_vectors_kernel(True, "prepare_linears_kernel")


@wp.func
def heavier(j: int, wm: float, iv: wp.vec4i, wv: wp.vec4):
    """``(joint, weight)`` of the largest weight after one more group, the earlier on ties."""
    for k in range(4):
        if wv[k] > wm:
            wm = wv[k]
            j = iv[k]
    return j, wm


@wp.func
def dqs_apply(b: vec8, x: wp.vec3):
    """Apply a blended (unnormalized) dual quaternion ``b = r + ε·d`` to ``x``, normalization
    folded in: ``x + 2·(r⃗×(r⃗×x + r_w·x) + r_w·d⃗ − d_w·r⃗ + r⃗×d⃗)/|r|²``. A zero blend (all
    weights zero) leaves ``x`` unchanged, as Gf's normalize returns the identity."""
    rv = wp.vec3(b[1], b[2], b[3])
    rw = b[0]
    dv = wp.vec3(b[5], b[6], b[7])
    s = 2.0 / wp.max(rw * rw + wp.dot(rv, rv), 1.0e-30)
    return x + s * (wp.cross(rv, wp.cross(rv, x) + rw * x) + rw * dv - b[4] * rv + wp.cross(rv, dv))


@wp.func
def rotation_only(b: vec8):
    """The real part of a blend, dual part zeroed: :func:`dqs_apply` then only rotates."""
    return vec8(b[0], b[1], b[2], b[3], 0.0, 0.0, 0.0, 0.0)


@wp.func
def by_method(method: int, lbs: wp.vec3, dqs: wp.vec3, blend: wp.array(dtype=float), v: int):
    """The result of ``method``: ``lbs``, ``dqs`` (also for COR, whose directions rotate as DQS's)
    or their per-vertex blend ``(1 − b)·lbs + b·dqs``, ``b = blend[v]``."""
    if method == LBS:
        return lbs
    if method == DQS or method == COR:
        return dqs
    b = blend[v]
    return lbs * (1.0 - b) + dqs * b


@wp.func
def group(indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4), v: int,
          groups: int, c: int, iv: wp.vec4i, wv: wp.vec4):
    """Influence group ``c`` of vertex ``v`` (group 0, ``iv`` and ``wv``, already read)."""
    if c == 0:
        return iv, wv
    return indices[v * groups + c], weights[v * groups + c]


@wp.func
def frame_rows(t: int, rows: int, frame_count: int):
    """``(row, first frame, end frame)`` of thread ``t`` of a flat launch: row ``t`` of the only
    frame, or row ``t mod rows`` of frame block ``t div rows``."""
    if frame_count == 1:
        return t, 0, 1
    block = t // rows
    first = block * POINT_FRAME_BLOCK
    return t - block * rows, first, wp.min(first + POINT_FRAME_BLOCK, frame_count)


@wp.func
def gather4(values: wp.array(dtype=Any), o: int, iv: wp.vec4i, wv: wp.vec4):
    """``Σ wᵢ·X[o + jᵢ]`` over one group of four influences (``o``: the frame's first joint)."""
    return (values[o + iv[0]] * wv[0] + values[o + iv[1]] * wv[1] + values[o + iv[2]] * wv[2]
            + values[o + iv[3]] * wv[3])


@wp.func
def gather(values: wp.array(dtype=Any), o: int, indices: wp.array(dtype=wp.vec4i),
           weights: wp.array(dtype=wp.vec4), v: int, groups: int, iv: wp.vec4i, wv: wp.vec4):
    """``Σ wᵢ·Xᵢ`` over the vertex's ``groups`` groups, group 0 (``iv``, ``wv``) already read."""
    acc = gather4(values, o, iv, wv)
    for c in range(1, groups):
        ic, wc = group(indices, weights, v, groups, c, iv, wv)
        acc += gather4(values, o, ic, wc)
    return acc


@wp.func
def dq_add4(b: vec8, dqs: wp.array(dtype=vec8), o: int, iv: wp.vec4i, wv: wp.vec4, pv: vec8,
            running_sum: int):
    """:func:`~dqskin.kernels.dqmath.dq_blend_add` of one group, signs against ``pv`` or (with
    ``running_sum``) against the sum so far."""
    if running_sum != 0:
        for k in range(4):
            b = dq_blend_add(b, dqs[o + iv[k]], wv[k], b)
        return b
    for k in range(4):
        b = dq_blend_add(b, dqs[o + iv[k]], wv[k], pv)
    return b


@wp.func
def dq_gather(dqs: wp.array(dtype=vec8), o: int, indices: wp.array(dtype=wp.vec4i),
              weights: wp.array(dtype=wp.vec4), v: int, groups: int, iv: wp.vec4i, wv: wp.vec4,
              pivot: int, unsorted: int, running_sum: int):
    """Sign-aligned weighted sum of the vertex's dual quaternions at the frame's joints ``o``
    (antipodality; a zero sum flips nothing); ``pivot`` the vertex's largest-weight joint
    (:func:`flat_pivot`: slot 0 unless ``unsorted``). The first term is set, not added to zero;
    its sign is +1 against itself or against the running sum's zero."""
    d0 = dqs[o + iv[0]]
    b = d0 * wv[0]
    if running_sum != 0:
        if groups == 1:
            # the running sum's signs from the pairwise dots of the four real parts: a chain of
            # scalars instead of one of dual quaternions (b_k · d_k = Σ_{m<k} s_m·w_m·(d_m · d_k))
            d1 = dqs[o + iv[1]]
            d2 = dqs[o + iv[2]]
            d3 = dqs[o + iv[3]]
            w0 = wv[0]
            s1 = wv[1] * wp.sign(w0 * dq_real_dot(d0, d1))
            s2 = wv[2] * wp.sign(w0 * dq_real_dot(d0, d2) + s1 * dq_real_dot(d1, d2))
            s3 = wv[3] * wp.sign(w0 * dq_real_dot(d0, d3) + s1 * dq_real_dot(d1, d3)
                                 + s2 * dq_real_dot(d2, d3))
            return b + d1 * s1 + d2 * s2 + d3 * s3
        for k in range(1, 4):
            b = dq_blend_add(b, dqs[o + iv[k]], wv[k], b)
        for c in range(1, groups):
            b = dq_add4(b, dqs, o, indices[v * groups + c], weights[v * groups + c], b, 1)
        return b
    pv = d0
    if unsorted != 0:
        pv = dqs[o + pivot]
        b = d0 * (wv[0] * dq_sign(d0, pv))
    for k in range(1, 4):
        b = dq_blend_add(b, dqs[o + iv[k]], wv[k], pv)
    for c in range(1, groups):
        b = dq_add4(b, dqs, o, indices[v * groups + c], weights[v * groups + c], pv, 0)
    return b


@wp.func
def flat_pivot(indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4), v: int,
               groups: int, iv: wp.vec4i, wv: wp.vec4, unsorted: int):
    """The joint of the vertex's largest weight, first on ties (once per vertex, not per frame):
    slot 0 of a sorted layout, else searched (``unsorted``)."""
    j = iv[0]
    if unsorted == 0:
        return j
    j, wm = heavier(j, wv[0], iv, wv)
    for c in range(1, groups):
        j, wm = heavier(j, wm, indices[v * groups + c], weights[v * groups + c])
    return j


@wp.func(inline=True)
def skin_frame(p: wp.vec3, v: int, f: int, o: int, iv: wp.vec4i, wv: wp.vec4, pivot: int,
               inf: InfluenceLayout, unsorted: int, running_sum: int,
               affines: wp.array(dtype=mat34), dqs: wp.array(dtype=vec8),
               residuals: wp.array(dtype=wp.mat33), has_residual: wp.array(dtype=wp.int32),
               method: int, residual: bool):
    """Point ``p`` of vertex ``v`` skinned with ``method`` at frame ``f`` (its joints from ``o``;
    group 0 of its influences, ``iv`` and ``wv``, already read); ``unsorted`` and
    ``running_sum``: ``inf``'s sign rule or the kernel's compile-time one; ``method`` and
    ``residual`` (the frame may have scale/shear) are compile-time constants, so only one
    method's code remains."""
    indices = contiguous_vec4i(inf.indices)
    weights = contiguous_vec4(inf.weights)
    groups = inf.groups
    if method == LBS:
        return affine_gather(affines, o, indices, weights, v, groups, iv, wv) * wp.vec4(
            p[0], p[1], p[2], 1.0)
    if method == COR:
        c4 = contiguous_vec4(inf.centers)[v]
        if c4[3] != 0.0:
            c = wp.vec3(c4[0], c4[1], c4[2])
            y = p - c
            if residual:
                if has_residual[f] != 0:
                    y = gather(residuals, o, indices, weights, v, groups, iv, wv) * y
            lc = affine_gather(affines, o, indices, weights, v, groups, iv, wv) * wp.vec4(
                c[0], c[1], c[2], 1.0)
            return dqs_apply(rotation_only(dq_gather(dqs, o, indices, weights, v, groups, iv, wv,
                                                     pivot, unsorted, running_sum)), y) + lc
    x = p
    if residual:
        if has_residual[f] != 0:
            x = gather(residuals, o, indices, weights, v, groups, iv, wv) * p
    d = dqs_apply(dq_gather(dqs, o, indices, weights, v, groups, iv, wv, pivot, unsorted,
                            running_sum), x)
    lbs = wp.vec3()
    if method == BLEND:
        lbs = affine_gather(affines, o, indices, weights, v, groups, iv, wv) * wp.vec4(
            p[0], p[1], p[2], 1.0)
    return by_method(method, lbs, d, contiguous_float(inf.blend), v)


SIGN_RULES = (None, "sorted", "searched", "running")
"""A point kernel's sign rule: None read at run time (``InfluenceLayout.running_sum`` and
``unsorted``), or fixed at compile time (DQS): the pivot in slot 0 of the sorted layout (a
Skinner's default), the pivot searched per vertex in input order (one-shot calls), the running
sum in input order (no pivot to search)."""


def _skin_points_kernel(method, residual, single, sign=None, packet=False):
    """The point kernel of one method, specialized at compile time: ``residual=False`` drops the
    scale/shear code (faster on the CPU for rigid launches); ``single`` skins one frame
    (``frame_count == 1``) with no frame-block code beside it (an unused frame loop in the same
    kernel slows the one-frame path); ``sign`` (DQS, one of :data:`SIGN_RULES`) fixes the sign
    rule at compile time, so only its code remains. The influence-group count stays a runtime
    argument: a kernel specialized for ``K <= 4`` is no faster and doubles the module's compile
    time. ``packet`` (CPU; LBS, or DQS with any sign rule; one group of four influences):
    thread ``t`` skins eight vertices at once (:mod:`.packets`), row ``t`` of ``ceil(V / 8)``
    per frame (one frame or a frame block alike)."""
    packet_func = packets.PACKETS.get((method, sign)) if packet else None

    def kernel(
        points: wp.array(dtype=wp.vec3),
        point_stride: int,
        inf: InfluenceLayout,
        affines: wp.array(dtype=mat34),
        dqs: wp.array(dtype=vec8),
        residuals: wp.array(dtype=wp.mat33),
        has_residual: wp.array(dtype=wp.int32),
        joint_count: int,
        frame_count: int,
        check: int,
        row_offset: int,
        # outputs
        out: wp.array(dtype=wp.vec3),
        flags: wp.array(dtype=wp.int32),
    ):
        t = wp.tid() + row_offset
        indices = contiguous_vec4i(inf.indices)
        weights = contiguous_vec4(inf.weights)
        if wp.static(packet):  # eight vertices a thread
            vertex_count = out.shape[0] // frame_count
            pr, pfirst, pend = frame_rows(t, (vertex_count + 7) // 8, frame_count)
            for f in range(pfirst, pend):  # one frame: pfirst 0, pend 1
                pbase = wp.int64(f) * wp.int64(point_stride)
                obase = wp.int64(f) * wp.int64(vertex_count)
                if wp.static(method == LBS):
                    packet_func(points, pbase, indices, weights, affines, f * joint_count,
                                pr * 8, vertex_count, out, obase, joint_count, check, flags)
                else:  # DQS: the frame's residual flag read, set on frames with scale/shear
                    packet_func(points, pbase, indices, weights, dqs, residuals, has_residual[f],
                                f * joint_count, pr * 8, vertex_count, out, obase, joint_count,
                                check, flags)
            return
        g = inf.groups
        # the sign-rule flags, constants (folded by the C++ compiler) unless read at run time
        rs = inf.running_sum * wp.static(int(sign is None)) + wp.static(int(sign == "running"))
        us = inf.unsorted * wp.static(int(sign is None)) + wp.static(int(sign == "searched"))
        if wp.static(single):  # one frame: vertex t, no frame loop
            iv = indices[t * g]
            wv = weights[t * g]
            pivot = iv[0]  # LBS has no sign rule: no search
            if wp.static(method != LBS):
                pivot = flat_pivot(indices, weights, t, g, iv, wv, us)
            out[t] = skin_frame(points[t], t, 0, 0, iv, wv, pivot, inf, us, rs, affines, dqs,
                                residuals, has_residual, wp.static(method), wp.static(residual))
            return
        vertex_count = out.shape[0] // frame_count
        v, first, end = frame_rows(t, vertex_count, frame_count)
        iv = indices[v * g]
        wv = weights[v * g]
        pivot = iv[0]  # LBS has no sign rule: no search
        if wp.static(method != LBS):
            pivot = flat_pivot(indices, weights, v, g, iv, wv, us)
        for f in range(first, end):
            out[wp.int64(f) * wp.int64(vertex_count) + wp.int64(v)] = skin_frame(
                points[wp.int64(f) * wp.int64(point_stride) + wp.int64(v)], v, f, f * joint_count,
                iv, wv, pivot, inf, us, rs, affines, dqs, residuals, has_residual,
                wp.static(method), wp.static(residual))

    rigid = "_rigid" if method in (DQS, COR) and not residual else ""
    one = "_one_frame" if single else ""
    rule = f"_{sign}" if sign else ""
    eight = "_packet" if packet else ""
    label = ['lbs', 'dqs', 'blend', 'cor'][method]
    name = f"skin_{label}{rigid}_kernel{one}{rule}{eight}"
    kernel.__doc__ = (f"Skin flat ``points`` (Fp·V) bind space, Fp 1 or F, into ``out`` (F·V) "
                      f"with method {method}; thread ``t``: vertex ``t`` of "
                      + ("the only frame." if single else "frame block ``t div V``, vertex "
                         "``t mod V``."))
    # one Warp module per method, forward-only as this one: a process builds, hashes and loads
    # only the kernels of the methods it uses (a shorter first skin call)
    module = f"{__name__}.{label}"
    wp.set_module_options({"enable_backward": False}, module=module)
    return wp.kernel(kernel, name=name, module=module)


class _PointKernels(dict):
    """:data:`SKIN_POINTS_KERNELS`: ``(method, residual, sign, packet)`` specs, one frame and
    frame blocks; a packet kernel serves both (one kernel object under both keys). A method's
    kernels are all defined on the first look-up of any of them (its Warp module then holds the
    same kernels whatever was asked first), so a process defines only the methods it uses."""

    def __init__(self, specs):
        super().__init__()
        self._specs = specs
        self._lock = threading.Lock()

    def __missing__(self, key):
        with self._lock:
            if key not in self:
                for m, r, sign, packet in self._specs:
                    if m != key[0]:
                        continue
                    for one in (True, False):
                        k = (m, r, one, sign, packet)
                        self[k] = (self[(m, r, True, sign, True)] if packet and not one
                                   else _skin_points_kernel(m, r, one and not packet, sign,
                                                            packet))
            return dict.__getitem__(self, key)  # KeyError for a key of no spec


SKIN_POINTS_KERNELS = _PointKernels((
    (LBS, False, None, False), (LBS, False, None, True),
    (DQS, True, "sorted", False), (DQS, False, "sorted", False), (DQS, True, "sorted", True),
    (DQS, True, "searched", False), (DQS, False, "searched", False),
    (DQS, True, "searched", True), (DQS, True, "running", False), (DQS, False, "running", False),
    (DQS, True, "running", True),
    (BLEND, True, None, False), (COR, True, None, False), (COR, False, None, False)))
"""The point-skinning kernels by ``(method, residual code, one frame, sign rule, packet)``: LBS
needs no residual code and has no sign rule, BLEND always has the residual code; DQS kernels have
their sign rule fixed (:data:`SIGN_RULES`), BLEND and COR read it at run time; packet kernels
(:mod:`.packets`, the CPU's) for LBS and DQS of each sign rule, which read each frame's
residual flag (one kernel for rigid and scaled launches: the flag is one load per eight
vertices) and have no one-frame variant (one frame runs the frame loop once, as fast as a
variant of its own would)."""


@wp.func
def dqs_vector(x: wp.vec3, v: int, f: int, o: int, iv: wp.vec4i, wv: wp.vec4, pivot: int,
               indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4), groups: int,
               running_sum: int, rotations: wp.array(dtype=wp.quat),
               residuals: wp.array(dtype=wp.mat33), has_residual: wp.array(dtype=wp.int32)):
    """Rotation-only DQS of a direction (sign-aligned quaternion blend, the sign rule of
    :func:`dq_gather`), unit length."""
    ref = rotations[o + pivot]
    r = wp.quat(0.0, 0.0, 0.0, 0.0)
    for c in range(groups):
        ic, wc = group(indices, weights, v, groups, c, iv, wv)
        for k in range(4):
            if running_sum != 0:
                ref = r
            q = rotations[o + ic[k]]
            r += q * (wc[k] * wp.sign(wp.dot(q, ref)))
    scaled = x
    if has_residual[f] != 0:
        scaled = gather(residuals, o, indices, weights, v, groups, iv, wv) * x
    if wp.length(r) < 1.0e-10:
        return wp.normalize(scaled)
    return wp.normalize(wp.quat_rotate(wp.normalize(r), scaled))


@wp.kernel
def skin_vectors_kernel(
    vectors: wp.array(dtype=wp.vec3),
    vector_stride: int,
    vector_vertex: wp.array(dtype=wp.int32),
    inf: InfluenceLayout,
    linears: wp.array(dtype=wp.mat33),
    rotations: wp.array(dtype=wp.quat),
    residuals: wp.array(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    joint_count: int,
    frame_count: int,
    method: int,
    row_offset: int,
    # outputs
    out: wp.array(dtype=wp.vec3),
):
    """Skin directions (normals or tangents), normalized, flat as the point kernels.

    ``vectors`` (Fp·N); ``vector_vertex`` (N,) maps each vector to the vertex whose influences it
    uses (identity for per-vertex data, the face-vertex map for faceVarying). For normals pass the
    inverse-transpose matrices and the rotations UsdSkel derives from them; for tangents the
    matrices themselves and their polar rotations.
    """
    indices = contiguous_vec4i(inf.indices)
    weights = contiguous_vec4(inf.weights)
    groups = inf.groups
    running_sum = inf.running_sum
    unsorted = inf.unsorted
    rows = out.shape[0] // frame_count
    n, first, end = frame_rows(wp.tid() + row_offset, rows, frame_count)
    v = vector_vertex[n]
    iv = indices[v * groups]
    wv = weights[v * groups]
    pivot = flat_pivot(indices, weights, v, groups, iv, wv, unsorted)
    for f in range(first, end):
        o = f * joint_count
        x = vectors[wp.int64(f) * wp.int64(vector_stride) + wp.int64(n)]
        lbs = wp.vec3()
        dqs = wp.vec3()
        if method == LBS or method == BLEND:
            lbs = wp.normalize(gather(linears, o, indices, weights, v, groups, iv, wv) * x)
        if method != LBS:
            dqs = dqs_vector(x, v, f, o, iv, wv, pivot, indices, weights, groups, running_sum,
                             rotations, residuals, has_residual)
        out[wp.int64(f) * wp.int64(rows) + wp.int64(n)] = wp.normalize(
            by_method(method, lbs, dqs, contiguous_float(inf.blend), v))


@wp.kernel
def transform_frames_kernel(
    xforms: wp.array(dtype=wp.mat44),
    normalize: int,
    # outputs
    values: wp.array2d(dtype=wp.vec3),
):
    """In place ``values[f, i] = xforms[f] · [values[f, i], 1]`` (points). For directions pass the
    inverse transpose with a zero translation and ``normalize = 1``."""
    f, i = wp.tid()
    y = wp.transform_point(xforms[f], values[f, i])
    if normalize != 0:
        y = wp.normalize(y)
    values[f, i] = y


# ---------------------------------------------------------------------------------------------
# launchers: keyword arguments, chunked over the CPU cores by dqskin.kernels.grid


def joints(*, affines: wp.array, dqs: wp.array, residuals: wp.array,
           has_residual: wp.array) -> Joints:
    """The :class:`Joints` of (F, J) work arrays."""
    s = Joints()
    s.affines, s.dqs, s.residuals, s.has_residual = affines, dqs, residuals, has_residual
    return s


def prepare_points(*, xforms: wp.array, joints: Joints, device: Device,
                   affines_only: bool = False) -> None:
    """Fill ``joints`` (a :class:`Joints` of (F, J) arrays) from ``xforms`` (F, J) ``wp.mat44``;
    ``affines_only``: only ``joints.affines`` (all LBS reads), the rest left as it was."""
    kernel = prepare_affines_kernel if affines_only else prepare_points_kernel
    if not affines_only:
        joints.has_residual.zero_()
    launch_rows(kernel, xforms.shape[0] * xforms.shape[1], [xforms],
                [joints.affines, joints.dqs, joints.residuals, joints.has_residual], device)


def prepare_vectors(*, xforms: wp.array, linears: wp.array, rotations: wp.array,
                    normal_linears: wp.array, normal_residuals: wp.array,
                    normal_rotations: wp.array, device: Device,
                    linears_only: bool = False) -> None:
    """Per (frame, joint) data of :func:`skin_vectors` (see :func:`prepare_vectors_kernel`);
    ``linears_only``: ``linears`` and ``normal_linears`` only (all LBS reads)."""
    kernel = prepare_linears_kernel if linears_only else prepare_vectors_kernel
    launch(kernel, xforms.shape, [xforms],
           [linears, rotations, normal_linears, normal_residuals, normal_rotations], device)


_flat_views = weakref.WeakKeyDictionary()


def _flat(a):
    """A 1-D view of contiguous array ``a`` (itself when 1-D), made once per array: making a view
    costs about half of a small launch. The view does not own or reference ``a`` (a cached view
    holding ``a`` would keep it alive): it is launched only while its caller holds ``a`` (the
    launches are synchronous), and the cache entry dies with ``a``; recorded launches keep
    only weak references (:mod:`.grid`)."""
    if a.ndim == 1:
        return a
    view = _flat_views.get(a)
    if view is None:
        if not a.is_contiguous:
            raise InputError(f"expected a contiguous array, got strides {a.strides}")
        if a.size == 0:
            view = wp.empty(0, dtype=a.dtype, device=a.device)
        else:
            view = wp.array(ptr=a.ptr, shape=(a.size,), dtype=a.dtype, device=a.device,
                            copy=False)
        _flat_views[a] = view
    return view


def frame_rows_array(values: wp.array, rows: int) -> tuple[wp.array, int]:
    """``(flat view, frame stride)`` of (Fp, rows) per-frame inputs, Fp 1 or F: stride 0 when one
    row serves every frame (also a row broadcast with stride 0)."""
    stride = rows if values.shape[0] > 1 else 0
    if stride and values.strides[0] == 0:
        row = values[0]  # contiguous, as the packet kernels read it (a copy of one row if not)
        return (row if row.is_contiguous else row.contiguous()), 0
    if not values.is_contiguous:  # a copy: flattened with a reference to it
        return values.contiguous().flatten(), stride
    return _flat(values), stride


def launch_frames(kernel: wp.Kernel, rows: int, frames: int, inputs: Sequence[Any],
                  outputs: Sequence[wp.array], device: Device, row_size: int = 1) -> None:
    """Launch a flat kernel (:func:`frame_rows`) over ``rows`` × ``frames``: one thread per row
    of a single frame, else per (frame block, row); chunks of threads on the CPU cores.
    ``row_size``: the rows (vertices) a thread's row stands for, to size the chunks."""
    if rows <= 0 or frames <= 0:
        return
    launch_rows(kernel, rows * -(-frames // FRAME_BLOCK), inputs, [_flat(o) for o in outputs],
                device, min_chunk=-(-MIN_WORK // (min(frames, FRAME_BLOCK) * row_size)))


def takes_packets(method: int, running_sum: int, groups: int, joint_count: int,
                  device: Device) -> bool:
    """Whether :func:`skin_points` runs a packet kernel (:mod:`.packets`): on the CPU, LBS or DQS
    (any sign rule) of one group of four influences, with at least one joint."""
    return method in (LBS, DQS) and groups == 1 and joint_count > 0 and is_cpu(device)


_no_flags = {}


def skin_points(*, method: int, points: wp.array, influences: InfluenceLayout, joints: Joints,
                rigid: bool, out: wp.array, device: Device, flags: wp.array | None = None) -> None:
    """Skin ``points`` (Fp, V) into ``out`` (F, V) with ``method`` (:data:`LBS`, :data:`DQS`,
    :data:`BLEND`, :data:`COR`) and ``influences`` (an :class:`~.layout.InfluenceLayout`).
    ``rigid`` (no frame has a residual) selects the DQS or COR kernel without the residual code.
    ``flags``: a zeroed (1,) ``int32`` array that a packet launch (:func:`takes_packets`; others
    raise) sets to 1 when a point is not finite, an index is outside the joints or a weight is
    negative or not finite: inputs unchecked on the host."""
    residual = method == BLEND or (method != LBS and not rigid)
    frames, verts = out.shape
    sign = None
    if method == DQS:
        sign = ("running" if influences.running_sum else
                "searched" if influences.unsorted else "sorted")
    jn = joints
    packet = takes_packets(method, influences.running_sum, influences.groups,
                           jn.affines.shape[1], device)
    if flags is None:
        key = str(device)
        flags = _no_flags.get(key)
        if flags is None:
            flags = _no_flags[key] = wp.empty(0, dtype=wp.int32, device=device)
        check = 0
    elif not packet:
        raise RuntimeError("skin_points: inputs can be checked by packet launches only")
    else:
        check = 1
    kernel = SKIN_POINTS_KERNELS[(method, residual or (packet and method == DQS), frames == 1,
                                  sign, packet)]
    size = packets.VERTICES if packet else 1
    launch_frames(kernel, -(-verts // size), frames,
                  [*frame_rows_array(points, verts), influences,
                   _flat(jn.affines), _flat(jn.dqs), _flat(jn.residuals), jn.has_residual,
                   jn.affines.shape[1], frames, check], [out, flags], device, row_size=size)


def skin_vectors(*, method: int, vectors: wp.array, vector_vertex: wp.array,
                 influences: InfluenceLayout, linears: wp.array, rotations: wp.array,
                 residuals: wp.array, has_residual: wp.array, out: wp.array,
                 device: Device) -> None:
    """Skin directions ``vectors`` (Fp, N) into ``out`` (F, N) with ``influences`` (an
    :class:`~.layout.InfluenceLayout`), normalized (see
    :func:`skin_vectors_kernel` for which per-joint arrays normals and tangents take). On the
    CPU, LBS, DQS and COR of one influence group run eight rows a thread
    (:mod:`.packet_normals`)."""
    frames, rows = out.shape
    if (method in (LBS, DQS, COR) and influences.groups == 1 and linears.shape[1] > 0
            and is_cpu(device)):
        # eight rows a thread (:mod:`.packet_normals`), bit for bit the kernel below
        if method == LBS:
            kernel, joint_data = (packet_normals.skin_vectors_lbs_packet_kernel,
                                  [_flat(linears)])
        else:
            rule = 2 if influences.running_sum else 1 if influences.unsorted else 0
            kernel, joint_data = (packet_normals.skin_vectors_dqs_packet_kernel,
                                  [_flat(rotations), _flat(residuals), has_residual])
        launch_frames(kernel, -(-rows // 8), frames,
                      [*frame_rows_array(vectors, rows), vector_vertex, influences, *joint_data,
                       linears.shape[1], frames, *([] if method == LBS else [rule])], [out],
                      device, row_size=packet_normals.ROWS)
        return
    launch_frames(skin_vectors_kernel, rows, frames,
                  [*frame_rows_array(vectors, rows), vector_vertex, influences,
                   _flat(linears), _flat(rotations), _flat(residuals), has_residual,
                   linears.shape[1], frames, int(method)], [out], device)


def transform_frames(*, xforms: wp.array, normalize: bool, values: wp.array,
                     device: Device) -> None:
    """In place ``values[f, i] = xforms[f]·[values[f, i], 1]`` (normalized with ``normalize``)."""
    launch(transform_frames_kernel, values.shape, [xforms, int(normalize)], [values], device)
