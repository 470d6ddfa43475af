"""Dual-quaternion algebra as ``@wp.func``, usable inside any Warp kernel.

A dual quaternion is stored as :data:`vec8` ``(rw, rx, ry, rz, dw, dx, dy, dz)`` -- the project's
public component order -- and represents the pose ``r + ε·½·t·r`` (rotate by ``r``, then translate
by ``t``). Warp's ``wp.quat`` is ``(x, y, z, w)``; the conversion happens only here, in
:func:`dq_real` / :func:`dq_dual` / :func:`dq_from_rt`.

Public ``@wp.func`` API (tested against :mod:`dqskin.dq` in ``tests/test_dqmath.py``): product
:func:`dq_mul`, :func:`dq_conjugate`, :func:`dq_transform_point`,
:func:`dq_transform_vector`, :func:`dq_from_rt` / :func:`dq_translation`,
:func:`dq_from_transform` / :func:`dq_to_transform`, :func:`dq_to_matrix`, and the antipodal
blend :func:`dq_blend_add`.

References: Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer Graphics and Beyond"
(product, transform, DLB); Montgomery-Smith & Shy, eq. 14 (normalization).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # forward-only kernels


vec8 = wp.types.vector(length=8, dtype=wp.float32)
"""A dual quaternion ``(rw, rx, ry, rz, dw, dx, dy, dz)``."""

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
"""The top three rows of a 4×4 affine transform."""

FACTOR_EPSILON = wp.constant(1.0e-10)
"""``|det A|`` below which ``GfMatrix4d::Factor`` fails: UsdSkel's DQS then gives the joint a zero
dual quaternion (it adds nothing to the blend) and no scale; so do the kernels."""

RESIDUAL_TOLERANCE = wp.constant(1.0e-6)
"""A scale/shear residual ``S`` within this of the identity (every entry) counts as rigid, as in
UsdSkel's DQS. The one definition for the kernels and the host."""

POLAR_NEAR = wp.constant(1.0e-3)
"""Largest ``|AᵀA − I|`` entry for which :func:`polar_rotation` iterates instead of taking the
SVD (:data:`dqskin.linalg.NEAR_ROTATION`)."""

POLAR_NEWTON_STEPS = 2
"""Polar iteration steps from within :data:`POLAR_NEAR`: float32-converged after two."""


@wp.func
def dq_real(a: vec8):
    """Rotation part as a Warp quaternion ``(x, y, z, w)``."""
    return wp.quat(a[1], a[2], a[3], a[0])


@wp.func
def dq_dual(a: vec8):
    """Dual part as a Warp quaternion ``(x, y, z, w)``."""
    return wp.quat(a[5], a[6], a[7], a[4])


@wp.func
def dq_from_rt(r: wp.quat, t: wp.vec3):
    """Pose that rotates by unit quaternion ``r`` then translates by ``t``: ``r + ε·½·t·r``."""
    x = r[0]
    y = r[1]
    z = r[2]
    w = r[3]
    return vec8(w, x, y, z,
                -0.5 * (t[0] * x + t[1] * y + t[2] * z),
                0.5 * (t[0] * w + t[1] * z - t[2] * y),
                0.5 * (t[1] * w + t[2] * x - t[0] * z),
                0.5 * (t[2] * w + t[0] * y - t[1] * x))


@wp.func
def dq_translation(a: vec8):
    """Translation of a unit dual quaternion: the vector part of ``t = 2·d·r*``."""
    w = a[0]
    x = a[1]
    y = a[2]
    z = a[3]
    dw = a[4]
    dx = a[5]
    dy = a[6]
    dz = a[7]
    return wp.vec3(2.0 * (dx * w - dw * x + dz * y - dy * z),
                   2.0 * (dy * w - dw * y + dx * z - dz * x),
                   2.0 * (dz * w - dw * z + dy * x - dx * y))


@wp.func
def dq_mul(a: vec8, b: vec8):
    """Concatenation ``a·b`` (apply ``b`` first, then ``a``), as the matrix product ``A @ B``.

    Written out per component: ``r = ra·rb``, ``d = ra·db + da·rb`` (Hamilton products).
    """
    aw = a[0]
    ax = a[1]
    ay = a[2]
    az = a[3]
    bw = b[0]
    bx = b[1]
    by = b[2]
    bz = b[3]
    cw = a[4]
    cx = a[5]
    cy = a[6]
    cz = a[7]
    dw = b[4]
    dx = b[5]
    dy = b[6]
    dz = b[7]
    return vec8(
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * dw - ax * dx - ay * dy - az * dz + cw * bw - cx * bx - cy * by - cz * bz,
        aw * dx + ax * dw + ay * dz - az * dy + cw * bx + cx * bw + cy * bz - cz * by,
        aw * dy - ax * dz + ay * dw + az * dx + cw * by - cx * bz + cy * bw + cz * bx,
        aw * dz + ax * dy - ay * dx + az * dw + cw * bz + cx * by - cy * bx + cz * bw)


@wp.func
def dq_conjugate(a: vec8):
    """Quaternion conjugate of both parts, ``r* + ε·d*``: the inverse of a unit dual quaternion."""
    return vec8(a[0], -a[1], -a[2], -a[3], a[4], -a[5], -a[6], -a[7])


@wp.func
def dq_transform_vector(a: vec8, v: wp.vec3):
    """Rotate direction ``v`` by unit dual quaternion ``a`` (no translation)."""
    return wp.quat_rotate(dq_real(a), v)


@wp.func
def dq_transform_point(a: vec8, p: wp.vec3):
    """Apply unit dual quaternion ``a`` to point ``p``: rotate, then translate."""
    return dq_transform_vector(a, p) + dq_translation(a)


@wp.func
def dq_real_dot(a: vec8, b: vec8):
    """Dot product of the real (rotation) parts of ``a`` and ``b``."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@wp.func
def dq_sign(a: vec8, pivot: vec8):
    """±1 putting ``a``'s real part on ``pivot``'s hemisphere (antipodality)."""
    return wp.sign(dq_real_dot(a, pivot))


@wp.func
def dq_blend_add(acc: vec8, a: vec8, w: float, pivot: vec8):
    """``acc + ±w·a``, the sign from :func:`dq_sign` -- one step of dual-quaternion linear
    blending (Kavan et al.); normalize the sum after."""
    return acc + a * (w * dq_sign(a, pivot))


@wp.func
def dq_from_transform(x: wp.transform):
    """Dual quaternion of a Warp ``wp.transform`` ``(p, q)``."""
    return dq_from_rt(wp.transform_get_rotation(x), wp.transform_get_translation(x))


@wp.func
def dq_to_transform(a: vec8):
    """Warp ``wp.transform`` ``(p, q)`` of unit dual quaternion ``a``."""
    return wp.transform(dq_translation(a), dq_real(a))


@wp.func
def quat_from_rotation(m: wp.mat33):
    """Unit Warp quaternion ``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    q = wp.quat()
    if tr > 0.0:
        s = wp.sqrt(tr + 1.0) * 2.0
        q = wp.quat((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s,
                    0.25 * s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = wp.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = wp.quat(0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s,
                    (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = wp.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = wp.quat((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s,
                    (m[0, 2] - m[2, 0]) / s)
    else:
        s = wp.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = wp.quat((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s,
                    (m[1, 0] - m[0, 1]) / s)
    return wp.normalize(q)


@wp.func
def dq_to_matrix(a: vec8):
    """4×4 rigid matrix (column-vector convention) of unit dual quaternion ``a``."""
    r = wp.quat_to_matrix(dq_real(a))
    t = dq_translation(a)
    return wp.mat44(r[0, 0], r[0, 1], r[0, 2], t[0],
                    r[1, 0], r[1, 1], r[1, 2], t[1],
                    r[2, 0], r[2, 1], r[2, 2], t[2],
                    0.0, 0.0, 0.0, 1.0)


@wp.func
def mat44_affine(m: wp.mat44):
    """The top three rows of ``m`` (a 3×4 affine)."""
    return mat34(m[0, 0], m[0, 1], m[0, 2], m[0, 3],
                 m[1, 0], m[1, 1], m[1, 2], m[1, 3],
                 m[2, 0], m[2, 1], m[2, 2], m[2, 3])


@wp.func
def mat44_linear(m: wp.mat44):
    """Upper-left 3×3 (linear part) of a 4×4 matrix."""
    return wp.mat33(m[0, 0], m[0, 1], m[0, 2],
                    m[1, 0], m[1, 1], m[1, 2],
                    m[2, 0], m[2, 1], m[2, 2])


@wp.func
def is_rotation(a: wp.mat33):
    """True when ``a`` is orthonormal with det +1 (to ~1e-6)."""
    e = wp.transpose(a) * a - wp.identity(n=3, dtype=float)
    err = (wp.abs(e[0, 0]) + wp.abs(e[1, 1]) + wp.abs(e[2, 2]) + wp.abs(e[0, 1]) + wp.abs(e[0, 2])
           + wp.abs(e[1, 2]))
    return err < 1.0e-6 and wp.determinant(a) > 0.0


@wp.func
def polar_rotation(a: wp.mat33):
    """Rotation factor ``R`` of the polar decomposition ``A = R·S``, det(R) = +1 (as
    ``GfMatrix4d::Factor``).

    Orthonormal input returns itself. A matrix with ``det A > 0`` within :data:`POLAR_NEAR` of a
    rotation (every ``|AᵀA − I|`` entry: a chain of float32 joint matrices, as skinning
    transforms are) takes :data:`POLAR_NEWTON_STEPS` steps of the polar iteration
    ``X ← (X + X⁻ᵀ)/2``, which squares the error each step (1e-3 → 5e-7 → float32 rounding), as
    :func:`dqskin.linalg.polar` does in float64. Otherwise ``R = U·Vᵀ`` from the SVD, negated when
    ``det A < 0`` (Gf negates all three scales of a reflection, leaving a proper rotation). ``A``
    is divided by its largest entry first (``R`` does not change), so scales near the float32
    limits neither overflow nor underflow in the SVD.
    """
    if is_rotation(a):
        return a
    e = wp.transpose(a) * a - wp.identity(n=3, dtype=float)
    off = wp.max(wp.max(wp.abs(e[0, 0]), wp.abs(e[1, 1])),
                 wp.max(wp.abs(e[2, 2]), wp.abs(e[0, 1])))
    off = wp.max(off, wp.max(wp.abs(e[0, 2]), wp.abs(e[1, 2])))
    if off < POLAR_NEAR and wp.determinant(a) > 0.0:
        x = a
        for _k in range(POLAR_NEWTON_STEPS):
            x = (x + wp.transpose(wp.inverse(x))) * 0.5
        return x
    big = float(0.0)
    for i in range(3):
        for k in range(3):
            big = wp.max(big, wp.abs(a[i, k]))
    u = wp.mat33()
    sigma = wp.vec3()
    v = wp.mat33()
    wp.svd3(a * (1.0 / wp.max(big, 1.0e-30)), u, sigma, v)
    # svd3 keeps U, V proper rotations and may return a negative singular value: restore the sign
    sgn = wp.vec3(wp.sign(sigma[0]), wp.sign(sigma[1]), wp.sign(sigma[2]))
    r = u * wp.diag(sgn) * wp.transpose(v)
    if wp.determinant(r) < 0.0:
        r = -r
    return r


@wp.func
def orthonormalize_step(tx: wp.vec3, ty: wp.vec3, tz: wp.vec3):
    """One iteration of ``GfVec3d::OrthogonalizeBasis`` (see :func:`orthonormalize_columns`):
    each unit column less its projections on the other two, averaged with itself, normalized."""
    bx = tx - ty * wp.dot(ty, tx)
    bx = bx - tz * wp.dot(tz, bx)
    by = ty - tx * wp.dot(tx, ty)
    by = by - tz * wp.dot(tz, by)
    bz = tz - tx * wp.dot(tx, tz)
    bz = bz - ty * wp.dot(ty, bz)
    return (wp.normalize((tx + bx) * 0.5), wp.normalize((ty + by) * 0.5),
            wp.normalize((tz + bz) * 0.5))


@wp.func
def orthonormalize_columns(m: wp.mat33):
    """Orthonormalize the columns of ``m`` exactly as ``GfMatrix3d::Orthonormalize`` does its rows.

    Gf's iterative symmetric scheme (``GfVec3d::OrthogonalizeBasis``, eps 1e-6, ≤ 20 iterations) is
    not the polar rotation; UsdSkel uses it to split normal matrices for DQS, so we match it.
    """
    tx = wp.normalize(wp.vec3(m[0, 0], m[1, 0], m[2, 0]))
    ty = wp.normalize(wp.vec3(m[0, 1], m[1, 1], m[2, 1]))
    tz = wp.normalize(wp.vec3(m[0, 2], m[1, 2], m[2, 2]))
    for _it in range(20):
        cx, cy, cz = orthonormalize_step(tx, ty, tz)
        err = wp.length_sq(tx - cx) + wp.length_sq(ty - cy) + wp.length_sq(tz - cz)
        if err < 1.0e-12:
            break
        tx = cx
        ty = cy
        tz = cz
    return wp.matrix_from_cols(tx, ty, tz)


@wp.func
def is_identity33(s: wp.mat33, tol: float):
    """True when every entry of ``s`` is within ``tol`` of the identity."""
    e = s - wp.identity(n=3, dtype=float)
    m = float(0.0)
    for i in range(3):
        for j in range(3):
            m = wp.max(m, wp.abs(e[i, j]))
    return m <= tol
