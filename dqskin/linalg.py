"""Small float64 pieces shared by the NumPy algebra and kinematics: cross-product matrices, the
polar split, safe normalization. Their float32 device counterparts are in
:mod:`dqskin.kernels.dqmath`."""

import numpy as np
import numpy.typing as npt

from .errors import InputError

__all__ = ["NEAR_ROTATION", "NEWTON_STEPS", "hat", "nonzero_norm2", "polar", "unit_or_x", "vee"]

NEAR_ROTATION = 1e-3
"""Largest ``|aᵀa − I|`` entry for which :func:`polar` iterates instead of taking the SVD."""

NEWTON_STEPS = 3
"""Polar iteration steps from within :data:`NEAR_ROTATION`: the error goes 1e-3 → 5e-7 → 1e-13
→ rounding."""


def hat(w: np.ndarray) -> np.ndarray:
    """(..., 3) → (..., 3, 3) cross-product matrices ``[w]×`` ([MS] eq. 21)."""
    z = np.zeros_like(w[..., 0])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1),
                     np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def vee(k: np.ndarray) -> np.ndarray:
    """Axial vector of the skew-symmetric part of (..., 3, 3) ``k``."""
    return 0.5 * np.stack([k[..., 2, 1] - k[..., 1, 2], k[..., 0, 2] - k[..., 2, 0],
                           k[..., 1, 0] - k[..., 0, 1]], -1)



def _cofactors(x):
    """(9, N) cofactor matrices and (N,) determinants of (9, N) row-major 3×3 matrices (one
    component per row: contiguous, so each step is a handful of NumPy passes)."""
    a00, a01, a02, a10, a11, a12, a20, a21, a22 = x
    c = np.stack([a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20,
                  a02 * a21 - a01 * a22, a00 * a22 - a02 * a20, a01 * a20 - a00 * a21,
                  a01 * a12 - a02 * a11, a02 * a10 - a00 * a12, a00 * a11 - a01 * a10])
    return c, a00 * c[0] + a01 * c[1] + a02 * c[2]


def polar(a: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Polar split ``a = R·S`` of (..., 3, 3) float64: ``R`` proper rotation, ``S`` symmetric.

    As the skinning and FK kernels (``GfMatrix4d::Factor``): ``R = U·Vᵀ`` from the SVD, negated
    when ``det a < 0`` (a reflection then lives in ``S``). A matrix with ``det a > 0`` within
    :data:`NEAR_ROTATION` of a rotation (every ``|aᵀa − I|`` entry; animation keys stored as float
    quaternions are within 1e-5) skips the SVD: :data:`NEWTON_STEPS` steps of the polar iteration
    ``X ← (X + X⁻ᵀ)/2``, which squares the error each step, reach the same ``R`` to rounding at a
    fraction of the SVD's cost.
    """
    a = np.asarray(a, dtype=np.float64)
    flat = a.reshape(-1, 3, 3)
    x = np.ascontiguousarray(flat.reshape(-1, 9).T)  # (9, N)
    gram = np.stack([x[i] * x[j] + x[i + 3] * x[j + 3] + x[i + 6] * x[j + 6]
                     for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))])
    gram[:3] -= 1.0
    near = np.abs(gram).max(axis=0) < NEAR_ROTATION
    near &= _cofactors(x)[1] > 0
    r = np.empty_like(flat)
    if near.any():
        y = x[:, near]
        for _ in range(NEWTON_STEPS):
            c, det = _cofactors(y)
            y = 0.5 * (y + c / det)
        r[near] = y.T.reshape(-1, 3, 3)
    if not near.all():
        u, _, vt = np.linalg.svd(flat[~near])
        rest = u @ vt
        r[~near] = np.where((np.linalg.det(rest) < 0)[..., None, None], -rest, rest)
    r = r.reshape(a.shape)
    return r, np.swapaxes(r, -1, -2) @ a


def nonzero_norm2(q: np.ndarray, name: str) -> np.ndarray:
    """Squared norm of ``q`` (shape ``(...)``); raise ``ValueError`` if any is zero."""
    n2 = np.sum(q * q, axis=-1)
    if np.any(n2 == 0):
        raise InputError(f"{name} has a zero-norm quaternion, which has no inverse or direction")
    return n2


def unit_or_x(v: np.ndarray) -> np.ndarray:
    """Normalize 3-vectors ``v`` (..., 3); zero vectors become the x axis ``(1, 0, 0)``."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    x_axis = np.zeros_like(v)
    x_axis[..., 0] = 1
    return np.where(n > 0, v / np.where(n > 0, n, 1), x_axis)
