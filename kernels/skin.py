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
* Sign rule (``Influences.running_sum``): 0, each joint's sign is taken against the pivot in slot 0
  (UsdSkel); otherwise against the running sum of the blend so far, the influences in their input
  order (Blender's Preserve Volume; the layout is then unsorted).

Normals use the inverse transpose of each linear part; tangents the linear part itself; both are
normalized after blending.

Influence layout (:class:`Influences`, built once per mesh by
:class:`dqskin.influences.Influences`): ``indices`` (V, C) ``wp.vec4i`` and ``weights`` (V, C)
``wp.vec4`` -- ``K`` influences in ``C = ceil(K/4)`` groups of four, sorted by descending weight
and zero-padded, so slot 0 is the antipodality pivot (the largest weight, first on ties, as
UsdSkel); or, ``unsorted``, in input order with the pivot searched per vertex (a one-shot call
whose ``(V, 4k)`` int32/float32 arrays are read in place: no layout pass). Per-(frame, joint)
data is a :class:`Joints` (from :func:`prepare_points`). The direction and velocity kernels blend
influences through the ``@wp.func`` blends on these structs, on (frame block, row) grids. The point
kernels read the same arrays as flat 1-D views (the ``gather`` blends), one thread per vertex of a
single frame, or per (frame block, vertex) with a block of frames read once per vertex: a 1-D
launch over 1-D arrays is what Warp compiles with constant strides and an inlined task loop on the
CPU. They are specialized at compile time for the method, rigid frames and ``K <= 4``.
Dual quaternions are packed :data:`vec8` in the public order ``(rw, rx, ry, rz, dw, dx, dy, dz)``.
"""

import weakref
from typing import Any

import warp as wp

from .dqmath import (
    FACTOR_EPSILON,
    RESIDUAL_TOLERANCE,
    dq_blend_add,
    dq_from_rt,
    dq_sign,
    is_identity33,
    mat34,
    mat44_linear,
    orthonormalize_columns,
    polar_rotation,
    quat_from_rotation,
    vec8,
)
from .grid import (
    FRAME_BLOCK,
    MIN_WORK,
    FrameBlocks,
    block_frames,
    launch,
    launch_blocks,
    launch_rows,
)

wp.set_module_options({"enable_backward": False})  # forward-only kernels


LBS = wp.constant(0)
DQS = wp.constant(1)
BLEND = wp.constant(2)
COR = wp.constant(3)

POINT_FRAME_BLOCK = wp.constant(FRAME_BLOCK)
"""Frames a point-kernel thread skins (one vertex, :data:`~dqskin.kernels.grid.FRAME_BLOCK`)."""


@wp.struct
class Influences:
    """A mesh's influences in the kernels' layout (see the module docstring)."""

    indices: wp.array2d(dtype=wp.vec4i)
    """(V, C) joint indices, four per group, largest weight first."""
    weights: wp.array2d(dtype=wp.vec4)
    """(V, C) weights, same layout."""
    blend: wp.array(dtype=float)
    """(V,) DQS fraction of ``method=BLEND``; empty otherwise."""
    centers: wp.array(dtype=wp.vec4)
    """(V,) centers of rotation of ``method=COR`` (bind space, ``w = 1``; ``w = 0``: none, the
    vertex falls back to DQS); empty otherwise."""
    running_sum: int
    """Sign reference of the rotation blends: 0 the pivot in slot 0 (largest weight, UsdSkel);
    nonzero the running sum of the blend so far, the slots in their input order (Blender)."""
    unsorted: int
    """Nonzero: the slots are in input order, not sorted by weight, and the pivot of
    ``running_sum = 0`` is searched per vertex (:func:`pivot_joint`)."""


@wp.struct
class Joints:
    """Per (frame, joint) data of the skinning transforms, from :func:`prepare_points_kernel`."""

    affines: wp.array2d(dtype=mat34)
    """(F, J) top rows of the 4×4 transforms (LBS)."""
    dqs: wp.array2d(dtype=vec8)
    """(F, J) unit dual quaternions of their polar rotation and translation (DQS)."""
    residuals: wp.array2d(dtype=wp.mat33)
    """(F, J) scale/shear residuals ``S = Rᵀ·A``."""
    has_residual: wp.array(dtype=wp.int32)
    """(F,) nonzero on frames where some ``S ≠ I``."""


@wp.kernel
def prepare_points_kernel(
    xforms: wp.array2d(dtype=wp.mat44),
    # outputs
    affines: wp.array2d(dtype=mat34),
    dqs: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
):
    """Per (frame, joint): 3×4 affine for LBS; polar split ``A = R·S`` into a unit dual
    quaternion and the residual ``S`` for DQS. ``has_residual`` must be
    zeroed before the launch; it is set for frames where some ``S ≠ I`` (1e-6, as UsdSkel).
    A (near-)singular ``A`` (``|det A| <`` :data:`FACTOR_EPSILON`) gets a zero dual quaternion
    and ``S = I``, as UsdSkel's DQS; a non-finite one NaN, so it propagates in every method."""
    f, j = wp.tid()
    m = xforms[f, j]
    affines[f, j] = mat34(m[0, 0], m[0, 1], m[0, 2], m[0, 3],
                          m[1, 0], m[1, 1], m[1, 2], m[1, 3],
                          m[2, 0], m[2, 1], m[2, 2], m[2, 3])
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


@wp.kernel
def prepare_vectors_kernel(
    xforms: wp.array2d(dtype=wp.mat44),
    # outputs
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    normal_linears: wp.array2d(dtype=wp.mat33),
    normal_residuals: wp.array2d(dtype=wp.mat33),
    normal_rotations: wp.array2d(dtype=wp.quat),
):
    """Per (frame, joint) matrices for directions. Tangents: the linear part ``A`` and its polar
    rotation (Warp quaternion). Normals:
    ``N = A⁻ᵀ`` split as UsdSkel does, ``N = Rn·(Rnᵀ·N)`` with ``Rn`` from
    :func:`orthonormalize_columns`."""
    f, j = wp.tid()
    a = mat44_linear(xforms[f, j])
    linears[f, j] = a
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:  # no inverse: adds nothing, as for points
        rotations[f, j] = wp.quat(0.0, 0.0, 0.0, 0.0)
        normal_linears[f, j] = wp.mat33()
        normal_residuals[f, j] = wp.identity(n=3, dtype=float)
        normal_rotations[f, j] = wp.quat(0.0, 0.0, 0.0, 0.0)
        return
    rotations[f, j] = quat_from_rotation(polar_rotation(a))
    n = wp.transpose(wp.inverse(a))
    rn = orthonormalize_columns(n)
    normal_linears[f, j] = n
    normal_residuals[f, j] = wp.transpose(rn) * n
    normal_rotations[f, j] = quat_from_rotation(rn)


@wp.func
def blend4(values: wp.array2d(dtype=Any), f: int, iv: wp.vec4i, wv: wp.vec4):
    """``Σ wᵢ·Xᵢ`` over one group of four influences of frame ``f``."""
    return (values[f, iv[0]] * wv[0] + values[f, iv[1]] * wv[1] + values[f, iv[2]] * wv[2]
            + values[f, iv[3]] * wv[3])


@wp.func
def blend_groups(inf: Influences, v: int, f: int, values: wp.array2d(dtype=Any), groups: int):
    """:func:`blend_joints` over the first ``groups`` groups (a compile-time 1 in the kernels
    specialized for ``K <= 4``: no loop)."""
    acc = blend4(values, f, inf.indices[v, 0], inf.weights[v, 0])
    for c in range(1, groups):
        acc += blend4(values, f, inf.indices[v, c], inf.weights[v, c])
    return acc


@wp.func
def blend_joints(inf: Influences, v: int, f: int, values: wp.array2d(dtype=Any)):
    """``Σ wᵢ·Xᵢ`` of the vertex's per-joint values (F, J): 3×4 affines (LBS) and their
    derivatives, 3×3 residuals ``S`` (DQS) and linear parts (directions)."""
    return blend_groups(inf, v, f, values, inf.indices.shape[1])


@wp.func
def heavier(j: int, wm: float, iv: wp.vec4i, wv: wp.vec4):
    """``(joint, weight)`` of the largest weight after one more group, the earlier on ties."""
    for k in range(4):
        if wv[k] > wm:
            wm = wv[k]
            j = iv[k]
    return j, wm


@wp.func
def pivot_joint(inf: Influences, v: int, groups: int):
    """The joint of the vertex's largest weight, first on ties: slot 0 of a sorted layout, else
    searched (``inf.unsorted``)."""
    iv = inf.indices[v, 0]
    j = iv[0]
    if inf.unsorted == 0:
        return j
    wm = inf.weights[v, 0][0]
    for c in range(groups):
        j, wm = heavier(j, wm, inf.indices[v, c], inf.weights[v, c])
    return j


@wp.func
def dqs_blend_groups(inf: Influences, v: int, f: int, dqs: wp.array2d(dtype=vec8), groups: int):
    """:func:`dqs_blend` over the first ``groups`` groups."""
    b = vec8()
    if inf.running_sum != 0:  # (one branch per vertex, not per influence)
        for c in range(groups):
            iv = inf.indices[v, c]
            wv = inf.weights[v, c]
            for k in range(4):
                b = dq_blend_add(b, dqs[f, iv[k]], wv[k], b)
        return b
    pv = dqs[f, pivot_joint(inf, v, groups)]
    for c in range(groups):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            b = dq_blend_add(b, dqs[f, iv[k]], wv[k], pv)
    return b


@wp.func
def dqs_blend(inf: Influences, v: int, f: int, dqs: wp.array2d(dtype=vec8)):
    """Sign-aligned weighted sum of the vertex's dual quaternions (pivot: slot 0, or the running
    sum with ``inf.running_sum``; a zero sum flips nothing)."""
    return dqs_blend_groups(inf, v, f, dqs, inf.indices.shape[1])


@wp.func
def dqs_blend_derivative(inf: Influences, v: int, f: int, dqs: wp.array2d(dtype=vec8),
                         dq_derivatives: wp.array2d(dtype=vec8)):
    """``Σ sᵢ·wᵢ·η̇ᵢ``: the derivative of :func:`dqs_blend`, whose signs ``sᵢ`` (the same rule)
    are locally constant."""
    pv = dqs[f, pivot_joint(inf, v, inf.indices.shape[1])]
    b = vec8()
    acc = vec8()
    for c in range(inf.indices.shape[1]):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            if inf.running_sum != 0:
                pv = b
            j = iv[k]
            sw = wv[k] * dq_sign(dqs[f, j], pv)
            b += dqs[f, j] * sw
            acc += dq_derivatives[f, j] * sw
    return acc


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
def by_method(inf: Influences, v: int, method: int, lbs: wp.vec3, dqs: wp.vec3):
    """The result of ``method``: ``lbs``, ``dqs`` (also for COR, whose directions rotate as DQS's)
    or their per-vertex blend ``(1 − b)·lbs + b·dqs``, ``b = inf.blend[v]``."""
    if method == LBS:
        return lbs
    if method == DQS or method == COR:
        return dqs
    b = inf.blend[v]
    return lbs * (1.0 - b) + dqs * b


# ---------------------------------------------------------------------------------------------
# point kernels: flat 1-D arrays, one (frame block, vertex) per thread
#
# Warp specializes a CPU kernel whose launch is 1-D and whose array arguments are all 1-D and
# contiguous: their strides become compile-time constants and the task loop is inlined (1.19's
# ``wp_linear_contiguous``). Arrays inside structs or 2-D arrays keep runtime strides, and a frame
# loop costs even when it runs once; measured on one thread, 1M points, that was 25-30% of the
# time. So the point kernels take the (V, C) influences and (F, J) / (F, V) arrays as flat views
# and skin one frame straight, without the loop.


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
        acc += gather4(values, o, indices[v * groups + c], weights[v * groups + c])
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
    """The sign-aligned blend of :func:`dqs_blend` on the flat layout; ``pivot`` the vertex's
    largest-weight joint (:func:`flat_pivot`: slot 0 unless ``unsorted``). The first term is set,
    not added to zero; its sign is +1 against itself or against the running sum's zero."""
    d0 = dqs[o + iv[0]]
    b = d0 * wv[0]
    if running_sum != 0:
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
    """:func:`pivot_joint` on the flat layout (once per vertex, not per frame)."""
    j = iv[0]
    if unsorted == 0:
        return j
    j, wm = heavier(j, wv[0], iv, wv)
    for c in range(1, groups):
        j, wm = heavier(j, wm, indices[v * groups + c], weights[v * groups + c])
    return j


@wp.func(inline=True)
def skin_frame(p: wp.vec3, v: int, f: int, o: int, iv: wp.vec4i, wv: wp.vec4, pivot: int,
               indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4), groups: int,
               blend: wp.array(dtype=float), centers: wp.array(dtype=wp.vec4), unsorted: int,
               running_sum: int,
               affines: wp.array(dtype=mat34), dqs: wp.array(dtype=vec8),
               residuals: wp.array(dtype=wp.mat33), has_residual: wp.array(dtype=wp.int32),
               method: int, residual: bool):
    """Point ``p`` of vertex ``v`` skinned with ``method`` at frame ``f`` (its joints from ``o``);
    ``method``, ``residual`` (the frame may have scale/shear) and, in the ``K <= 4`` kernels,
    ``groups`` are compile-time constants, so only one method's code remains."""
    if method == LBS:
        return gather(affines, o, indices, weights, v, groups, iv, wv) * wp.vec4(
            p[0], p[1], p[2], 1.0)
    if method == COR:
        c4 = centers[v]
        if c4[3] != 0.0:
            c = wp.vec3(c4[0], c4[1], c4[2])
            y = p - c
            if residual:
                if has_residual[f] != 0:
                    y = gather(residuals, o, indices, weights, v, groups, iv, wv) * y
            lc = gather(affines, o, indices, weights, v, groups, iv, wv) * wp.vec4(
                c[0], c[1], c[2], 1.0)
            return dqs_apply(rotation_only(dq_gather(dqs, o, indices, weights, v, groups, iv, wv,
                                                     pivot, unsorted, running_sum)), y) + lc
    x = p
    if residual:
        if has_residual[f] != 0:
            x = gather(residuals, o, indices, weights, v, groups, iv, wv) * p
    d = dqs_apply(dq_gather(dqs, o, indices, weights, v, groups, iv, wv, pivot, unsorted,
                            running_sum), x)
    if method == BLEND:
        lbs = gather(affines, o, indices, weights, v, groups, iv, wv) * wp.vec4(p[0], p[1], p[2],
                                                                               1.0)
        b = blend[v]
        return lbs * (1.0 - b) + d * b
    return d


def _skin_points_kernel(method, residual, four):
    """The point kernel of one method, specialized at compile time: ``residual=False`` drops the
    scale/shear code (~18% faster on the CPU for rigid launches), ``four`` (``K <= 4``, one
    influence group) drops the loops over groups."""

    def kernel(
        points: wp.array(dtype=wp.vec3),
        point_stride: int,
        indices: wp.array(dtype=wp.vec4i),
        weights: wp.array(dtype=wp.vec4),
        groups: int,
        blend: wp.array(dtype=float),
        centers: wp.array(dtype=wp.vec4),
        running_sum: int,
        unsorted: int,
        affines: wp.array(dtype=mat34),
        dqs: wp.array(dtype=vec8),
        residuals: wp.array(dtype=wp.mat33),
        has_residual: wp.array(dtype=wp.int32),
        joint_count: int,
        frame_count: int,
        row_offset: int,
        # outputs
        out: wp.array(dtype=wp.vec3),
    ):
        t = wp.tid() + row_offset
        g = groups
        if wp.static(four):
            g = 1
        if frame_count == 1:  # one frame: vertex t, no frame loop
            iv = indices[t * g]
            wv = weights[t * g]
            pivot = flat_pivot(indices, weights, t, g, iv, wv, unsorted)
            out[t] = skin_frame(points[t], t, 0, 0, iv, wv, pivot, indices, weights, g, blend,
                                centers, unsorted, running_sum, affines, dqs, residuals,
                                has_residual, wp.static(method), wp.static(residual))
            return
        vertex_count = out.shape[0] // frame_count
        block = t // vertex_count
        v = t - block * vertex_count
        first = block * POINT_FRAME_BLOCK
        iv = indices[v * g]
        wv = weights[v * g]
        pivot = flat_pivot(indices, weights, v, g, iv, wv, unsorted)
        for f in range(first, wp.min(first + POINT_FRAME_BLOCK, frame_count)):
            out[wp.int64(f) * wp.int64(vertex_count) + wp.int64(v)] = skin_frame(
                points[wp.int64(f) * wp.int64(point_stride) + wp.int64(v)], v, f, f * joint_count,
                iv, wv, pivot, indices, weights, g, blend, centers, unsorted, running_sum, affines,
                dqs, residuals, has_residual, wp.static(method), wp.static(residual))

    rigid = "_rigid" if method in (DQS, COR) and not residual else ""
    name = f"skin_{['lbs', 'dqs', 'blend', 'cor'][method]}{rigid}_kernel{'_k4' if four else ''}"
    kernel.__doc__ = (f"Skin flat ``points`` (Fp·V) bind space, Fp 1 or F, into ``out`` (F·V) "
                      f"with method {method}; thread ``t``: vertex ``t`` of one frame, or vertex "
                      f"``t mod V`` of frame block ``t div V``.")
    return wp.kernel(kernel, name=name)


SKIN_POINTS_KERNELS = {(m, r, four): _skin_points_kernel(m, r, four)
                       for m, r in ((LBS, False), (DQS, True), (DQS, False), (BLEND, True),
                                    (COR, True), (COR, False))
                       for four in (False, True)}
"""The point-skinning kernels by ``(method, residual code, K <= 4)``: LBS needs no residual code,
BLEND always has it."""


@wp.func
def dqs_vector(x: wp.vec3, inf: Influences, v: int, f: int, rotations: wp.array2d(dtype=wp.quat),
               residuals: wp.array2d(dtype=wp.mat33), use_residual: bool):
    """Rotation-only DQS of a direction (sign-aligned quaternion blend, the sign rule of
    :func:`dqs_blend`), unit length."""
    pivot = rotations[f, pivot_joint(inf, v, inf.indices.shape[1])]
    r = wp.quat(0.0, 0.0, 0.0, 0.0)
    for c in range(inf.indices.shape[1]):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            if inf.running_sum != 0:
                pivot = r
            q = rotations[f, iv[k]]
            r += q * (wv[k] * wp.sign(wp.dot(q, pivot)))
    scaled = x
    if use_residual:
        scaled = blend_joints(inf, v, f, residuals) * x
    if wp.length(r) < 1.0e-10:
        return wp.normalize(scaled)
    return wp.normalize(wp.quat_rotate(wp.normalize(r), scaled))


@wp.kernel
def skin_vectors_kernel(
    vectors: wp.array2d(dtype=wp.vec3),
    vector_vertex: wp.array(dtype=wp.int32),
    inf: Influences,
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    method: int,
    blocks: FrameBlocks,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """Skin directions (normals or tangents), normalized, over a (frame block, vector) grid.

    ``vectors`` (Fp, N); ``vector_vertex`` (N,) maps each vector to the vertex whose influences it
    uses (identity for per-vertex data, the face-vertex map for faceVarying). For normals pass the
    inverse-transpose matrices and the rotations UsdSkel derives from them; for tangents the
    matrices themselves and their polar rotations.
    """
    blk, i = wp.tid()
    first, end, row = block_frames(blocks, blk, out.shape[0])
    n = i + row
    v = vector_vertex[n]
    last = vectors.shape[0] - 1
    for f in range(first, end):
        x = vectors[wp.min(f, last), n]
        lbs = wp.vec3()
        dqs = wp.vec3()
        if method == LBS or method == BLEND:
            lbs = wp.normalize(blend_joints(inf, v, f, linears) * x)
        if method != LBS:
            dqs = dqs_vector(x, inf, v, f, rotations, residuals, has_residual[f] != 0)
        out[f, n] = wp.normalize(by_method(inf, v, method, lbs, dqs))


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


def influences(*, indices, weights, blend, centers, running_sum=False, unsorted=False):
    """The :class:`Influences` struct of a mesh's device arrays."""
    s = Influences()
    s.indices, s.weights, s.blend, s.centers = indices, weights, blend, centers
    s.running_sum, s.unsorted = int(bool(running_sum)), int(bool(unsorted))
    return s


def joints(*, affines, dqs, residuals, has_residual):
    """The :class:`Joints` struct of (F, J) work arrays."""
    s = Joints()
    s.affines, s.dqs, s.residuals, s.has_residual = affines, dqs, residuals, has_residual
    return s


def prepare_points(*, xforms, joints, device):
    """Fill ``joints`` (a :class:`Joints` of (F, J) arrays) from ``xforms`` (F, J) ``wp.mat44``."""
    joints.has_residual.zero_()
    launch(prepare_points_kernel, xforms.shape, [xforms],
           [joints.affines, joints.dqs, joints.residuals, joints.has_residual], device)


def prepare_vectors(*, xforms, linears, rotations, normal_linears, normal_residuals,
                    normal_rotations, device):
    """Per (frame, joint) data of :func:`skin_vectors` (see :func:`prepare_vectors_kernel`)."""
    launch(prepare_vectors_kernel, xforms.shape, [xforms],
           [linears, rotations, normal_linears, normal_residuals, normal_rotations], device)


_flat_views = weakref.WeakKeyDictionary()


def _flat(a):
    """A 1-D view of contiguous array ``a`` (itself when 1-D), made once per array: a view costs
    ~5 µs, the point launch takes seven. The view does not own or reference ``a`` (a cached view
    holding ``a`` would keep it alive); it is only passed to launches together with ``a``'s
    struct, which does."""
    if a.ndim == 1:
        return a
    view = _flat_views.get(a)
    if view is None:
        if not a.is_contiguous:
            raise ValueError(f"skin_points: expected a contiguous array, got strides {a.strides}")
        if a.size == 0:
            view = wp.empty(0, dtype=a.dtype, device=a.device)
        else:
            view = wp.array(ptr=a.ptr, shape=(a.size,), dtype=a.dtype, device=a.device,
                            copy=False)
        _flat_views[a] = view
    return view


def skin_points(*, method, points, influences, joints, rigid, out, device):
    """Skin ``points`` (Fp, V) into ``out`` (F, V) with ``method`` (:data:`LBS`, :data:`DQS`,
    :data:`BLEND`, :data:`COR`). ``rigid`` (no frame has a residual) selects the DQS or COR
    kernel without the residual code. One thread per vertex of a single frame, else per (frame
    block, vertex); chunks of threads on the CPU cores."""
    residual = method == BLEND or (method != LBS and not rigid)
    groups = influences.indices.shape[1]
    kernel = SKIN_POINTS_KERNELS[(method, residual, groups == 1)]
    frames, verts = out.shape
    per_thread = min(frames, FRAME_BLOCK)
    inf, jn = influences, joints
    point_stride = verts if points.shape[0] > 1 else 0
    if point_stride and points.strides[0] == 0:  # one row broadcast to every frame
        points, point_stride = points[0], 0
    elif not points.is_contiguous:
        points = points.contiguous()
    launch_rows(kernel, verts * -(-frames // FRAME_BLOCK),
                [_flat(points), point_stride, _flat(inf.indices),
                 _flat(inf.weights), groups, inf.blend, inf.centers, inf.running_sum,
                 inf.unsorted, _flat(jn.affines), _flat(jn.dqs), _flat(jn.residuals),
                 jn.has_residual, jn.affines.shape[1], frames],
                [_flat(out)], device, min_chunk=-(-MIN_WORK // per_thread))


def skin_vectors(*, method, vectors, vector_vertex, influences, linears, rotations, residuals,
                 has_residual, out, device):
    """Skin directions ``vectors`` (Fp, N) into ``out`` (F, N), normalized (see
    :func:`skin_vectors_kernel` for which per-joint arrays normals and tangents take)."""
    launch_blocks(skin_vectors_kernel, out.shape[1], out.shape[0],
                  [vectors, vector_vertex, influences, linears, rotations, residuals,
                   has_residual, int(method)], [out], device)


def transform_frames(*, xforms, normalize, values, device):
    """In place ``values[f, i] = xforms[f]·[values[f, i], 1]`` (normalized with ``normalize``)."""
    launch(transform_frames_kernel, values.shape, [xforms, int(normalize)], [values], device)
