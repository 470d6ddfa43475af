"""Dual-quaternion algebra as ``@wp.func``, usable inside any Warp kernel.

A dual quaternion is stored as :data:`vec8` ``(rw, rx, ry, rz, dw, dx, dy, dz)`` -- the project's
public component order -- and represents the pose ``r + ε·½·t·r`` (rotate by ``r``, then translate
by ``t``). Warp's ``wp.quat`` is ``(x, y, z, w)``; the conversion happens only here, in
:func:`dq_real` / :func:`dq_dual` / :func:`dq_pack`.

References: Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer Graphics and Beyond"
(product, transform, DLB); Montgomery-Smith & Shy, eq. 14 (normalization).
"""

import warp as wp

vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.func
def dq_real(a: vec8):
    """Rotation part as a Warp quaternion ``(x, y, z, w)``."""
    return wp.quat(a[1], a[2], a[3], a[0])


@wp.func
def dq_dual(a: vec8):
    """Dual part as a Warp quaternion ``(x, y, z, w)``."""
    return wp.quat(a[5], a[6], a[7], a[4])


@wp.func
def dq_pack(r: wp.quat, d: wp.quat):
    """Pack real and dual Warp quaternions into a :data:`vec8` in ``(w, x, y, z)`` order."""
    return vec8(r[3], r[0], r[1], r[2], d[3], d[0], d[1], d[2])


@wp.func
def dq_from_rt(r: wp.quat, t: wp.vec3):
    """Pose that rotates by unit quaternion ``r`` then translates by ``t``: ``r + ε·½·t·r``."""
    d = wp.mul(wp.quat(t[0], t[1], t[2], 0.0), r) * 0.5
    return dq_pack(r, d)


@wp.func
def dq_translation(a: vec8):
    """Translation of a unit dual quaternion: ``t = 2·d·r*``."""
    t = wp.mul(dq_dual(a), wp.quat_inverse(dq_real(a))) * 2.0
    return wp.vec3(t[0], t[1], t[2])


@wp.func
def dq_mul(a: vec8, b: vec8):
    """Concatenation ``a·b`` (apply ``b`` first, then ``a``), as the matrix product ``A @ B``."""
    ar = dq_real(a)
    br = dq_real(b)
    return dq_pack(wp.mul(ar, br), wp.mul(ar, dq_dual(b)) + wp.mul(dq_dual(a), br))


@wp.func
def dq_conjugate(a: vec8):
    """Quaternion conjugate of both parts; the inverse of a unit dual quaternion."""
    return vec8(a[0], -a[1], -a[2], -a[3], a[4], -a[5], -a[6], -a[7])


@wp.func
def dq_normalize(a: vec8):
    """Unit dual quaternion nearest ``a`` (Montgomery-Smith & Shy eq. 14).

    ``r' = r/|r|``, ``d' = d/|r| − (r'·d/|r|)·r'``: unit real part and Plücker condition ``r'·d' = 0``.
    """
    r = dq_real(a)
    inv = 1.0 / wp.length(r)
    rn = r * inv
    dn = dq_dual(a) * inv
    dn = dn - rn * wp.dot(rn, dn)
    return dq_pack(rn, dn)


@wp.func
def dq_transform_point(a: vec8, p: wp.vec3):
    """Apply unit dual quaternion ``a`` to point ``p``: rotate, then translate."""
    return wp.quat_rotate(dq_real(a), p) + dq_translation(a)


@wp.func
def dq_transform_vector(a: vec8, v: wp.vec3):
    """Apply the rotation of unit dual quaternion ``a`` to direction ``v`` (no translation)."""
    return wp.quat_rotate(dq_real(a), v)


@wp.func
def dq_from_matrix(m: wp.mat44):
    """Dual quaternion of a rigid 4×4 matrix (column-vector convention, rotation orthonormal)."""
    r = wp.quat_from_matrix(wp.mat33(m[0, 0], m[0, 1], m[0, 2],
                                      m[1, 0], m[1, 1], m[1, 2],
                                      m[2, 0], m[2, 1], m[2, 2]))
    return dq_from_rt(wp.normalize(r), wp.vec3(m[0, 3], m[1, 3], m[2, 3]))


@wp.func
def dq_to_matrix(a: vec8):
    """4×4 rigid matrix (column-vector convention) of unit dual quaternion ``a``."""
    rm = wp.quat_to_matrix(dq_real(a))
    t = dq_translation(a)
    return wp.mat44(rm[0, 0], rm[0, 1], rm[0, 2], t[0],
                    rm[1, 0], rm[1, 1], rm[1, 2], t[1],
                    rm[2, 0], rm[2, 1], rm[2, 2], t[2],
                    0.0, 0.0, 0.0, 1.0)


@wp.func
def dq_to_transform(a: vec8):
    """Warp ``wp.transform`` ``(p, q)`` of unit dual quaternion ``a``."""
    return wp.transform(dq_translation(a), dq_real(a))


@wp.func
def dq_from_transform(x: wp.transform):
    """Dual quaternion of a Warp ``wp.transform``."""
    return dq_from_rt(wp.transform_get_rotation(x), wp.transform_get_translation(x))


@wp.func
def dq_blend_add(acc: vec8, a: vec8, w: float, pivot: wp.quat):
    """Accumulate ``w·a`` into ``acc``, flipping ``a`` onto the hemisphere of ``pivot`` (antipodality)."""
    s = w
    if wp.dot(dq_real(a), pivot) < 0.0:
        s = -w
    return acc + a * s


@wp.func
def dq_normalize_blend(a: vec8):
    """:func:`dq_normalize` of a blended sum; the identity when its real part vanishes (as Gf)."""
    if wp.length(dq_real(a)) < 1.0e-10:
        return vec8(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return dq_normalize(a)


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
    err = wp.abs(e[0, 0]) + wp.abs(e[1, 1]) + wp.abs(e[2, 2]) + wp.abs(e[0, 1]) + wp.abs(e[0, 2]) + wp.abs(e[1, 2])
    return err < 1.0e-6 and wp.determinant(a) > 0.0


@wp.func
def polar_rotation(a: wp.mat33):
    """Rotation factor ``R`` of the polar decomposition ``A = R·S``, det(R) = +1 (as ``GfMatrix4d::Factor``).

    Orthonormal input returns itself; otherwise ``R = U·Vᵀ`` from the SVD, negated when ``det A < 0``
    (Gf negates all three scales of a reflection, leaving a proper rotation).
    """
    if is_rotation(a):
        return a
    u = wp.mat33()
    sigma = wp.vec3()
    v = wp.mat33()
    wp.svd3(a, u, sigma, v)
    # svd3 keeps U, V proper rotations and may return a negative singular value: restore the sign
    sgn = wp.vec3(wp.sign(sigma[0]), wp.sign(sigma[1]), wp.sign(sigma[2]))
    r = u * wp.diag(sgn) * wp.transpose(v)
    if wp.determinant(r) < 0.0:
        r = -r
    return r


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
        bx = tx - ty * wp.dot(ty, tx)
        bx = bx - tz * wp.dot(tz, bx)
        by = ty - tx * wp.dot(tx, ty)
        by = by - tz * wp.dot(tz, by)
        bz = tz - tx * wp.dot(tx, tz)
        bz = bz - ty * wp.dot(ty, bz)
        cx = wp.normalize((tx + bx) * 0.5)
        cy = wp.normalize((ty + by) * 0.5)
        cz = wp.normalize((tz + bz) * 0.5)
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
