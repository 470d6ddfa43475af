"""Per-vertex velocity kernels: time derivatives of LBS, DQS and blended skinned points.

Same semantics, influence layout and grid as :mod:`dqskin.kernels.skin`, whose ``@wp.func``
blends they call. Each kernel differentiates the skinning formula by the chain rule, given the time
derivatives of the skinning transforms ``Ȧ`` and of the rest points ``ṗ``:

* LBS: ``p' = Σ wᵢ·Aᵢ·[p, 1]`` → ``ṗ' = Σ wᵢ·(Ȧᵢ·[p, 1] + Aᵢ·[ṗ, 0])``.
* DQS: ``b = r + ε·d = Σ sᵢ·wᵢ·ηᵢ`` (``sᵢ = ±1``, locally constant) and, with ``x`` the point (or
  ``Σ wᵢ·Sᵢ·p`` on frames with a residual), ``p' = x + 2·g(r, d, x)/|r|²`` where
  ``g = r⃗×(r⃗×x) + r_w·(r⃗×x) + r_w·d⃗ − d_w·r⃗ + r⃗×d⃗`` (the normalization of Montgomery-Smith
  eq. 14 folded into the transform, as in the skinning kernel). Then
  ``ṗ' = ẋ + 2·ġ/|r|² − 2·g·(2·r·ṙ)/|r|⁴`` with ``ḃ = Σ sᵢ·wᵢ·η̇ᵢ`` and
  ``ẋ = Σ wᵢ·(Ṡᵢ·p + Sᵢ·ṗ)`` (``ẋ = ṗ`` without a residual).
* blend: ``(1 − b)·LBS' + b·DQS'``.
* COR (center ``c``): ``p' = R(r)·y + Σ wᵢ·Aᵢ·[c, 1]``, ``y = p − c`` (through the residuals on
  frames with one), ``R(r)`` the rotation of the blend's real part: ``ṗ' = Ṙ·y + R·ẏ +
  Σ wᵢ·Ȧᵢ·[c, 1]``; vertices without a center as DQS.

The joints' ``η̇`` and ``Ṡ`` come from the polar split ``A = R·S`` (:func:`polar_rotation`, as
skinning) and its derivative ``Rᵀ·Ȧ = [ω]×·S + Ṡ``: the skew part gives
``((tr S)·I − S)·ω = 2·vee(Rᵀ·Ȧ)``, then ``q̇ = ½·q·ω`` and ``Ṡ = Rᵀ·Ȧ − [ω]×·S``.
"""

import warp as wp

from .._warp import Device
from .blend import affine_gather
from .dqmath import (
    FACTOR_EPSILON,
    RESIDUAL_TOLERANCE,
    dq_from_rt,
    dq_sign,
    is_identity33,
    mat34,
    mat44_affine,
    mat44_linear,
    polar_rotation,
    quat_from_rotation,
    vec8,
)
from .grid import launch
from .layout import InfluenceLayout, contiguous_float, contiguous_vec4, contiguous_vec4i
from .skin import (
    BLEND,
    COR,
    LBS,
    Joints,
    by_method,
    dq_gather,
    flat_pivot,
    frame_rows,
    frame_rows_array,
    gather,
    group,
    launch_frames,
    prepare_points,
    rotation_only,
    skin_points,
)
from .skin import _flat as flat
from .skin import joints as skin_joints

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.func
def skew(w: wp.vec3):
    """Cross-product matrix ``[w]×``."""
    return wp.mat33(0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0)


@wp.kernel
def prepare_derivatives_kernel(
    xforms: wp.array2d(dtype=wp.mat44),
    xform_derivatives: wp.array2d(dtype=wp.mat44),
    # outputs
    affine_derivatives: wp.array2d(dtype=mat34),
    dq_derivatives: wp.array2d(dtype=vec8),
    residual_derivatives: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
):
    """Per (frame, joint): ``Ȧ`` as 3×4, ``η̇`` and ``Ṡ`` from the polar split's derivative.
    Raises ``has_residual`` (set by :func:`~dqskin.kernels.skin.prepare_points_kernel`) on
    frames where some ``Ṡ ≠ 0``."""
    f, j = wp.tid()
    m = xforms[f, j]
    md = xform_derivatives[f, j]
    affine_derivatives[f, j] = mat44_affine(md)
    a = mat44_linear(m)
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:  # a zero DQ in the blend, as skinning
        dq_derivatives[f, j] = vec8()
        residual_derivatives[f, j] = wp.mat33()
        return
    r = polar_rotation(a)
    s = wp.transpose(r) * a
    x = wp.transpose(r) * mat44_linear(md)
    axial = wp.vec3(x[2, 1] - x[1, 2], x[0, 2] - x[2, 0], x[1, 0] - x[0, 1])
    trace = s[0, 0] + s[1, 1] + s[2, 2]
    omega = wp.inverse(wp.identity(n=3, dtype=float) * trace - s) * axial
    s_dot = x - skew(omega) * s
    q = quat_from_rotation(r)
    q_dot = q * wp.quat(omega[0], omega[1], omega[2], 0.0) * 0.5
    t = wp.vec3(m[0, 3], m[1, 3], m[2, 3])
    t_dot = wp.vec3(md[0, 3], md[1, 3], md[2, 3])
    # η = q + ε·½·t·q (dq_from_rt is linear in q)  →  η̇ = q̇ + ε·½·(t·q̇ + ṫ·q)
    e = dq_from_rt(q_dot, t)
    e_t = dq_from_rt(q, t_dot)
    dq_derivatives[f, j] = vec8(e[0], e[1], e[2], e[3], e[4] + e_t[4], e[5] + e_t[5],
                                e[6] + e_t[6], e[7] + e_t[7])
    residual_derivatives[f, j] = s_dot
    if not is_identity33(s_dot + wp.identity(n=3, dtype=float), RESIDUAL_TOLERANCE):
        wp.atomic_max(has_residual, f, 1)


@wp.kernel
def prepare_affine_rates_kernel(
    xform_derivatives: wp.array2d(dtype=wp.mat44),
    # outputs
    affine_derivatives: wp.array2d(dtype=mat34),
):
    """Per (frame, joint): ``Ȧ`` as 3×4 only, all LBS reads (the DQS rates are left as they
    were)."""
    f, j = wp.tid()
    affine_derivatives[f, j] = mat44_affine(xform_derivatives[f, j])


@wp.func
def dqs_apply_derivative(b: vec8, b_dot: vec8, x: wp.vec3, x_dot: wp.vec3):
    """``d/dt`` of :func:`~dqskin.kernels.skin.dqs_apply` ``(b, x)`` along ``(ḃ, ẋ)``; a zero blend
    (all weights zero) leaves the point as it is, so its velocity is ``ẋ``."""
    rv = wp.vec3(b[1], b[2], b[3])
    rw = b[0]
    n2 = rw * rw + wp.dot(rv, rv)
    if n2 < 1.0e-20:
        return x_dot
    dv = wp.vec3(b[5], b[6], b[7])
    dw = b[4]
    rdv = wp.vec3(b_dot[1], b_dot[2], b_dot[3])
    rdw = b_dot[0]
    ddv = wp.vec3(b_dot[5], b_dot[6], b_dot[7])
    ddw = b_dot[4]
    rx = wp.cross(rv, x)
    g = wp.cross(rv, rx) + rw * rx + rw * dv - dw * rv + wp.cross(rv, dv)
    rx_dot = wp.cross(rdv, x) + wp.cross(rv, x_dot)
    g_dot = (wp.cross(rdv, rx) + wp.cross(rv, rx_dot) + rdw * rx + rw * rx_dot
             + rdw * dv + rw * ddv - ddw * rv - dw * rdv + wp.cross(rdv, dv) + wp.cross(rv, ddv))
    n2_dot = 2.0 * (rw * rdw + wp.dot(rv, rdv))
    return x_dot + (2.0 / n2) * g_dot - (2.0 * n2_dot / (n2 * n2)) * g


class JointRates:
    """Time derivatives of a :class:`~dqskin.kernels.skin.Joints`, from
    :func:`prepare_derivatives_kernel`."""

    __slots__ = ("affines", "dqs", "residuals")

    affines: wp.array2d(dtype=mat34)
    """(F, J) ``Ȧ`` (top rows)."""
    dqs: wp.array2d(dtype=vec8)
    """(F, J) ``η̇``."""
    residuals: wp.array2d(dtype=wp.mat33)
    """(F, J) ``Ṡ``."""


@wp.func
def dq_gather_derivative(dqs: wp.array(dtype=vec8), dq_rates: wp.array(dtype=vec8), o: int,
                         indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                         v: int, groups: int, iv: wp.vec4i, wv: wp.vec4, pivot: int,
                         running_sum: int):
    """``Σ sᵢ·wᵢ·η̇ᵢ``: the derivative of :func:`~dqskin.kernels.skin.dq_gather`, whose signs
    ``sᵢ`` (the same rule) are locally constant."""
    ref = dqs[o + pivot]
    b = vec8()
    acc = vec8()
    for c in range(groups):
        ic, wc = group(indices, weights, v, groups, c, iv, wv)
        for k in range(4):
            if running_sum != 0:
                ref = b
            j = o + ic[k]
            sw = wc[k] * dq_sign(dqs[j], ref)
            b += dqs[j] * sw
            acc += dq_rates[j] * sw
    return acc


@wp.kernel
def velocity_kernel(
    points: wp.array(dtype=wp.vec3),
    point_stride: int,
    point_velocities: wp.array(dtype=wp.vec3),
    velocity_stride: int,
    inf: InfluenceLayout,
    affines: wp.array(dtype=mat34),
    dqs: wp.array(dtype=vec8),
    residuals: wp.array(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    affine_rates: wp.array(dtype=mat34),
    dq_rates: wp.array(dtype=vec8),
    residual_rates: wp.array(dtype=wp.mat33),
    joint_count: int,
    frame_count: int,
    method: int,
    row_offset: int,
    # outputs
    out: wp.array(dtype=wp.vec3),
):
    """Velocities of skinned points, flat as the point kernels. ``points``, ``point_velocities``
    (Fp·V) bind space, Fp 1 or F; ``out`` (F·V) skeleton space per unit time."""
    indices = contiguous_vec4i(inf.indices)
    weights = contiguous_vec4(inf.weights)
    g = inf.groups
    running_sum = inf.running_sum
    unsorted = inf.unsorted
    rows = out.shape[0] // frame_count
    v, first, end = frame_rows(wp.tid() + row_offset, rows, frame_count)
    iv = indices[v * g]
    wv = weights[v * g]
    pivot = flat_pivot(indices, weights, v, g, iv, wv, unsorted)
    c4 = wp.vec4()
    if method == COR:
        c4 = contiguous_vec4(inf.centers)[v]
    for f in range(first, end):
        o = f * joint_count
        p = points[wp.int64(f) * wp.int64(point_stride) + wp.int64(v)]
        pd = point_velocities[wp.int64(f) * wp.int64(velocity_stride) + wp.int64(v)]
        lbs = wp.vec3()
        dqs_v = wp.vec3()
        if method == LBS or method == BLEND:
            lbs = (affine_gather(affine_rates, o, indices, weights, v, g, iv, wv)
                   * wp.vec4(p[0], p[1], p[2], 1.0)
                   + affine_gather(affines, o, indices, weights, v, g, iv, wv)
                   * wp.vec4(pd[0], pd[1], pd[2], 0.0))
        if method != LBS:
            x = p
            xd = pd
            cor = c4[3] != 0.0  # COR with a center: the rotation acts on y = p − c
            if cor:
                x = p - wp.vec3(c4[0], c4[1], c4[2])
            if has_residual[f] != 0:
                s = gather(residuals, o, indices, weights, v, g, iv, wv)
                xd = gather(residual_rates, o, indices, weights, v, g, iv, wv) * x + s * pd
                x = s * x
            b = dq_gather(dqs, o, indices, weights, v, g, iv, wv, pivot, unsorted, running_sum)
            bd = dq_gather_derivative(dqs, dq_rates, o, indices, weights, v, g, iv, wv, pivot,
                                      running_sum)
            if cor:
                dqs_v = dqs_apply_derivative(rotation_only(b), rotation_only(bd), x, xd) + (
                    affine_gather(affine_rates, o, indices, weights, v, g, iv, wv)
                    * wp.vec4(c4[0], c4[1], c4[2], 1.0))
            else:
                dqs_v = dqs_apply_derivative(b, bd, x, xd)
        out[wp.int64(f) * wp.int64(rows) + wp.int64(v)] = by_method(
            method, lbs, dqs_v, contiguous_float(inf.blend), v)


# ---------------------------------------------------------------------------------------------
# launchers


def joint_rates(*, affines: wp.array, dqs: wp.array, residuals: wp.array) -> JointRates:
    """The :class:`JointRates` of (F, J) work arrays."""
    r = JointRates()
    r.affines, r.dqs, r.residuals = affines, dqs, residuals
    return r


def prepare(*, xforms: wp.array, xform_derivatives: wp.array, joints: Joints,
            rates: JointRates, device: Device, affines_only: bool = False) -> None:
    """Fill ``joints`` and ``rates`` from the (F, J) ``wp.mat44`` transforms and derivatives;
    ``affines_only``: their 3×4 affines only (all LBS reads)."""
    prepare_points(xforms=xforms, joints=joints, device=device, affines_only=affines_only)
    if affines_only:
        launch(prepare_affine_rates_kernel, xforms.shape, [xform_derivatives], [rates.affines],
               device)
        return
    launch(prepare_derivatives_kernel, xforms.shape, [xforms, xform_derivatives],
           [rates.affines, rates.dqs, rates.residuals, joints.has_residual], device)


def velocities(*, method: int, points: wp.array, point_velocities: wp.array | None,
               influences: InfluenceLayout, joints: Joints, rates: JointRates, out: wp.array,
               device: Device) -> None:
    """Velocities of ``points`` skinned with ``method`` into ``out`` (F, V); ``point_velocities``
    None: the rest points do not move. LBS then has ``ṗ' = Σ wᵢ·Ȧᵢ·[p, 1]``, the LBS of the
    points with the rates ``Ȧ`` as affines: :func:`~.skin.skin_points`' kernel (the packet kernel
    on the CPU: faster than the velocity kernel there)."""
    frames, verts = out.shape
    jn = joints
    if point_velocities is None:
        if method == LBS:
            skin_points(method=LBS, points=points, influences=influences, out=out, rigid=True,
                        joints=skin_joints(affines=rates.affines, dqs=jn.dqs,
                                           residuals=jn.residuals, has_residual=jn.has_residual),
                        device=device)
            return
        point_velocities = wp.zeros((1, verts), dtype=wp.vec3, device=device)
    launch_frames(velocity_kernel, verts, frames,
                  [*frame_rows_array(points, verts), *frame_rows_array(point_velocities, verts),
                   influences, flat(jn.affines), flat(jn.dqs),
                   flat(jn.residuals), jn.has_residual, flat(rates.affines), flat(rates.dqs),
                   flat(rates.residuals), jn.affines.shape[1], frames, int(method)], [out],
                  device)
