"""Small float64 pieces shared by the NumPy algebra and kinematics: cross-product matrices, the
polar split, safe normalization. Their float32 device counterparts are in
:mod:`dqskin.kernels.dqmath`."""

import numpy as np

__all__ = ["hat", "nonzero_norm2", "polar", "unit_or_x", "vee"]


def hat(w):
    """(..., 3) → (..., 3, 3) cross-product matrices ``[w]×`` ([MS] eq. 21)."""
    z = np.zeros_like(w[..., 0])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1),
                     np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def vee(k):
    """Axial vector of the skew-symmetric part of (..., 3, 3) ``k``."""
    return 0.5 * np.stack([k[..., 2, 1] - k[..., 1, 2], k[..., 0, 2] - k[..., 2, 0],
                           k[..., 1, 0] - k[..., 0, 1]], -1)



def polar(a):
    """Polar split ``a = R·S`` of (..., 3, 3) float64: ``R`` proper rotation, ``S`` symmetric.

    As the skinning and FK kernels (``GfMatrix4d::Factor``): ``R = U·Vᵀ`` from the SVD, negated
    when ``det a < 0`` (a reflection then lives in ``S``).
    """
    u, _, vt = np.linalg.svd(a)
    r = u @ vt
    r = np.where((np.linalg.det(r) < 0)[..., None, None], -r, r)
    return r, np.swapaxes(r, -1, -2) @ a


def nonzero_norm2(q, name):
    """Squared norm of ``q`` (shape ``(...)``); raise ``ValueError`` if any is zero."""
    n2 = np.sum(q * q, axis=-1)
    if np.any(n2 == 0):
        raise ValueError(f"{name} has a zero-norm quaternion, which has no inverse or direction")
    return n2


def unit_or_x(v):
    """Normalize 3-vectors ``v`` (..., 3); zero vectors become the x axis ``(1, 0, 0)``."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    x_axis = np.zeros_like(v)
    x_axis[..., 0] = 1
    return np.where(n > 0, v / np.where(n > 0, n, 1), x_axis)
