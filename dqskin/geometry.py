"""Small float64 NumPy geometry of meshes and bone segments, shared by rigging checks, skeleton
embedding, automatic weights and retargeting: End Site positions, distances to segments,
generalized winding numbers, rotations that align directions.
"""

import numpy as np
import numpy.typing as npt

__all__ = ["align_rotation", "best_rotation", "end_site_points", "outside_mesh",
           "segment_distances", "winding_numbers"]


def end_site_points(bind_transforms: npt.ArrayLike, end_sites: list | None) -> np.ndarray:
    """(N, 3) float64 positions of BVH End Sites ``(joint, (3,) offset)`` (joint-local), in the
    space of the (J, 4, 4) ``bind_transforms``, in ``end_sites`` order."""
    bind = np.asarray(bind_transforms, np.float64)
    return np.asarray([(bind[j] @ np.append(np.asarray(off, np.float64), 1.0))[:3]
                       for j, off in end_sites or []], np.float64).reshape(-1, 3)


def segment_distances(points: npt.ArrayLike, heads: npt.ArrayLike, tails: npt.ArrayLike,
                      chunk: int = 4096) -> np.ndarray:
    """(N, B) float64 distances from ``points`` (N, 3) to the segments ``heads``–``tails``
    (B, 3) (a point where they coincide), in the points' unit."""
    p = np.asarray(points, np.float64)
    h, t = np.asarray(heads, np.float64), np.asarray(tails, np.float64)
    d = t - h
    dd = np.maximum((d * d).sum(1), 1e-300)
    out = np.empty((p.shape[0], h.shape[0]))
    for a in range(0, p.shape[0], chunk):
        q = p[a:a + chunk, None, :] - h
        u = np.clip(np.einsum("nbk,bk->nb", q, d) / dd, 0.0, 1.0)
        out[a:a + chunk] = np.linalg.norm(q - u[..., None] * d, axis=2)
    return out


def winding_numbers(queries: npt.ArrayLike, points: npt.ArrayLike, faces: npt.ArrayLike,
                    chunk: int = 64) -> np.ndarray:
    """(Q,) float64 generalized winding numbers of the triangle mesh at ``queries`` (Q, 3)
    (Jacobson et al. 2013: the summed signed solid angles over 4π): about 1 inside a closed,
    outward-facing surface, 0 outside, in between near holes."""
    q = np.asarray(queries, np.float64).reshape(-1, 3)
    P = np.asarray(points, np.float64)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    A, B, C = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    out = np.zeros(q.shape[0])
    for s in range(0, q.shape[0], chunk):
        a, b, c = A - q[s:s + chunk, None], B - q[s:s + chunk, None], C - q[s:s + chunk, None]
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("qtk,qtk->qt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("qtk,qtk->qt", a, b) * lc
               + np.einsum("qtk,qtk->qt", b, c) * la + np.einsum("qtk,qtk->qt", c, a) * lb)
        out[s:s + chunk] = 2.0 * np.arctan2(det, den).sum(1) / (4.0 * np.pi)
    return out


def outside_mesh(queries: npt.ArrayLike, points: npt.ArrayLike, faces: npt.ArrayLike
                 ) -> np.ndarray:
    """(Q,) bool: which ``queries`` (Q, 3) lie outside the triangle mesh (generalized winding
    number below ½, :func:`winding_numbers`)."""
    return winding_numbers(queries, points, faces) < 0.5


def align_rotation(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """(3, 3) float64 the smallest rotation taking direction ``a`` (3,) onto direction ``b``
    (identity when either is zero; a half turn about an axis normal to ``a`` when opposite)."""
    u, w = np.asarray(a, np.float64), np.asarray(b, np.float64)
    na, nb = np.linalg.norm(u), np.linalg.norm(w)
    if na < 1e-300 or nb < 1e-300:
        return np.eye(3)
    u, w = u / na, w / nb
    v, c = np.cross(u, w), float(u @ w)
    if c < -1.0 + 1e-12:
        axis = np.cross(u, np.array([1.0, 0.0, 0.0]))
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(u, np.array([0.0, 1.0, 0.0]))
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def best_rotation(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """(3, 3) float64 the rotation ``R`` minimizing ``Σ |R·aᵢ − bᵢ|²`` over the rows of ``a`` and
    ``b`` (N, 3) (Kabsch, no reflection); :func:`align_rotation` for one row."""
    a, b = np.asarray(a, np.float64).reshape(-1, 3), np.asarray(b, np.float64).reshape(-1, 3)
    if a.shape[0] == 1:
        return align_rotation(a[0], b[0])
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt
