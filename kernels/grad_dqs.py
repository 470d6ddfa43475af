"""The DQS point kernel's adjoint, written out: one pass over the vertices that recomputes the
blend and applies the closed-form derivative of the normalized blended dual quaternion, for
:mod:`dqskin.autograd` (the other methods use the adjoints Warp generates, :mod:`.grad`).

Forward (:func:`.grad.points_kernel` with ``DQS``): per vertex and frame, the sign-aligned blend
``b = Σ σᵢ·wᵢ·qᵢ`` of the joints' unit dual quaternions ``qᵢ = rᵢ + ε·dᵢ`` (``σᵢ = ±1``, a
step function of the joints' real parts, whose derivative is zero), the blended residuals
``x = Σ wᵢ·Sᵢ·p``, and ``y = x + s·A`` with ``b = (r_w, r⃗, d_w, d⃗)``,
``s = 2 / max(|r|², 10⁻³⁰)`` and ``A = r⃗×(r⃗×x + r_w·x) + r_w·d⃗ − d_w·r⃗ + r⃗×d⃗``
(:func:`~.skin.dqs_apply`). With ``g = ∂L/∂y`` and ``c = s²`` where ``|r|² > 10⁻³⁰`` (else 0, the
guard's derivative):

* ``∂L/∂x = g + s·(r⃗×(r⃗×g) − r_w·r⃗×g)`` (the rotation's transpose applied to ``g``)
* ``∂L/∂r_w = s·g·(r⃗×x + d⃗) − c·r_w·(g·A)``
* ``∂L/∂r⃗ = s·((g·r⃗)·x + (r⃗·x)·g − 2(g·x)·r⃗ + r_w·x×g − d_w·g + d⃗×g) − c·(g·A)·r⃗``
* ``∂L/∂d_w = −s·g·r⃗``, ``∂L/∂d⃗ = s·(r_w·g + g×r⃗)``

and through the sums: ``∂L/∂qᵢ += σᵢ·wᵢ·∂L/∂b``, ``∂L/∂Sᵢ += wᵢ·(∂L/∂x)·pᵀ``,
``∂L/∂wᵢ = σᵢ·(∂L/∂b)·qᵢ + (∂L/∂x)·Sᵢ·p``, ``∂L/∂p = Σ wᵢ·Sᵢᵀ·∂L/∂x``.

A thread handles one vertex and loops over the frames, so the per-vertex adjoints (points,
weights) are written, not accumulated, and need no zeroed buffer; the per-joint adjoints are
added to the buffers of the launch (one per CPU worker, :func:`.grad.launch_vertices`; atomic on
CUDA).
"""

import functools

import warp as wp

from .dqmath import dq_sign, vec8
from .grad import _pivot_slot, fused_cpu_flags

__all__ = ["dqs_apply_adjoint", "dqs_points_adjoint_kernel"]


@wp.func
def dqs_apply_adjoint(b: vec8, x: wp.vec3, g: wp.vec3):
    """``(∂L/∂b, ∂L/∂x)`` of ``y = dqs_apply(b, x)`` for ``g = ∂L/∂y`` (module docstring)."""
    rw = b[0]
    rv = wp.vec3(b[1], b[2], b[3])
    dw = b[4]
    dv = wp.vec3(b[5], b[6], b[7])
    n2 = rw * rw + wp.dot(rv, rv)
    s = 2.0 / wp.max(n2, 1.0e-30)
    c = float(0.0)
    if n2 > 1.0e-30:
        c = s * s
    e = wp.cross(rv, x) + dv
    ga = wp.dot(g, wp.cross(rv, e) + rw * e - dw * rv)  # g·A
    h = wp.cross(rv, g)
    k = h - rw * g
    g_rw = s * wp.dot(g, e) - c * rw * ga
    g_rv = s * (wp.cross(e, g) + wp.cross(k, x) - dw * g) - (c * ga) * rv
    g_dv = -s * k
    gx = g + s * (wp.cross(rv, h) - rw * h)
    grv = wp.dot(g, rv)
    return vec8(g_rw, g_rv[0], g_rv[1], g_rv[2], -s * grv, g_dv[0], g_dv[1], g_dv[2]), gx


@functools.cache
def dqs_points_adjoint_kernel(influences: int, running_sum: bool) -> wp.Kernel:
    """The adjoint of the DQS point kernel for ``influences`` (K) per vertex and a sign rule
    (``running_sum``: Blender's; else the largest weight's joint), compiled on first use in a
    Warp module of its own; a thread per vertex ``first + tid``, all frames."""
    pivot_slot = _pivot_slot(influences)
    wvec = wp.types.vector(length=influences, dtype=float)
    ivec = wp.types.vector(length=influences, dtype=wp.int32)

    def kernel(
        points: wp.array(dtype=wp.vec3),
        point_stride: int,
        indices: wp.array2d(dtype=wp.int32),
        weights: wp.array2d(dtype=float),
        dqs: wp.array(dtype=vec8),
        residuals: wp.array(dtype=wp.mat33),
        grad: wp.array(dtype=wp.vec3),
        joint_count: int,
        frames: int,
        first: int,
        # outputs
        adj_points: wp.array(dtype=wp.vec3),
        adj_weights: wp.array2d(dtype=float),
        adj_dqs: wp.array(dtype=vec8),
        adj_residuals: wp.array(dtype=wp.mat33),
    ):
        v = first + wp.tid()
        vertex_count = weights.shape[0]
        pivot = pivot_slot(weights, v)
        gw = wvec()
        wv = wvec()
        iv = ivec()
        for k in range(wp.static(influences)):
            wv[k] = weights[v, k]
            iv[k] = indices[v, k]
        gp_shared = wp.vec3()
        for f in range(frames):
            o = f * joint_count
            p = points[f * point_stride + v]
            pv = dqs[o + iv[pivot]]
            b = vec8()
            m = wp.mat33()  # Σ wᵢ·Sᵢ
            sign = wvec()  # σᵢ
            for k in range(wp.static(influences)):
                j = o + iv[k]
                q = dqs[j]
                if wp.static(running_sum):
                    sign[k] = dq_sign(q, b)
                else:
                    sign[k] = dq_sign(q, pv)
                w = wv[k]
                b = b + q * (w * sign[k])  # dq_blend_add
                m = m + residuals[j] * w
            gb, gx = dqs_apply_adjoint(b, m * p, grad[f * vertex_count + v])
            gs = wp.outer(gx, p)  # ∂L/∂(Σ wᵢ·Sᵢ)
            for k in range(wp.static(influences)):
                j = o + iv[k]
                w = wv[k]
                gw[k] = gw[k] + sign[k] * wp.dot(gb, dqs[j]) + wp.ddot(gs, residuals[j])
                wp.atomic_add(adj_dqs, j, gb * (w * sign[k]))
                wp.atomic_add(adj_residuals, j, gs * w)
            gp = gx * m  # (Σ wᵢ·Sᵢ)ᵀ·∂L/∂x
            if point_stride == 0:
                gp_shared = gp_shared + gp
            else:
                adj_points[f * point_stride + v] = gp
        if point_stride == 0:
            adj_points[v] = gp_shared
        for k in range(wp.static(influences)):
            adj_weights[v, k] = gw[k]

    label = "running_sum" if running_sum else "largest_weight"
    name = f"grad_points_dqs_adjoint_k{influences}_{label}"
    kernel.__doc__ = (f"Adjoint of the DQS point kernel, {influences} influences, "
                      f"{label.replace('_', ' ')} sign rule, per vertex ``first + tid``.")
    module = f"{__name__}.{name}"
    wp.set_module_options({"enable_backward": False, "max_unroll": max(32, influences),
                           "cpu_compiler_flags": fused_cpu_flags()}, module=module)
    return wp.kernel(kernel, name=name, module=module)
