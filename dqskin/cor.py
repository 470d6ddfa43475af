"""Optimized centers of rotation (Le & Hodgins, "Real-time Skeletal Skinning with Optimized Centers
of Rotation", ACM TOG 35(4), SIGGRAPH 2016), precomputed once per mesh and cached on disk.

Each vertex ``v`` gets a center ``p*ᵥ``: the average of the triangle centroids ``cₜ``, weighted by
area ``aₜ`` times the similarity ``s(wᵥ, wₜ)`` of the vertex's skinning weights to the triangle's
(the mean of its corners'), ``σ`` = :data:`dqskin.options.SIGMA` (the paper's value); see
:mod:`dqskin.kernels.cor` for the formula. ``method="cor"`` then skins ``v`` by the rotation of the
normalized, sign-aligned quaternion blend ``R`` and the LBS image of its center:
``v' = R·(v − p*) + Σ wⱼ·Aⱼ·[p*, 1]``.

Acceleration, exact first: the similarity is a sum of one term per joint pair that
both weight vectors share, so triangles are listed per joint pair, entries of one pair with equal
weights are merged (area and moment summed), triangles weighting fewer than two joints drop out,
and vertices with equal weight vectors (which have equal centers) are computed once. The cost is
the number of (vertex weight vector, pair, triangle entry) triples, not vertices × triangles.
Painted weights are rarely equal, though: above :data:`AUTO_TERMS` triples the weights are
clustered on a grid (``cluster``), which bounds the entries per pair (an approximation: a center
moves by up to about the grid step times the weights' falloff width, see
:func:`rotation_centers`; logged at INFO level on the ``dqskin.cor`` logger when it happens).

Optional refinement (``subdivide``, the paper's ε = 0.1): triangles are split 1→4 at their edge
midpoints, weights interpolated, until the weights at the two ends of every edge are within ε, so
the sum approximates the integral over the surface better where weights change fast.

A vertex no triangle is similar to (one-hot weights, or no face sharing two of its joints) has no
center (NaN); ``method="cor"`` skins it as DQS -- for one-hot weights both are the joint's own
rigid motion.

Cache: ``$DQSKIN_CACHE_DIR`` (default ``$XDG_CACHE_HOME/dqskin``, else ``~/.cache/dqskin``),
``cor/<sha256>.npz`` (:mod:`dqskin.cache`), keyed by the points (bind space, float64), faces,
influences, σ, the subdivision, the clustering and :data:`ALGORITHM_VERSION`; any change to
one of them is a different file.
Files are written atomically; an unreadable one is recomputed; a cache that cannot be written is
skipped.
"""

import hashlib
import logging

import numpy as np
import numpy.typing as npt
import warp as wp

from . import cache as _cache
from ._warp import Device, resolve_device
from .errors import InputError
from .influences import check_influences
from .kernels import cor as KC
from .options import SIGMA
from .shapes import as_real

__all__ = ["ALGORITHM_VERSION", "check_faces", "rotation_centers"]

log = logging.getLogger(__name__)


CLUSTER = 1.0 / 256
"""Weight grid of ``cluster="auto"`` when it clusters (see :func:`rotation_centers`)."""

AUTO_TERMS = 50_000_000
"""``cluster="auto"`` computes exactly up to this many similarity terms, and clusters on the
:data:`CLUSTER` grid above it."""

ALGORITHM_VERSION = 2
"""Part of the cache key: bump when the computed centers change."""


def check_faces(faces: npt.ArrayLike, vertex_count: int) -> np.ndarray:
    """(T, 3) int64 triangles; ValueError naming ``faces`` for a bad shape, type or index."""
    f = as_real("faces", faces)
    if f.size == 0:
        return np.zeros((0, 3), np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"faces: expected (T, 3) integer triangles, got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= vertex_count:
        raise InputError(f"faces: vertex index out of range for {vertex_count} points")
    return f.astype(np.int64)


def _cache_key(points, faces, idx, wts, sigma, subdivide, cluster):
    h = hashlib.sha256(f"dqskin-cor-v{ALGORITHM_VERSION}:{float(sigma)!r}:{subdivide!r}:"
                       f"{cluster!r}:{AUTO_TERMS}:{CLUSTER!r}:".encode())
    for a in (points.astype("<f8"), faces.astype("<i8"), idx.astype("<i8"), wts.astype("<f4")):
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _sparse_rows(rows, cols, vals, row_count, col_count):
    """Sum duplicates and drop zeros: (row, col, value) sorted by (row, col)."""
    keep = vals > 0
    key = rows[keep] * col_count + cols[keep]
    uniq, inv = np.unique(key, return_inverse=True)
    sums = np.bincount(inv, weights=vals[keep], minlength=uniq.size)
    nz = sums > 0
    uniq, sums = uniq[nz], sums[nz]
    return uniq // col_count, uniq % col_count, sums


def _pairs(rows, cols, vals, row_count):
    """Every pair ``a < b`` of entries within a row (entries sorted by (row, col)): arrays of
    (row, col_a, col_b, val_a, val_b)."""
    counts = np.bincount(rows, minlength=row_count)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out: list[list[np.ndarray]] = [[] for _ in range(5)]
    m = int(counts.max()) if counts.size else 0
    for a in range(m):
        for b in range(a + 1, m):
            r = np.nonzero(counts > b)[0]
            ia, ib = start[r] + a, start[r] + b
            for lst, x in zip(out, (r, cols[ia], cols[ib], vals[ia], vals[ib])):
                lst.append(x)
    empty = (np.zeros(0, np.int64),) * 3 + (np.zeros(0),) * 2
    return tuple(np.concatenate(x) if x else e for x, e in zip(out, empty))


def _weight_vectors(idx, wts, J, cluster):
    """Distinct vertex weight vectors: ``(uniq (U, 2m) [joints..., weights...] with -1 padding,
    inverse (V,), m)``, each vector's joints ascending. With ``cluster``, vectors whose weights
    round to the same multiples of it are one, at their mean weights."""
    V, K = idx.shape
    vr, vc, vw = _sparse_rows(np.repeat(np.arange(V), K), idx.reshape(-1),
                              wts.reshape(-1).astype(np.float64), V, J)
    counts = np.bincount(vr, minlength=V)
    m = int(counts.max()) if counts.size else 0
    slot = np.arange(vr.size) - np.concatenate([[0], np.cumsum(counts)[:-1]])[vr]
    dense = np.full((V, 2 * max(m, 1)), -1.0)
    dense[vr, slot] = vc
    dense[vr, m + slot] = vw
    if cluster is None:
        uniq, inverse = np.unique(dense, axis=0, return_inverse=True)
        return uniq, inverse.reshape(-1), m
    key = dense.copy()
    key[:, m:] = np.round(dense[:, m:] / cluster)
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    size = np.bincount(inverse, minlength=len(uniq))
    for c in range(m, dense.shape[1]):
        uniq[:, c] = np.bincount(inverse, weights=dense[:, c], minlength=len(uniq)) / size
    return uniq, inverse, m


def _corner_weights(faces, idx, wts, J):
    """Each triangle's joints ``(T, L)`` (-1 padded) and its corners' weights on them
    ``(T, 3, L)``."""
    T, K = faces.shape[0], idx.shape[1]
    t = np.repeat(np.arange(T), 3 * K)
    corner = np.tile(np.repeat(np.arange(3), K), T)
    j, w = idx[faces].reshape(-1), wts[faces].reshape(-1).astype(np.float64)
    keep = w > 0
    t, corner, j, w = t[keep], corner[keep], j[keep], w[keep]
    keys, first = np.unique(t * J + j, return_index=True)
    kt = keys // J
    counts = np.bincount(kt, minlength=T)
    slot = np.arange(keys.size) - np.concatenate([[0], np.cumsum(counts)[:-1]])[kt]
    L = max(int(counts.max()) if counts.size else 0, 1)
    joints = np.full((T, L), -1, np.int64)
    joints[kt, slot] = keys % J
    cw = np.zeros((T, 3, L))
    np.add.at(cw, (t, corner, slot[np.searchsorted(keys, t * J + j)]), w)
    return joints, cw


def _subdivide(tri, cw, eps, max_levels=8):
    """Split triangles ``tri`` (T, 3, 3) 1→4 at their edge midpoints (weights ``cw`` (T, 3, L)
    interpolated) until the weights at the two ends of every edge are within ``eps`` (Euclidean
    distance); returns ``(pieces (T', 3, 3), their weights (T', 3, L), parent triangle (T',))``."""
    parent = np.arange(tri.shape[0])
    out = []
    for level in range(max_levels + 1):
        gap = np.max(np.stack([np.linalg.norm(cw[:, a] - cw[:, b], axis=-1)
                               for a, b in ((0, 1), (1, 2), (2, 0))]), axis=0, initial=0.0)
        fine = gap <= eps if level < max_levels else np.ones(len(gap), bool)
        out.append((tri[fine], cw[fine], parent[fine]))
        tri, cw, parent = tri[~fine], cw[~fine], parent[~fine]
        if not len(tri):
            break
        mp = [(tri[:, a] + tri[:, b]) / 2 for a, b in ((0, 1), (1, 2), (2, 0))]
        mw = [(cw[:, a] + cw[:, b]) / 2 for a, b in ((0, 1), (1, 2), (2, 0))]
        tri = np.concatenate([np.stack(c, 1) for c in ((tri[:, 0], mp[0], mp[2]),
                                                        (mp[0], tri[:, 1], mp[1]),
                                                        (mp[2], mp[1], tri[:, 2]),
                                                        (mp[0], mp[1], mp[2]))])
        cw = np.concatenate([np.stack(c, 1) for c in ((cw[:, 0], mw[0], mw[2]),
                                                       (mw[0], cw[:, 1], mw[1]),
                                                       (mw[2], mw[1], cw[:, 2]),
                                                       (mw[0], mw[1], mw[2]))])
        parent = np.tile(parent, 4)
    return tuple(np.concatenate(x) for x in zip(*out))


def _pair_entries(points, faces, idx, wts, J, subdivide, cluster):
    """Triangles as joint-pair entries, merged: ``(keys (P,) j·J + k, starts (P,), ends (P,),
    weights (E, 2), areas (E,), moments (E, 3))``, entries of key ``keys[i]`` at
    ``starts[i]:ends[i]``. Entries of one pair merge when their two weights are equal, or with
    ``cluster`` when they round to the same multiples of it (at their area-weighted mean)."""
    joints, cw = _corner_weights(faces, idx, wts, J)
    tri, parent = points[faces], np.arange(faces.shape[0])
    if subdivide is not None:
        tri, cw, parent = _subdivide(tri, cw, subdivide)
    T = tri.shape[0]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    moment = area[:, None] * tri.mean(axis=1)
    tw = cw.mean(axis=1)
    tj = joints[parent]
    L = tw.shape[1]
    tr, tc, tw = _sparse_rows(np.repeat(np.arange(T), L), tj.reshape(-1), tw.reshape(-1), T, J)
    pt, pj, pk, pwj, pwk = _pairs(tr, tc, tw, T)
    keep = area[pt] > 0
    pt, pwj, pwk = pt[keep], pwj[keep], pwk[keep]
    pkey = pj[keep] * J + pk[keep]
    # merge entries of one pair with equal (or, clustered, nearby) weights
    bj, bk = (pwj, pwk) if cluster is None else (np.floor(pwj / cluster), np.floor(pwk / cluster))
    order = np.lexsort((bk, bj, pkey))
    pkey, pwj, pwk, bj, bk, pt = (a[order] for a in (pkey, pwj, pwk, bj, bk, pt))
    new = np.ones(pkey.size, bool)
    new[1:] = (pkey[1:] != pkey[:-1]) | (bj[1:] != bj[:-1]) | (bk[1:] != bk[:-1])
    group = np.cumsum(new) - 1
    ekey = pkey[new]
    a = area[pt]
    earea = np.bincount(group, weights=a, minlength=ekey.size)
    emom = np.stack([np.bincount(group, weights=moment[pt, i], minlength=ekey.size)
                     for i in range(3)], axis=1)
    if cluster is None:
        ew = np.stack([pwj[new], pwk[new]], 1)
    else:
        ew = np.stack([np.bincount(group, weights=a * w, minlength=ekey.size) / earea
                       for w in (pwj, pwk)], 1)
    keys, starts = np.unique(ekey, return_index=True)
    ends = np.append(starts[1:], ekey.size)
    return keys, starts, ends, ew, earea, emom


def _plan(points, faces, idx, wts, subdivide, cluster):
    """Everything the center kernel reads (host arrays), its cost in similarity terms, and how
    to map its U results back to the V vertices."""
    J = int(idx.max()) + 1 if idx.size else 1
    uniq, inverse, m = _weight_vectors(idx, wts, J, cluster)
    U = uniq.shape[0]
    keys, starts, ends, ew, earea, emom = _pair_entries(points, faces, idx, wts, J, subdivide,
                                                        cluster)
    # rows: (distinct weight vector, joint pair it has and some triangle shares)
    ur = np.repeat(np.arange(U), m)
    ok = uniq[:, :m].reshape(-1) >= 0 if m else np.zeros(0, bool)
    ur, uc = ur[ok], uniq[:, :m].reshape(-1)[ok].astype(np.int64)
    uw = uniq[:, m:].reshape(-1)[ok] if m else np.zeros(0)
    rr, rj, rk, rwj, rwk = _pairs(ur, uc, uw, U)
    pos = np.searchsorted(keys, rj * J + rk)
    pos = np.minimum(pos, max(keys.size - 1, 0))
    hit = (keys.size > 0) & (keys[pos] == rj * J + rk) if keys.size else np.zeros(rr.size, bool)
    # rows grouped by weight vector, the vectors in a fixed shuffled order: the launch splits them
    # into equal-count chunks per core, and similar (equally costly) vectors sort together
    shuffle = np.random.default_rng(0).permutation(U)
    rank = np.empty(U, np.int64)
    rank[shuffle] = np.arange(U)
    o = np.argsort(rank[rr[hit]], kind="stable")
    rr, pos, rwj, rwk = rank[rr[hit][o]], pos[hit][o], rwj[hit][o], rwk[hit][o]
    spans = np.stack([starts[pos], ends[pos]], 1)
    plan = dict(row_offsets=np.concatenate([[0], np.cumsum(np.bincount(rr, minlength=U))]),
                row_entries=spans, row_weights=np.stack([rwj, rwk], 1), entry_weights=ew,
                entry_areas=earea, entry_moments=emom)
    return plan, int(np.sum(spans[:, 1] - spans[:, 0])), rank[inverse]


def _compute(points, faces, idx, wts, sigma, subdivide, cluster, device):
    plan, terms, back = _plan(points, faces, idx, wts, subdivide,
                              None if cluster == "auto" else cluster)
    if cluster == "auto" and terms > AUTO_TERMS:
        exact_terms = terms
        plan, terms, back = _plan(points, faces, idx, wts, subdivide, CLUSTER)
        log.info("centers of rotation: %d points, %d exact similarity terms > AUTO_TERMS = %d: "
                 "weights clustered on a 1/%g grid (%d terms; centers approximate, pass "
                 "cluster=None for exact ones)", len(points), exact_terms, AUTO_TERMS,
                 1 / CLUSTER, terms)
    else:
        log.debug("centers of rotation: %d points, %d similarity terms, cluster=%r",
                  len(points), terms, cluster)
    types = dict(row_offsets=wp.int32, row_entries=wp.vec2i, row_weights=wp.vec2d,
                 entry_weights=wp.vec2d, entry_areas=wp.float64, entry_moments=wp.vec3d)
    arrays: dict[str, wp.array] = {
        k: wp.array(np.asarray(v, dtype=np.int32 if t in (wp.int32, wp.vec2i) else np.float64),
                    dtype=t, device=device)
        for (k, v), t in zip(plan.items(), types.values())}
    out = wp.empty(len(plan["row_offsets"]) - 1, dtype=wp.vec4d, device=device)
    KC.centers(sigma=sigma, out=out, device=device, **arrays)
    c = out.numpy()
    return np.where(c[:, 3:] > 0, c[:, :3], np.nan)[back]


def _positive_or_none(name, value, also=""):
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"{name}: expected a positive number{also} or None, got {value!r}")
    return v


def rotation_centers(points: npt.ArrayLike, faces: npt.ArrayLike, joint_indices: npt.ArrayLike,
                     joint_weights: npt.ArrayLike, *, sigma: float = SIGMA,
                     subdivide: float | None = None, cluster: float | str | None = "auto",
                     cache: bool = True, device: Device = None) -> np.ndarray:
    """Optimized centers of rotation of a mesh's vertices (see the module docstring).

    Parameters
    ----------
    points : (V, 3) float
        Rest points, in the space the centers are wanted in (the skinner passes bind space).
    faces : (T, 3) int
        Triangles.
    joint_indices, joint_weights : (V, K) int, (V, K) float
        Influences (as :class:`dqskin.Skinner`); repeated joints of a vertex are summed.
    sigma : float
        Similarity width, :data:`dqskin.options.SIGMA` by default.
    subdivide : float, optional
        Refine the integral as the paper does: split triangles 1→4 at their edge midpoints (weights
        interpolated) until the weights at the ends of every edge are within this Euclidean
        distance (the paper's 0.1), at most 8 times. None: one term per input triangle.
    cluster : float, "auto" or None
        Weight grid of the clustering: a joint pair's triangle entries whose two weights fall in
        one cell merge (at their area-weighted mean weights), and vertices whose weights round to
        the same multiples share one center (at their mean weights). None: exact. "auto"
        (default): exact up to :data:`AUTO_TERMS` similarity terms, else the :data:`CLUSTER`
        grid (1/256), logged at INFO level. The error scales with the grid step ``g`` and the
        weights' falloff width ``ℓ`` (1 / the steepest weight gradient: the distance over which
        a weight would change by 1): a center moves by up to about ``g·ℓ``, a skinned point by
        its center's error times ``|Σ wⱼ·Lⱼ − R|`` (less); sharp falloffs barely move, smooth
        ones over a whole limb move the most.
        ``tools/bench_cor.py --exact`` prints both errors.
    cache : bool
        Read and write the on-disk cache (:func:`dqskin.cache.cache_dir`).
    device : str, optional
        Warp device of the computation.

    Returns
    -------
    (V, 3) float64
        Centers, same space as ``points``; NaN rows for vertices without one.
    """
    pts = as_real("points", points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points: expected (V, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("points: NaN or infinite coordinates")
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"sigma: expected a positive number, got {sigma!r}")
    subdivide = _positive_or_none("subdivide", subdivide)
    cluster = cluster if cluster == "auto" else _positive_or_none("cluster", cluster, ', "auto"')
    idx, wts = check_influences(joint_indices, joint_weights, pts.shape[0])
    tris = check_faces(faces, pts.shape[0])
    key = _cache_key(pts, tris, idx, wts, sigma, subdivide, cluster)
    path = _cache.cache_dir() / "cor" / f"{key}.npz"
    if cache:
        hit = _cache.load(path, {"centers": ((pts.shape[0], 3), np.float64)})
        if hit is not None:
            return hit["centers"]
    res = _compute(pts, tris, idx, wts, float(sigma), subdivide, cluster,
                   resolve_device(device))
    if cache:
        _cache.store(path, centers=res)
    return res
