"""Quaternions as ``(..., 4)`` NumPy arrays ordered ``(w, x, y, z)``.

Products are Hamilton products (``i*j = k``). A unit quaternion ``q`` rotates a
vector ``v`` as ``q v q*``; rotation matrices use the column-vector convention
``v' = R @ v``. Every function accepts arbitrary leading batch dimensions and
broadcasts them between arguments. Floating inputs keep their dtype (float32 in,
float32 out); integer inputs are computed in float64. Scalar parameters (angles,
interpolation times) are cast to the dtype of the quaternion or vector argument.
A last axis of the wrong length raises ``ValueError``.

References
----------
[K] B. Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer
    Graphics and Beyond", 2012 (shared/references/000_e688072581e8ee3b.txt).
[MS] S. Montgomery-Smith and C. Shy, "An Introduction to Using Dual Quaternions
    to Study Kinematics", 2023 (shared/references/003_d8d7d9932a992693.txt).
"""

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .linalg import nonzero_norm2, unit_or_x
from .shapes import as_float, concat

__all__ = [
    "identity",
    "mul",
    "conjugate",
    "inverse",
    "dot",
    "norm",
    "normalize",
    "rotate",
    "from_axis_angle",
    "to_axis_angle",
    "from_matrix",
    "to_matrix",
    "exp",
    "log",
    "slerp",
]










def identity(shape: int | Sequence[int] = (), dtype: npt.DTypeLike = np.float64) -> np.ndarray:
    """Identity quaternions ``(1, 0, 0, 0)``.

    Parameters
    ----------
    shape : int or tuple of int
        Batch shape.
    dtype : numpy dtype
        Floating dtype of the result.

    Returns
    -------
    (*shape, 4) array of ``dtype``
    """
    batch = ((shape,) if isinstance(shape, (int, np.integer)) or np.ndim(shape) == 0
             else tuple(shape))
    q = np.zeros((*batch, 4), dtype=dtype)
    q[..., 0] = 1
    return q


def mul(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Hamilton product ``a b`` ([K] eq. 9).

    As rotations, ``mul(a, b)`` applies ``b`` first, then ``a``.

    Parameters
    ----------
    a, b : (..., 4) array_like, ``(w, x, y, z)``
        Broadcast against each other.

    Returns
    -------
    (..., 4) array
    """
    a = as_float(a, "a", 4)
    b = as_float(b, "b", 4)
    aw, ax, ay, az = (a[..., k] for k in range(4))
    bw, bx, by, bz = (b[..., k] for k in range(4))
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def conjugate(q: npt.ArrayLike) -> np.ndarray:
    """Conjugate ``q* = (w, -x, -y, -z)`` ([K] eq. 6).

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (..., 4) array
    """
    q = as_float(q, "q", 4)
    return np.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def inverse(q: npt.ArrayLike) -> np.ndarray:
    """Multiplicative inverse ``q* / |q|^2`` ([MS] sec. 2); ``q*`` for unit ``q`` ([K] eq. 10).

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (..., 4) array

    Raises
    ------
    ValueError
        If any ``q`` is zero.
    """
    q = as_float(q, "q", 4)
    return conjugate(q) / nonzero_norm2(q, "q")[..., None]


def dot(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Four-dimensional inner product ``Re(a b*)`` ([MS] eq. 5).

    Parameters
    ----------
    a, b : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (...) array
    """
    a = as_float(a, "a", 4)
    b = as_float(b, "b", 4)
    return np.sum(a * b, axis=-1)


def norm(q: npt.ArrayLike) -> np.ndarray:
    """Euclidean norm ``|q| = sqrt(q q*)`` ([MS] sec. 2).

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (...) array
    """
    q = as_float(q, "q", 4)
    return np.sqrt(np.sum(q * q, axis=-1))


def normalize(q: npt.ArrayLike) -> np.ndarray:
    """Unit quaternion ``q / |q|`` ([K] eq. 45).

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (..., 4) array

    Raises
    ------
    ValueError
        If any ``q`` is zero (it has no direction).
    """
    q = as_float(q, "q", 4)
    return q / np.sqrt(nonzero_norm2(q, "q"))[..., None]


def rotate(q: npt.ArrayLike, v: npt.ArrayLike) -> np.ndarray:
    """Rotate 3-vectors: ``q v q^-1`` ([K] eq. 5).

    ``q`` need not be unit: the result is the rotation by ``q / |q|``.

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``
    v : (..., 3) array_like
        Broadcast against ``q``'s batch shape.

    Returns
    -------
    (..., 3) array

    Raises
    ------
    ValueError
        If any ``q`` is zero.
    """
    q = as_float(q, "q", 4)
    v = as_float(v, "v", 3)
    u = q[..., 1:]
    w = q[..., :1]
    # q v q* = |q|^2 v + 2 (w u x v + u x (u x v)), from expanding eq. 5.
    uv = np.cross(u, v)
    scale = 2 / nonzero_norm2(q, "q")[..., None]
    return v + scale * (w * uv + np.cross(u, uv))


def from_axis_angle(axis: npt.ArrayLike, angle: npt.ArrayLike) -> np.ndarray:
    """Quaternion ``(cos(angle/2), axis sin(angle/2))`` ([K] eq. 3).

    Parameters
    ----------
    axis : (..., 3) array_like
        Rotation axis; normalized here.
    angle : (...) array_like
        Right-handed rotation angle [rad]; cast to ``axis``'s dtype and broadcast
        against ``axis``'s batch shape.

    Returns
    -------
    (..., 4) array, ``(w, x, y, z)``

    Raises
    ------
    ValueError
        If any axis is the zero vector.
    """
    axis = as_float(axis, "axis", 3)
    angle = as_float(angle, "angle", dtype=axis.dtype)
    n = np.linalg.norm(axis, axis=-1)
    if np.any(n == 0):
        raise InputError("axis has a zero vector, which defines no rotation axis")
    half = 0.5 * angle[..., None]
    return concat(np.cos(half), np.sin(half) * axis / n[..., None])


def to_axis_angle(q: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Axis and angle of the rotation represented by ``q`` ([K] eq. 4).

    ``q`` and ``-q`` give the same result: the angle is in ``[0, pi]``. The
    quaternion need not be unit. At angle 0 (no rotation) the axis is
    ``(1, 0, 0)``; at angle pi either axis direction is valid and the one along
    ``q``'s vector part (with ``w >= 0``) is returned.

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    axis : (..., 3) array
        Unit rotation axis.
    angle : (...) array
        Rotation angle [rad] in ``[0, pi]``.
    """
    q = as_float(q, "q", 4)
    q = np.where(q[..., :1] < 0, -q, q)
    u = q[..., 1:]
    s = np.linalg.norm(u, axis=-1)
    return unit_or_x(u), 2 * np.arctan2(s, q[..., 0])


def from_matrix(m: npt.ArrayLike) -> np.ndarray:
    """Unit quaternion of a rotation matrix (Shepperd's method).

    Of the four equivalent formulas for ``q`` (one per quaternion component),
    the one dividing by the largest component is used, so the result is accurate
    for every rotation angle. The result is normalized, so an approximately
    orthonormal matrix gives a nearby unit quaternion, and its sign is chosen so
    that ``w >= 0``.

    Parameters
    ----------
    m : (..., 3, 3) or (..., 4, 4) array_like
        Rotation matrices, column-vector convention (``v' = m @ v``); for 4x4
        input the upper-left 3x3 block is used. Must be proper rotations
        (``det = +1``); reflections give meaningless results.

    Returns
    -------
    (..., 4) array, ``(w, x, y, z)``
    """
    m = as_float(m, "m")
    if m.ndim < 2 or m.shape[-2:] not in ((3, 3), (4, 4)):
        raise InputError(f"m must have shape (..., 3, 3) or (..., 4, 4), got shape {m.shape}")
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # Row k equals 4 q_k q: exact for rotations, best conditioned for the largest q_k.
    candidates = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], axis=-1),
            np.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], axis=-1),
            np.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], axis=-1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], axis=-1),
        ],
        axis=-2,
    )
    diagonal = np.stack([m00 + m11 + m22, m00, m11, m22], axis=-1)
    best = np.argmax(diagonal, axis=-1)[..., None, None]
    q = np.take_along_axis(candidates, best, axis=-2)[..., 0, :]
    q = np.where(q[..., :1] < 0, -q, q)
    return normalize(q)


def to_matrix(q: npt.ArrayLike) -> np.ndarray:
    """Rotation matrix of ``q``, column-vector convention ``v' = R @ v`` ([K] eq. 7).

    [K] eq. 7 as printed has sign errors in its off-diagonal terms; this is the
    standard matrix of ``v -> q v q*`` (eq. 5). ``q`` need not be unit: each
    product of two components is divided by ``|q|^2``, which normalizes without a
    square root ([K] eq. 46).

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (..., 3, 3) array

    Raises
    ------
    ValueError
        If any ``q`` is zero.
    """
    q = as_float(q, "q", 4)
    s = 2 / nonzero_norm2(q, "q")
    w, x, y, z = (q[..., k] for k in range(4))
    rows = [
        [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
        [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
        [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def exp(q: npt.ArrayLike) -> np.ndarray:
    """Quaternion exponential ``e^w (cos|v|, v/|v| sin|v|)`` ([K] eq. 14).

    For a pure quaternion ``(0, a theta)`` with unit ``a`` this is
    ``(cos theta, a sin theta)``, the rotation by ``2 theta`` about ``a``.

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (..., 4) array
    """
    q = as_float(q, "q", 4)
    u = q[..., 1:]
    theta = np.linalg.norm(u, axis=-1, keepdims=True)
    # sin(theta)/theta via np.sinc, exact at theta = 0.
    e = np.exp(q[..., :1])
    return e * np.concatenate([np.cos(theta), np.sinc(theta / np.pi) * u], axis=-1)


def log(q: npt.ArrayLike) -> np.ndarray:
    """Principal quaternion logarithm ``(ln|q|, v/|v| atan2(|v|, w))`` (inverse of [K] eq. 14).

    ``exp(log(q)) == q`` for every nonzero ``q``; the vector part has length in
    ``[0, pi]``. Singular point: for a negative real ``q = (-c, 0, 0, 0)`` the
    direction is arbitrary and ``(ln c, pi, 0, 0)`` is returned.

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``

    Returns
    -------
    (..., 4) array

    Raises
    ------
    ValueError
        If any ``q`` is zero.
    """
    q = as_float(q, "q", 4)
    n2 = nonzero_norm2(q, "q")
    u = q[..., 1:]
    s = np.linalg.norm(u, axis=-1, keepdims=True)
    theta = np.arctan2(s, q[..., :1])
    return concat(0.5 * np.log(n2)[..., None], theta * unit_or_x(u))


def slerp(q0: npt.ArrayLike, q1: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """Spherical linear interpolation along the shorter arc ([K] eq. 17).

    Both inputs are normalized; ``q1`` is negated where ``dot(q0, q1) < 0`` so
    that the rotation takes the shortest path ([K] "Shortest or Longest
    Interpolation Path"). ``slerp(q0, q1, 0) == normalize(q0)`` and
    ``slerp(q0, q1, 1) == +-normalize(q1)``. Equals ``q0 (q0* q1)^t`` ([K] eq. 16).

    Parameters
    ----------
    q0, q1 : (..., 4) array_like, ``(w, x, y, z)``
        Start and end rotations.
    t : (...) array_like
        Interpolation parameter, typically in ``[0, 1]``; cast to the
        quaternions' dtype and broadcast against their batch shape.

    Returns
    -------
    (..., 4) array
        Unit quaternions.

    Raises
    ------
    ValueError
        If any input quaternion is zero.
    """
    q0 = normalize(as_float(q0, "q0", 4))
    q1 = normalize(as_float(q1, "q1", 4))
    q1 = np.where(dot(q0, q1)[..., None] < 0, -q1, q1)
    t = as_float(t, "t", dtype=np.result_type(q0, q1))[..., None]
    # Angle between the unit 4-vectors, accurate also for nearly equal inputs.
    omega = 2 * np.arctan2(norm(q0 - q1), norm(q0 + q1))[..., None]
    sin_omega = np.sin(omega)
    safe = np.where(sin_omega > 0, sin_omega, 1)
    k0 = np.where(sin_omega > 0, np.sin((1 - t) * omega) / safe, 1 - t)
    k1 = np.where(sin_omega > 0, np.sin(t * omega) / safe, t)
    return k0 * q0 + k1 * q1
