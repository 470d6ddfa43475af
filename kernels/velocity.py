"""Per-vertex velocity kernels: time derivatives of LBS and DQS skinned points, batched over frames.

Same semantics and grid as :mod:`dqskin.kernels.skin` (influences sorted by descending weight so
slot 0 is the antipodality pivot; a thread per vertex and block of frames); influences as plain
(V, K) arrays. Each kernel
differentiates the skinning formula by the chain rule, given the time derivatives of the joint data
and of the rest points:

* LBS: ``p' = Σ wᵢ·Aᵢ·[p, 1]`` → ``ṗ' = Σ wᵢ·(Ȧᵢ·[p, 1] + Aᵢ·[ṗ, 0])``.
* DQS: ``b = r + ε·d = Σ sᵢ·wᵢ·ηᵢ`` (``sᵢ = ±1``, locally constant) and, with ``x`` the point (or
  ``Σ wᵢ·Sᵢ·p`` on frames with a residual), ``p' = x + 2·g(r, d, x)/|r|²`` where
  ``g = r⃗×(r⃗×x) + r_w·(r⃗×x) + r_w·d⃗ − d_w·r⃗ + r⃗×d⃗`` (the normalization of Montgomery-Smith
  eq. 14 folded into the transform, as in the skinning kernel). Then
  ``ṗ' = ẋ + 2·ġ/|r|² − 2·g·(2·r·ṙ)/|r|⁴`` with ``ḃ = Σ sᵢ·wᵢ·η̇ᵢ`` and
  ``ẋ = Σ wᵢ·(Ṡᵢ·p + Sᵢ·ṗ)`` (``ẋ = ṗ`` without a residual).

Dual quaternions arrive as :data:`~dqskin.kernels.dqmath.vec8` in the project's ``(w, x, y, z)``
order and are converted to Warp quaternions with :func:`~dqskin.kernels.dqmath.dq_real` /
:func:`~dqskin.kernels.dqmath.dq_dual`.
"""

import warp as wp


from .dqmath import dq_dual, dq_real, vec8
from .skin import mat34

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.kernel
def lbs_velocity_kernel(
    points: wp.array2d(dtype=wp.vec3),
    point_velocities: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=float),
    affines: wp.array2d(dtype=mat34),
    affine_derivatives: wp.array2d(dtype=mat34),
    frame_block: int,
    block_offset: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """LBS velocity. ``points``, ``point_velocities`` (Fp, V) bind space, Fp 1 or F;
    ``affines``, ``affine_derivatives`` (F, J) 3×4; ``out`` (F, V) skeleton space per unit time."""
    b, i = wp.tid()
    v = i + vertex_offset
    f0 = (b + block_offset) * frame_block
    last_p = points.shape[0] - 1
    last_v = point_velocities.shape[0] - 1
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        p = points[wp.min(f, last_p), v]
        pd = point_velocities[wp.min(f, last_v), v]
        acc = mat34()
        acc_dot = mat34()
        for k in range(indices.shape[1]):
            j = indices[v, k]
            w = weights[v, k]
            acc += affines[f, j] * w
            acc_dot += affine_derivatives[f, j] * w
        out[f, v] = (acc_dot * wp.vec4(p[0], p[1], p[2], 1.0)
                     + acc * wp.vec4(pd[0], pd[1], pd[2], 0.0))


@wp.kernel
def dqs_velocity_kernel(
    points: wp.array2d(dtype=wp.vec3),
    point_velocities: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=float),
    dqs: wp.array2d(dtype=vec8),
    dq_derivatives: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    residual_derivatives: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    frame_block: int,
    block_offset: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """DQS velocity. ``dqs``, ``dq_derivatives`` (F, J) unit joint DQs and their time derivatives;
    ``residuals`` and their derivatives (F, J); other arrays as :func:`lbs_velocity_kernel`."""
    b, i = wp.tid()
    v = i + vertex_offset
    f0 = (b + block_offset) * frame_block
    last_p = points.shape[0] - 1
    last_v = point_velocities.shape[0] - 1
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        p = points[wp.min(f, last_p), v]
        pd = point_velocities[wp.min(f, last_v), v]
        use_residual = has_residual[f] != 0
        pivot = dq_real(dqs[f, indices[v, 0]])
        r = wp.quat(0.0, 0.0, 0.0, 0.0)
        d = wp.quat(0.0, 0.0, 0.0, 0.0)
        rd = wp.quat(0.0, 0.0, 0.0, 0.0)
        dd = wp.quat(0.0, 0.0, 0.0, 0.0)
        x = p
        xd = pd
        if use_residual:
            x = wp.vec3()
            xd = wp.vec3()
        for k in range(indices.shape[1]):
            j = indices[v, k]
            eta = dqs[f, j]
            eta_dot = dq_derivatives[f, j]
            q = dq_real(eta)
            w = weights[v, k]
            s = w * wp.sign(wp.dot(q, pivot))
            r += q * s
            d += dq_dual(eta) * s
            rd += dq_real(eta_dot) * s
            dd += dq_dual(eta_dot) * s
            if use_residual:
                x += (residuals[f, j] * p) * w
                xd += (residual_derivatives[f, j] * p + residuals[f, j] * pd) * w
        rv = wp.vec3(r[0], r[1], r[2])
        rw = r[3]
        n2 = rw * rw + wp.dot(rv, rv)
        if n2 < 1.0e-20:
            out[f, v] = xd  # all weights zero: the skinned point is x itself
        else:
            dv = wp.vec3(d[0], d[1], d[2])
            dw = d[3]
            rdv = wp.vec3(rd[0], rd[1], rd[2])
            rdw = rd[3]
            ddv = wp.vec3(dd[0], dd[1], dd[2])
            ddw = dd[3]
            rx = wp.cross(rv, x)
            g = wp.cross(rv, rx) + rw * rx + rw * dv - dw * rv + wp.cross(rv, dv)
            rx_dot = wp.cross(rdv, x) + wp.cross(rv, xd)
            g_dot = (wp.cross(rdv, rx) + wp.cross(rv, rx_dot) + rdw * rx + rw * rx_dot
                     + rdw * dv + rw * ddv - ddw * rv - dw * rdv
                     + wp.cross(rdv, dv) + wp.cross(rv, ddv))
            n2_dot = 2.0 * (rw * rdw + wp.dot(rv, rdv))
            out[f, v] = xd + (2.0 / n2) * g_dot - (2.0 * n2_dot / (n2 * n2)) * g
