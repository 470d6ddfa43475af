"""Dual quaternions as ``(..., 8)`` NumPy arrays ``(rw, rx, ry, rz, dw, dx, dy, dz)``.

A dual quaternion is ``r + eps d`` with ``eps^2 = 0``; ``r`` (the real part) and
``d`` (the dual part) are Hamilton quaternions ordered ``(w, x, y, z)`` as in
:mod:`dqskin.quat`. A rigid pose "rotate by the unit quaternion ``q``, then
translate by ``t``" is the unit dual quaternion ``q + eps (1/2) t q``, so that
``t = 2 d r*``. ``mul(a, b)`` applies ``b`` first, then ``a``, exactly like the
4x4 matrix product ``A @ B`` (column-vector convention ``p' = M @ [p, 1]``).

A dual quaternion is *unit* when ``|r| = 1`` and ``r . d = 0`` (the Plücker
condition); ``dq`` and ``-dq`` represent the same pose. Functions that read a
pose (``to_rt``, ``to_matrix``, ``transform_point``, ``transform_vector``,
``to_screw``, ``power``, ``sclerp``, ``nlerp``) first project their input onto
the unit dual quaternions with :func:`normalize` ([MS] eq. 14), so scaled or
drifted inputs are accepted; ``dlb`` normalizes only its blended result.

Every function accepts arbitrary leading batch dimensions and broadcasts them
between arguments. Floating inputs keep their dtype (float32 in, float32 out);
integer inputs are computed in float64. Scalar parameters (interpolation times,
weights, angles) are cast to the dtype of the dual quaternion or vector
arguments. A last axis of the wrong length raises ``ValueError``.

Singular points
---------------
* A zero real part (``r = 0``) has no norm, inverse or pose: :func:`norm`,
  :func:`normalize`, :func:`inverse` and everything built on them raise
  ``ValueError``.
* ``log`` of the identity is zero. ``log`` of ``-1 + eps y`` (a full turn,
  ``rw = -1``), which has no canonical value ([MS] after eq. 48), returns
  ``-pi y/|y| - eps y``, rotating about ``-y/|y|`` (about ``(1, 0, 0)`` when
  ``y = 0``); it satisfies ``exp(log(dq)) == dq`` and matches :func:`to_screw`.
* :func:`to_screw` of a pure translation (``rx = ry = rz = 0``) returns
  ``theta = 0`` (or ``2 pi`` when ``rw = -1``), the translation direction as the
  axis, its length as ``d >= 0`` and zero moment; of the identity it returns
  the axis ``(1, 0, 0)`` and ``d = 0``.

References
----------
[K] B. Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer
    Graphics and Beyond", 2012 (shared/references/000_e688072581e8ee3b.txt).
[C] "Dual Quaternions" note on the three conjugates and on ``t = 2 d r*``
    (shared/references/001_9d80ba7dedfc8820.txt).
[MS] S. Montgomery-Smith and C. Shy, "An Introduction to Using Dual Quaternions
    to Study Kinematics", 2023 (shared/references/003_d8d7d9932a992693.txt).
[B] "Dual Quaternion" note on matrix conversion and DLB
    (shared/references/004_36c1f3d9accc74fe.txt; no equation numbers).
"""

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from . import dual, quat
from .errors import InputError
from .linalg import nonzero_norm2, unit_or_x
from .shapes import as_float, concat

__all__ = [
    "identity",
    "mul",
    "conjugate_quat",
    "conjugate_dual",
    "conjugate_both",
    "norm",
    "normalize",
    "inverse",
    "inverse_unit",
    "dot",
    "from_rotation",
    "from_translation",
    "from_rt",
    "to_rt",
    "from_matrix",
    "to_matrix",
    "transform_point",
    "transform_vector",
    "to_screw",
    "from_screw",
    "power",
    "sclerp",
    "nlerp",
    "dlb",
    "exp",
    "log",
    "exp_twist",
    "lie_difference",
    "twist",
    "wrench",
]


def _dq(x: npt.ArrayLike, name: str) -> np.ndarray:
    """``x`` as a floating ``(..., 8)`` array; ``ValueError`` naming ``name`` otherwise."""
    return as_float(x, name, 8)


def _scale(dq: np.ndarray, s: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Product of ``dq`` and the dual number ``s = (s0, s1)``: ``s0 r + eps (s0 d + s1 r)``."""
    r, d = dq[..., :4], dq[..., 4:]
    s0, s1 = s[0][..., None], s[1][..., None]
    return concat(s0 * r, s0 * d + s1 * r)


def identity(shape: int | Sequence[int] = (), dtype: npt.DTypeLike = np.float64) -> np.ndarray:
    """Identity dual quaternions ``[1, 0, 0, 0][0, 0, 0, 0]`` ([K] eq. 24): ``(*shape, 8)`` of
    ``dtype``, the real part :func:`dqskin.quat.identity` (``shape``: int or tuple; batch shape)."""
    r = quat.identity(shape, dtype)
    return concat(r, np.zeros_like(r))


def mul(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Product ``a b = r_a r_b + eps (r_a d_b + d_a r_b)`` ([K] eq. 31).

    As poses, ``b`` is applied first, then ``a``: ``to_matrix(mul(a, b)) ==
    to_matrix(a) @ to_matrix(b)`` ([MS] eq. 3 and 7).

    Parameters
    ----------
    a, b : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Broadcast against each other.

    Returns
    -------
    (..., 8) array
    """
    a = _dq(a, "a")
    b = _dq(b, "b")
    ra, da = a[..., :4], a[..., 4:]
    rb, db = b[..., :4], b[..., 4:]
    return concat(quat.mul(ra, rb), quat.mul(ra, db) + quat.mul(da, rb))


def conjugate_quat(dq: npt.ArrayLike) -> np.ndarray:
    """Quaternion conjugate ``r* + eps d*`` ([C] eq. 5, first; [K] eq. 32; [MS] eq. 8).

    Reverses products, ``(a b)* = b* a*``, and is the inverse of a unit dual
    quaternion ([MS] eq. 10).

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array
    """
    dq = _dq(dq, "dq")
    return concat(quat.conjugate(dq[..., :4]), quat.conjugate(dq[..., 4:]))


def conjugate_dual(dq: npt.ArrayLike) -> np.ndarray:
    """Dual-number conjugate ``r - eps d`` ([C] eq. 5, second; [MS] sec. 3).

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array
    """
    dq = _dq(dq, "dq")
    return concat(dq[..., :4], -dq[..., 4:])


def conjugate_both(dq: npt.ArrayLike) -> np.ndarray:
    """Combined conjugate ``r* - eps d*`` ([C] eq. 5, third; [MS] eq. 18).

    A point ``p`` maps as ``1 + eps p' = dq (1 + eps p) conjugate_both(dq)``.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array
    """
    dq = _dq(dq, "dq")
    return concat(quat.conjugate(dq[..., :4]), -quat.conjugate(dq[..., 4:]))


def norm(dq: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Dual-number norm ``|dq| = |r| + eps (r . d)/|r|`` ([MS] eq. 11-12).

    Multiplicative: ``|a b| = |a| |b|`` as dual numbers ([MS] eq. 13). A unit
    dual quaternion has norm ``(1, 0)``.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    real, dual : (...) arrays
        The dual number ``real + eps dual``.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = _dq(dq, "dq")
    r, d = dq[..., :4], dq[..., 4:]
    norm2 = nonzero_norm2(r, "real part of dq")
    return dual.sqrt((norm2, 2 * quat.dot(r, d)))


def normalize(dq: npt.ArrayLike) -> np.ndarray:
    """Project onto the unit dual quaternions: ``|dq|^-1 dq`` ([MS] eq. 14).

    The result has ``|r| = 1`` and satisfies the Plücker condition ``r . d = 0``.
    Explicitly it is ``r/|r| + eps (d/|r| - (r . d) r/|r|^3)``; the right-hand
    side printed in [MS] eq. 14 omits the ``1/|r|`` factors of the dual part and
    is only correct when ``|r| = 1``. Properties: idempotent, ``normalize(k dq)
    == sign(k) normalize(dq)`` for scalar ``k != 0``, and ``normalize(a b) ==
    normalize(a) normalize(b)`` ([MS] eq. 15). The pose is unchanged when ``dq``
    is already unit up to scale.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = _dq(dq, "dq")
    n = norm(dq)
    return _scale(dq, dual.div((np.ones_like(n[0]), np.zeros_like(n[1])), n))


def inverse(dq: npt.ArrayLike) -> np.ndarray:
    """Multiplicative inverse ``r^-1 - eps r^-1 d r^-1`` ([MS] eq. 9).

    Valid for any dual quaternion with a nonzero real part; for unit ones
    :func:`inverse_unit` is cheaper and equal.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = _dq(dq, "dq")
    r_inv = quat.inverse(dq[..., :4])
    return concat(r_inv, -quat.mul(quat.mul(r_inv, dq[..., 4:]), r_inv))


def inverse_unit(dq: npt.ArrayLike) -> np.ndarray:
    """Inverse of a unit dual quaternion, its quaternion conjugate ``r* + eps d*`` ([MS] eq. 10).

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Unit dual quaternions (not checked).

    Returns
    -------
    (..., 8) array
    """
    return conjugate_quat(dq)


def dot(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Dot product of the real parts, ``r_a . r_b`` ([K] Listing 1, ``Dot``).

    Its sign tells whether ``a`` and ``b`` lie in the same hemisphere, i.e.
    whether interpolating from ``a`` to ``b`` takes the shorter path ([K]
    "Shortest or Longest Interpolation Path").

    Parameters
    ----------
    a, b : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (...) array
    """
    a = _dq(a, "a")
    b = _dq(b, "b")
    return quat.dot(a[..., :4], b[..., :4])


def from_rotation(q: npt.ArrayLike) -> np.ndarray:
    """Pure rotation ``q + eps 0`` ([K] eq. 27).

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``
        Rotation; normalized here.

    Returns
    -------
    (..., 8) array

    Raises
    ------
    ValueError
        If any ``q`` is zero.
    """
    q = quat.normalize(q)
    return concat(q, np.zeros_like(q))


def from_translation(t: npt.ArrayLike) -> np.ndarray:
    """Pure translation ``1 + eps (0, t/2)`` ([K] eq. 28).

    Parameters
    ----------
    t : (..., 3) array_like
        Translation vector.

    Returns
    -------
    (..., 8) array
    """
    t = as_float(t, "t", 3)
    r = np.zeros(t.shape[:-1] + (4,), dtype=t.dtype)
    r[..., 0] = 1
    return concat(r, concat(np.zeros_like(t[..., :1]), 0.5 * t))


def from_rt(q: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """Pose "rotate by ``q``, then translate by ``t``": ``q + eps (1/2) t q``.

    [K] eq. 25-26; [MS] eq. 17; [C] eq. 11-14.

    Parameters
    ----------
    q : (..., 4) array_like, ``(w, x, y, z)``
        Rotation; normalized here.
    t : (..., 3) array_like
        Translation; broadcast against ``q``'s batch shape.

    Returns
    -------
    (..., 8) array
        Unit dual quaternions.

    Raises
    ------
    ValueError
        If any ``q`` is zero.
    """
    q = quat.normalize(q)
    t = as_float(t, "t", 3)
    t_quat = concat(np.zeros_like(t[..., :1]), t)
    return concat(q, 0.5 * quat.mul(t_quat, q))


def to_rt(dq: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation of the pose ``normalize(dq)``: ``q = r``, ``t = 2 d r*``.

    [K] eq. 29.

    Computed without normalizing first as ``q = r/|r|`` and ``t = 2 Im(d r*)/|r|^2``,
    which equals eq. 29 applied to ``normalize(dq)``: the component of ``d``
    along ``r`` only contributes to the discarded real part. ``q`` keeps the sign
    of ``r``, so ``from_rt(*to_rt(dq)) == normalize(dq)``.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    q : (..., 4) array
        Unit rotation quaternion ``(w, x, y, z)``.
    t : (..., 3) array
        Translation.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = _dq(dq, "dq")
    r, d = dq[..., :4], dq[..., 4:]
    norm2 = nonzero_norm2(r, "real part of dq")
    t = 2 * quat.mul(d, quat.conjugate(r))[..., 1:] / norm2[..., None]
    return r / np.sqrt(norm2)[..., None], t


def from_matrix(m: npt.ArrayLike) -> np.ndarray:
    """Unit dual quaternion of a rigid 4x4 transform ([B] "Converting Matrix to Dual Quaternion").

    The rotation block goes through :func:`dqskin.quat.from_matrix` (Shepperd's
    method, normalized, ``rw >= 0``); the bottom row is ignored.

    Parameters
    ----------
    m : (..., 4, 4) array_like
        Rigid transforms, column-vector convention ``p' = m @ [p, 1]``.

    Returns
    -------
    (..., 8) array
    """
    m = as_float(m, "m")
    if m.ndim < 2 or m.shape[-2:] != (4, 4):
        raise InputError(f"m must have shape (..., 4, 4), got shape {m.shape}")
    return from_rt(quat.from_matrix(m[..., :3, :3]), m[..., :3, 3])


def to_matrix(dq: npt.ArrayLike) -> np.ndarray:
    """4x4 rigid transform of the pose ``normalize(dq)``.

    Rotation block from [K] eq. 7 (see :func:`dqskin.quat.to_matrix`), translation
    column from [K] eq. 29 ([B] "Converting Dual Quaternion to Matrix").

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 4, 4) array
        ``[[R, t], [0, 0, 0, 1]]``, column-vector convention ``p' = M @ [p, 1]``.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    q, t = to_rt(dq)
    m = np.zeros(q.shape[:-1] + (4, 4), dtype=q.dtype)
    m[..., :3, :3] = quat.to_matrix(q)
    m[..., :3, 3] = t
    m[..., 3, 3] = 1
    return m


def transform_point(dq: npt.ArrayLike, p: npt.ArrayLike) -> np.ndarray:
    """Apply the pose to points: ``p' = r p r* + 2 d r*`` ([MS] eq. 19; [K] eq. 35).

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Poses (normalized first).
    p : (..., 3) array_like
        Points; broadcast against ``dq``'s batch shape.

    Returns
    -------
    (..., 3) array

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    q, t = to_rt(dq)
    return quat.rotate(q, as_float(p, "p", 3)) + t


def transform_vector(dq: npt.ArrayLike, v: npt.ArrayLike) -> np.ndarray:
    """Apply only the rotation of the pose to direction vectors: ``v' = r v r*`` ([K] eq. 5).

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
    v : (..., 3) array_like
        Vectors; broadcast against ``dq``'s batch shape.

    Returns
    -------
    (..., 3) array

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = _dq(dq, "dq")
    return quat.rotate(dq[..., :4], as_float(v, "v", 3))


def _screw_axis(c: np.ndarray, u: np.ndarray, s: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """Rotation axis ``u/s``; for ``s = 0`` the direction of ``sign(c) dv``, or ``(1, 0, 0)``.

    Shared by :func:`to_screw` and :func:`log` so that both choose the same axis
    at the singular points.
    """
    sign = np.where(c < 0, -1, 1).astype(u.dtype)[..., None]
    fallback = unit_or_x(sign * dv)
    safe_s = np.where(s > 0, s, 1)[..., None]
    return np.where(s[..., None] > 0, u / safe_s, fallback)


def to_screw(dq: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Screw parameters ``(theta, d, l, m)`` of ``normalize(dq)`` ([K] eq. 36-37).

    The pose is a rotation by ``theta`` about the line with unit direction ``l``
    and moment ``m = p x l`` (``p`` any point on the line; Plücker coordinates),
    combined with a translation ``d`` along ``l``. With ``s = |r_xyz|``:
    ``theta = 2 atan2(s, rw)`` in ``[0, 2 pi]``, ``l = r_xyz / s``,
    ``d = 2 (l . d_xyz cos(theta/2) - dw sin(theta/2))`` and ``m`` the part of
    ``d_xyz`` perpendicular to ``l`` divided by ``s``. Under the Plücker condition
    these equal eq. 37 but avoid its ``acos`` and divisions at small angles.
    ``-dq`` gives ``(2 pi - theta, -d, -l, -m)``, the same screw motion.

    Singular point: for a pure translation (``s = 0``) ``theta`` is 0 (``2 pi``
    when ``rw < 0``), ``l`` is the translation direction (so ``d >= 0`` is its
    length), ``m = 0``; for the identity ``l = (1, 0, 0)`` and ``d = 0``. As the
    rotation angle tends to 0 with a translation perpendicular to the axis, the
    axis moves to infinity and ``m`` grows without bound.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    theta : (...) array
        Rotation angle [rad].
    d : (...) array
        Translation along the axis (pitch distance).
    l : (..., 3) array
        Unit axis direction.
    m : (..., 3) array
        Axis moment, perpendicular to ``l``.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = normalize(dq)
    c, u = dq[..., 0], dq[..., 1:4]
    dw, dv = dq[..., 4], dq[..., 5:8]
    s = np.linalg.norm(u, axis=-1)
    half = np.arctan2(s, c)
    l = _screw_axis(c, u, s, dv)
    along = np.sum(l * dv, axis=-1)
    d = 2 * (along * np.cos(half) - dw * np.sin(half))
    safe_s = np.where(s > 0, s, 1)[..., None]
    m = np.where(s[..., None] > 0, (dv - along[..., None] * l) / safe_s, 0)
    return 2 * half, d, l, m


def from_screw(theta: npt.ArrayLike, d: npt.ArrayLike, l: npt.ArrayLike,
               m: npt.ArrayLike) -> np.ndarray:
    """Unit dual quaternion of screw parameters ([K] eq. 38).

    ``r = (cos(theta/2), l sin(theta/2))``,
    ``d = (-(d/2) sin(theta/2), m sin(theta/2) + (d/2) cos(theta/2) l)``.
    With ``theta = 0`` this is the pure translation by ``d l``.

    Parameters
    ----------
    theta : (...) array_like
        Rotation angle [rad]; cast to ``l``/``m``'s dtype.
    d : (...) array_like
        Translation along the axis; cast to ``l``/``m``'s dtype.
    l : (..., 3) array_like
        Unit axis direction (not normalized here).
    m : (..., 3) array_like
        Axis moment, perpendicular to ``l``.

    Returns
    -------
    (..., 8) array
        All arguments broadcast against each other's batch shapes.
    """
    l = as_float(l, "l", 3)
    m = as_float(m, "m", 3)
    dtype = np.result_type(l, m)
    half = 0.5 * as_float(theta, "theta", dtype=dtype)[..., None]
    d = as_float(d, "d", dtype=dtype)[..., None]
    sin, cos = np.sin(half), np.cos(half)
    real = concat(cos, sin * l)
    dual_part = concat(-0.5 * d * sin, sin * m + 0.5 * d * cos * l)
    return concat(real, dual_part)


def power(dq: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """Power ``dq^t`` via the screw parameters ([K] eq. 39-40).

    Scales angle and translation along the screw axis by ``t``:
    ``from_screw(t theta, t d, l, m)`` with ``(theta, d, l, m) = to_screw(dq)``.
    Equals ``exp(t log(dq))`` for unit ``dq``. ``dq^0`` is exactly the identity.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Normalized first.
    t : (...) array_like
        Exponent; cast to ``dq``'s dtype, broadcast against its batch shape.

    Returns
    -------
    (..., 8) array
        Unit dual quaternions.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    dq = _dq(dq, "dq")
    t = as_float(t, "t", dtype=dq.dtype)
    theta, d, l, m = to_screw(dq)
    return from_screw(t * theta, t * d, l, m)


def sclerp(a: npt.ArrayLike, b: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """Screw linear interpolation ``a (a^-1 b)^t`` along the shorter path ([K] eq. 41; [MS] eq. 41).

    Both inputs are normalized; ``b`` is negated where ``dot(a, b) < 0`` ([K]
    "Shortest or Longest Interpolation Path"), so ``sclerp(a, -b, t) ==
    sclerp(a, b, t)``. The motion is a constant-speed screw: rotation angle and
    translation along the axis grow linearly in ``t``. ``sclerp(a, b, 0) ==
    normalize(a)`` and ``sclerp(a, b, 1) == +-normalize(b)`` (the sign of
    ``a``'s hemisphere).

    Parameters
    ----------
    a, b : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Start and end poses.
    t : (...) array_like
        Interpolation parameter, typically in ``[0, 1]``; cast to the poses'
        dtype and broadcast against their batch shape.

    Returns
    -------
    (..., 8) array
        Unit dual quaternions.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    a = normalize(_dq(a, "a"))
    b = normalize(_dq(b, "b"))
    b = np.where(dot(a, b)[..., None] < 0, -b, b)
    t = as_float(t, "t", dtype=np.result_type(a, b))
    return mul(a, power(mul(conjugate_quat(a), b), t))


def nlerp(a: npt.ArrayLike, b: npt.ArrayLike, t: npt.ArrayLike) -> np.ndarray:
    """Normalized linear interpolation ``normalize(a + (b - a) t)``, shorter path ([K] eq. 44).

    Both inputs are normalized and ``b`` is negated where ``dot(a, b) < 0``.
    The normalization is the dual-number one ([MS] eq. 14). Cheap, but the
    speed along the path is not constant.

    Parameters
    ----------
    a, b : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Start and end poses.
    t : (...) array_like
        Interpolation parameter in ``[0, 1]``; cast to the poses' dtype and
        broadcast against their batch shape.

    Returns
    -------
    (..., 8) array
        Unit dual quaternions.

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    a = normalize(_dq(a, "a"))
    b = normalize(_dq(b, "b"))
    b = np.where(dot(a, b)[..., None] < 0, -b, b)
    t = as_float(t, "t", dtype=np.result_type(a, b))[..., None]
    return normalize(a + (b - a) * t)


def dlb(dqs: npt.ArrayLike, weights: npt.ArrayLike) -> np.ndarray:
    """Dual quaternion linear blending ``normalize(sum_k w_k s_k dq_k)`` ([B] DLB; [K] "DLB").

    Antipodality: every ``dq_k`` is multiplied by ``s_k = +-1`` so that its real
    part lies in the hemisphere of the pivot, the input with the largest weight
    (first on ties): ``s_k = -1`` where ``dot(dq_k, dq_pivot) < 0``. Without this,
    ``dq`` and ``-dq`` (the same pose) would blend differently. The weighted sum
    is then normalized with the dual-number norm ([MS] eq. 14). The resulting
    pose does not depend on the signs of the inputs; as an 8-vector it follows
    the sign of the pivot input. Inputs are used as given (not normalized first),
    so they should be unit.

    Parameters
    ----------
    dqs : (..., K, 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Poses to blend, e.g. bone transforms influencing a vertex.
    weights : (..., K) array_like
        Blend weights (need not sum to 1); cast to ``dqs``'s dtype and broadcast
        against its batch shape.

    Returns
    -------
    (..., 8) array
        Unit dual quaternions.

    Raises
    ------
    ValueError
        If any blended real part is zero (e.g. all weights zero).
    """
    dqs = _dq(dqs, "dqs")
    if dqs.ndim < 2:
        raise InputError(f"dqs must have shape (..., K, 8), got shape {dqs.shape}")
    weights = as_float(weights, "weights", dtype=dqs.dtype)
    if weights.ndim == 0 or weights.shape[-1] not in (1, dqs.shape[-2]):
        raise InputError(
            f"weights must have shape (..., {dqs.shape[-2]}), got shape {weights.shape}"
        )
    batch = np.broadcast_shapes(dqs.shape[:-2], weights.shape[:-1])
    dqs = np.broadcast_to(dqs, batch + dqs.shape[-2:])
    weights = np.broadcast_to(weights, batch + dqs.shape[-2:-1])
    pivot = np.take_along_axis(dqs, np.argmax(weights, axis=-1)[..., None, None], axis=-2)
    signs = np.where(dot(dqs, pivot) < 0, -1, 1).astype(dqs.dtype)
    return normalize(np.sum((weights * signs)[..., None] * dqs, axis=-2))


def exp(xi: npt.ArrayLike) -> np.ndarray:
    """Dual quaternion exponential ``sum_k xi^k / k!`` ([MS] eq. 39), closed form ([MS] eq. 43-44).

    For a vector dual quaternion ``xi = (0, a theta, 0, u)`` (unit ``a``), with
    ``u = u1 a + u_perp``, the result is
    ``(cos theta + a sin theta)(1 + eps u1 a) + eps (sin theta / theta) u_perp``,
    the pose reached after unit time of the constant body twist
    ``(omega, v) = (2 a theta, 2 u)`` ([MS] eq. 26, 40). Nonzero scalar parts
    ``(rw, dw)`` form a central dual number and contribute the factor
    ``e^rw (1 + eps dw)``. The result is unit iff both scalar parts are zero.

    Parameters
    ----------
    xi : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array
    """
    xi = _dq(xi, "xi")
    w_half, v_half = xi[..., 1:4], xi[..., 5:8]
    theta = np.linalg.norm(w_half, axis=-1, keepdims=True)
    a = unit_or_x(w_half)
    v1 = np.sum(v_half * a, axis=-1, keepdims=True)
    v_perp = v_half - v1 * a
    sin, cos = np.sin(theta), np.cos(theta)
    real = concat(cos, sin * a)
    dual_part = concat(-v1 * sin, v1 * cos * a + np.sinc(theta / np.pi) * v_perp)
    scalar = dual.apply(np.exp, np.exp, (xi[..., 0], xi[..., 4]))
    return _scale(concat(real, dual_part), scalar)


def log(dq: npt.ArrayLike) -> np.ndarray:
    """Principal dual quaternion logarithm ([MS] eq. 46-48).

    For a unit ``dq = c + s a + eps (x + y1 a + y2 b)`` (``a``, ``b``
    orthonormal, ``s >= 0``) with ``phi = atan2(s, c)`` in ``[0, pi]``:
    ``log(dq) = phi a + eps ((c y1 - s x) a + (phi/s) y2 b)``, a vector dual
    quaternion ``(0, omega/2, 0, v/2)``: ``(omega, v)`` is the constant body
    twist that reaches ``dq`` from the identity in unit time, with
    ``|omega| <= 2 pi``: the principal value, the smallest ``|omega|`` among the
    logarithms of this ``dq`` ([MS] sec. 8). ``exp(log(dq)) == dq``.
    A non-unit ``dq`` adds the dual-number logarithm of its norm,
    ``ln|r| + eps (r . d)/|r|^2``, to the scalar parts, so ``exp(log(dq)) == dq``
    holds for every ``dq`` with a nonzero real part.

    Singular points: ``log`` of the identity is zero; for ``rw = -1`` (a full
    turn, ``dq = -1 + eps y``) the result is ``-pi y/|y| - eps y``, i.e. the axis
    ``-y/|y|`` (``(1, 0, 0)`` when ``y = 0``), consistent with :func:`to_screw`.
    Inputs with ``rw`` near ``-1`` are ill-conditioned. Sign-align with
    :func:`dot` first if the shorter of the two possible motions is wanted.

    Parameters
    ----------
    dq : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``

    Returns
    -------
    (..., 8) array

    Raises
    ------
    ValueError
        If any real part is zero.
    """
    unit = normalize(dq)
    c, u = unit[..., :1], unit[..., 1:4]
    x, y = unit[..., 4:5], unit[..., 5:8]
    s = np.linalg.norm(u, axis=-1)
    a = _screw_axis(c[..., 0], u, s, y)
    s = s[..., None]
    phi = np.arctan2(s, c)
    y1 = np.sum(y * a, axis=-1, keepdims=True)
    ratio = np.where(s > 0, phi / np.where(s > 0, s, 1), 1)
    dual_vec = (c * y1 - s * x) * a + ratio * (y - y1 * a)
    scalar = dual.apply(np.log, np.reciprocal, norm(dq))
    return concat(concat(scalar[0][..., None], phi * a), concat(scalar[1][..., None], dual_vec))


def exp_twist(omega: npt.ArrayLike, v: npt.ArrayLike) -> np.ndarray:
    """Pose after unit time of constant body twist ``(omega, v)``: ``exp(omega/2 + eps v/2)``.

    [MS] eq. 26, 40.

    ``exp_twist(t omega, t v)`` is the screw motion with angular velocity
    ``omega`` and linear velocity ``v``, both in the moving (body) frame, and
    :func:`twist` of it returns ``(omega, v)``.

    Parameters
    ----------
    omega : (..., 3) array_like
        Angular velocity [rad per unit time], body frame.
    v : (..., 3) array_like
        Linear velocity, body frame; broadcast against ``omega``'s batch shape.

    Returns
    -------
    (..., 8) array
        Unit dual quaternions.
    """
    omega = as_float(omega, "omega", 3)
    v = as_float(v, "v", 3)
    zero = np.zeros_like(omega[..., :1])
    return exp(concat(zero, 0.5 * omega, zero, 0.5 * v))


def lie_difference(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Twist taking pose ``a`` to pose ``b`` in unit time: ``log(a^-1 b)``.

    Satisfies ``mul(a, exp(lie_difference(a, b))) == b``. This is the exact
    version of the Lie difference ``b Delta a = Im(a* b)`` of [MS] eq. 37, which
    it matches to first order for nearby poses ([MS] eq. 35-38). No sign
    alignment is done: sign-align ``b`` with :func:`dot` for the shorter motion.

    Parameters
    ----------
    a, b : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Reference and target poses.

    Returns
    -------
    (..., 8) array
        Vector dual quaternion ``(0, omega/2, 0, v/2)`` for unit inputs.

    Raises
    ------
    ValueError
        If any real part of ``a`` or ``a^-1 b`` is zero.
    """
    return log(mul(inverse(_dq(a, "a")), _dq(b, "b")))


def twist(eta: npt.ArrayLike, eta_dot: npt.ArrayLike,
          frame: str = "body") -> tuple[np.ndarray, np.ndarray]:
    """Angular and linear velocity of a moving pose ([MS] eq. 25-26).

    ``frame="body"``: ``phi = eta^-1 eta_dot = omega/2 + eps v/2`` ([MS] eq.
    25-26), velocities in the moving frame (``d/dt [R t] = [R t][S(omega) v]``,
    eq. 23, so ``dt/dt = R v``). ``frame="spatial"``: ``eta_dot eta^-1``
    ([MS] note after eq. 26), velocities in the fixed frame, with ``v`` the
    velocity of the body point currently at the origin (``dt/dt = omega x t +
    v``). The scalar parts of ``phi``, zero when ``eta_dot`` is tangent to the
    unit dual quaternions, are dropped.

    Parameters
    ----------
    eta : (..., 8) array_like, ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        Pose (unit dual quaternion).
    eta_dot : (..., 8) array_like
        Its time derivative.
    frame : {"body", "spatial"}
        Frame in which the velocities are expressed.

    Returns
    -------
    omega : (..., 3) array
        Angular velocity [rad per unit time].
    v : (..., 3) array
        Linear velocity.

    Raises
    ------
    ValueError
        If ``frame`` is not "body" or "spatial", or any real part of ``eta`` is zero.
    """
    eta = _dq(eta, "eta")
    eta_dot = _dq(eta_dot, "eta_dot")
    if frame == "body":
        phi = mul(inverse(eta), eta_dot)
    elif frame == "spatial":
        phi = mul(eta_dot, inverse(eta))
    else:
        raise InputError(f'frame must be "body" or "spatial", got {frame!r}')
    return 2 * phi[..., 1:4], 2 * phi[..., 5:8]


def wrench(torque: npt.ArrayLike, force: npt.ArrayLike) -> np.ndarray:
    """Wrench dual quaternion ``2 q + 2 eps p`` ([MS] eq. 27).

    ``q`` is the torque and ``p`` the force applied at the origin of the moving
    frame, both expressed in the moving frame. The factor 2 makes the 8-vector
    dot product with the twist ``omega/2 + eps v/2`` the power
    ``q . omega + p . v`` ([MS] eq. 30).

    Parameters
    ----------
    torque : (..., 3) array_like
    force : (..., 3) array_like
        Broadcast against ``torque``'s batch shape.

    Returns
    -------
    (..., 8) array
        ``(0, 2 torque, 0, 2 force)``.
    """
    torque = as_float(torque, "torque", 3)
    force = as_float(force, "force", 3)
    zero = np.zeros_like(torque[..., :1])
    return concat(zero, 2 * torque, zero, 2 * force)
