"""dqskin.linalg.polar against SciPy's polar decomposition (independent float64 code)."""

import numpy as np
import pytest
from scipy.linalg import polar as scipy_polar
from scipy.spatial.transform import Rotation

from dqskin import linalg


def scipy_rotation(a):
    """The proper rotation of ``a = R·S`` as the FK kernels define it: SciPy's orthogonal factor,
    negated when it is a reflection."""
    out = np.empty_like(a)
    for i, m in enumerate(a.reshape(-1, 3, 3)):
        u, _ = scipy_polar(m)
        out.reshape(-1, 3, 3)[i] = -u if np.linalg.det(u) < 0 else u
    return out


def rotations(rng, n):
    return Rotation.random(n, random_state=rng).as_matrix()


def perturbed(r, size, rng):
    """``r`` times ``I + E``, ``E`` symmetric with entries up to ``size``: ``|aᵀa − I|`` about
    ``2·size``."""
    e = rng.uniform(-size, size, r.shape)
    return r @ (np.eye(3) + 0.5 * (e + np.swapaxes(e, -1, -2)))


@pytest.mark.parametrize("case", ["rotation", "float32 keys", "near threshold", "past threshold",
                                  "scaled", "reflected", "mixed"])
def test_polar_matches_scipy(case):
    rng = np.random.default_rng(7)
    r = rotations(rng, 60)
    a = {"rotation": r,
         "float32 keys": r.astype(np.float32).astype(np.float64),
         "near threshold": perturbed(r, 4e-4, rng),
         "past threshold": perturbed(r, 2e-3, rng),
         "scaled": r * rng.uniform(0.01, 100, (60, 1, 3)),
         "reflected": -r,
         "mixed": np.concatenate([r[:20], -r[20:40] * 3, perturbed(r[40:], 1e-6, rng)])}[case]
    a = a.reshape(4, 15, 3, 3)  # batch shape kept
    rot, s = linalg.polar(a)
    assert rot.shape == s.shape == a.shape
    np.testing.assert_allclose(rot, scipy_rotation(a), atol=1e-13)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-13)
    np.testing.assert_allclose(rot @ s, a, atol=1e-12 * np.abs(a).max())
    np.testing.assert_allclose(s, np.swapaxes(s, -1, -2), atol=1e-12 * np.abs(a).max())


def test_near_rotations_skip_the_svd(monkeypatch):
    """Animation keys (float32 quaternions: within 1e-5 of a rotation) take the polar
    iteration, not the SVD; a scaled matrix still takes the SVD."""
    rng = np.random.default_rng(3)
    keys = rotations(rng, 50).astype(np.float32).astype(np.float64)
    calls = []
    svd = np.linalg.svd
    monkeypatch.setattr(np.linalg, "svd",
                        lambda m, *a, **k: calls.append(len(m)) or svd(m, *a, **k))
    linalg.polar(keys)
    assert calls == []
    linalg.polar(np.concatenate([keys, 2 * keys[:3]]))
    assert calls == [3]


def test_singular_and_degenerate_matrices_take_the_svd():
    rng = np.random.default_rng(5)
    r = rotations(rng, 3)
    a = np.stack([r[0] @ np.diag([1.0, 1.0, 0.0]), np.zeros((3, 3)), r[2]])
    rot, s = linalg.polar(a)
    np.testing.assert_allclose(rot[2], r[2], atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(rot[:2]), 1.0, atol=1e-12)
    np.testing.assert_allclose(rot @ s, a, atol=1e-12)


@pytest.mark.parametrize("case", ["rotation", "float32 chain", "near threshold", "past threshold",
                                  "scaled", "reflected"])
def test_kernel_polar_rotation_matches_scipy(case):
    """The kernels' float32 ``polar_rotation`` (identity, polar iteration or SVD by the input)
    against SciPy's float64 polar decomposition of the same float32 matrices."""
    import warp as wp

    from dqskin.kernels import dqmath

    @wp.kernel(module="unique")
    def polar_kernel(a: wp.array(dtype=wp.mat33), out: wp.array(dtype=wp.mat33)):
        i = wp.tid()
        out[i] = dqmath.polar_rotation(a[i])

    rng = np.random.default_rng(11)
    r = rotations(rng, 200)
    chain = r.copy()
    for _ in range(8):  # products of float32 rotations: off a rotation by float32 rounding
        chain = (chain.astype(np.float32) @ rotations(rng, 200).astype(np.float32))
    a = {"rotation": r, "float32 chain": chain,
         "near threshold": perturbed(r, 4e-4, rng),
         "past threshold": perturbed(r, 2e-3, rng),
         "scaled": r * rng.uniform(0.01, 100, (200, 1, 3)),
         "reflected": -r}[case].astype(np.float32)
    wa = wp.array(a, dtype=wp.mat33, device="cpu")
    out = wp.empty(len(a), dtype=wp.mat33, device="cpu")
    wp.launch(polar_kernel, dim=len(a), inputs=[wa, out], device="cpu")
    got = out.numpy().astype(np.float64)
    tol = 5e-6 if case in ("past threshold", "scaled", "reflected") else 1e-6  # SVD: float32 svd3
    np.testing.assert_allclose(got, scipy_rotation(a.astype(np.float64)), atol=tol)
    np.testing.assert_allclose(np.linalg.det(got), 1.0, atol=tol)
