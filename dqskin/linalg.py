"""Small float64 3×3 pieces shared by the NumPy kinematics: cross-product matrices and the polar
split. Their float32 device counterparts are in :mod:`dqskin.kernels.dqmath`."""

import numpy as np

__all__ = ["hat", "polar", "vee"]


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
