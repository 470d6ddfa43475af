"""Automatic skinning weights: bone heat (Baran & Popović 2007), what Blender's "With Automatic
Weights" computes.

The weight of joint ``j`` over the surface is the equilibrium of heat diffusing from the bones:

    (L + M·H) w_j = M·H p_j

with ``L`` the (positive semi-definite) cotangent Laplacian and ``M`` the lumped vertex areas of the
intrinsic-Delaunay "robust Laplacian" (Sharp & Crane 2020, the ``robust-laplacian`` package:
well-posed on non-manifold and badly shaped meshes), ``H`` diagonal with
``H_i = n_i / d_i²`` where ``d_i`` is the distance from vertex ``i`` to its nearest bone segment
and ``n_i`` the number of bones that near (within ``1 + 10⁻⁴``) and visible from it, and
``p_j[i] = 1/n_i`` for those bones of joint ``j``. A vertex whose nearest bone is hidden behind
the surface gets ``H_i = 0``: its weights come from diffusion alone. ``M·H`` is scale-free (areas
grow as the square of the unit, ``H`` shrinks by it), so the weights do not depend on the length
unit. The sparse matrix is factorized once (SuperLU) and every joint's right-hand side solved
together. Distances and visibility rays (a ``wp.Mesh`` BVH) run in a Warp kernel
(:mod:`dqskin.kernels.bone_heat`).

Results are sparse (at most ``max_influences`` per vertex, the largest kept), non-negative and a
partition of unity. Coincident vertices (split at UV or normal seams) are welded first, so heat
diffuses across seams; they get equal weights. Parts of the mesh that no visible bone heats (a
separate eye, a closed accessory) and vertices outside every triangle take the nearest bone
rigidly.

Bones: :func:`bone_segments` turns a skeleton's bind pose into segments, each owned by a joint:
one from every joint to each child not at the same place ("bones pointed at their children"), and
for a leaf one to its BVH End Site when known, else pointed into the region of the mesh it owns
(:func:`shape_leaves`: a head's skull and snout, a hand, a foot), or, without a mesh, along its
parent's direction (half that bone's length).

Cache: :func:`automatic_weights` stores results as ``.npz`` files (:mod:`dqskin.cache`) under
:func:`dqskin.cache.cache_dir` (``$DQSKIN_CACHE_DIR``, else ``$XDG_CACHE_HOME/dqskin``, else
``~/.cache/dqskin``), in ``weights/``, named by a SHA-256 of everything the result depends on:
the points (in skeleton space) and triangles, the bone segments and their joints, the joint
count, ``max_influences``, the visibility switch, and :data:`ALGORITHM_VERSION`. Any change of
those is a different file (nothing is overwritten or invalidated in place); an entry that cannot
be read or does not fit (empty, truncated, other shapes or dtypes, indices out of range) is
computed again and replaced; delete the folder to reclaim space.

References
----------
I. Baran and J. Popović, "Automatic Rigging and Animation of 3D Characters", SIGGRAPH 2007.
N. Sharp and K. Crane, "A Laplacian for Nonmanifold Triangle Meshes", SGP 2020.
"""

import hashlib

import numpy as np
import numpy.typing as npt
import warp as wp

from . import cache as _cache
from ._warp import Device, resolve_device
from .errors import InputError, Param
from .geometry import end_site_points, segment_distances
from .influences import check_influences, weight_order
from .kernels import bone_heat as BH
from .skeleton import Skeleton

__all__ = ["ALGORITHM_VERSION", "automatic_weights", "bone_heat_weights", "bone_segments",
           "shape_leaves", "sparsify"]

ALGORITHM_VERSION = 3
"""Bumped whenever the weights this module computes change; part of the cache key."""

_LEAF_ITERATIONS = 2  # leaf bones re-pointed at the region they own, this many times
_LEAF_PERCENTILE = 85  # ... as far as this percentile of the region along their direction
_NEAR = 1.0e-4  # bones within (1 + _NEAR) of the nearest distance share the heat (as Blender)


def bone_segments(skeleton: Skeleton, *, end_sites: list | None = None,
                  leaf_fraction: float = 0.5, joints: npt.ArrayLike | None = None,
                  points: npt.ArrayLike | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bone segments of a skeleton's bind pose, in skeleton space: from each joint to each of
    its children (through children at the joint's own place, to theirs), else to its End Sites,
    else along its parent bone.

    Parameters
    ----------
    skeleton : dqskin.Skeleton
    end_sites : list of (joint, (3,) float), optional
        Leaf tips in the joint's local frame (BVH End Sites, :attr:`BvhMotion.end_sites`).
    leaf_fraction : float
        A leaf without an End Site extends along its parent bone's direction by this fraction of
        that bone's length.
    joints : sequence of int, optional
        The joints that deform (own bones); all by default. A glTF skeleton also holds the
        skin's ancestors (an "Armature" node above the hips), which should not take weights.
    points : (V, 3) float, optional
        The mesh's rest points (skeleton space). When given, a leaf without an End Site points
        into the region of the mesh it owns instead of along its parent (:func:`shape_leaves`).

    Returns
    -------
    heads, tails : (B, 3) float64
        Segment ends; ``head == tail`` for a joint with no extent (a lone root).
    joints : (B,) int32
        The joint that owns each segment; every deforming joint owns at least one.
    """
    bind = skeleton.bind_transforms
    pos = bind[:, :3, 3]
    J = skeleton.joint_count
    scale = max(float(np.ptp(pos, axis=0).max()), 1e-12)
    tiny = 1e-6 * scale
    heads: list[np.ndarray] = []
    tails: list[np.ndarray] = []
    owner: list[int] = []
    guessed: list[int] = []  # leaf segments along their parent (no End Site)
    tips: dict[int, list[np.ndarray]] = {}
    for (j, _), x in zip(end_sites or [], end_site_points(bind, end_sites)):
        tips.setdefault(int(j), []).append(x)
    deforming = range(J) if joints is None else sorted({int(j) for j in np.ravel(joints)})
    if not len(deforming) or deforming[0] < 0 or deforming[-1] >= J:
        raise InputError(f"joints: expected indices of the {J} joints, got {list(deforming)}")
    kids = [np.nonzero(skeleton.parents == j)[0] for j in range(J)]

    def reach(j, at):
        """Where the bone of a joint at ``at`` points: its children, and through children at
        the same place (a CMU "lhand" at its wrist) their children and End Sites."""
        out = []
        for c in kids[j]:
            if np.linalg.norm(pos[c] - at) > tiny:
                out.append(pos[c])
            else:
                out += reach(c, at) or [t for t in tips.get(int(c), [])
                                        if np.linalg.norm(t - at) > tiny]
        return out

    for j in deforming:
        ends = reach(j, pos[j])
        if not ends:
            ends = [t for t in tips.get(j, []) if np.linalg.norm(t - pos[j]) > tiny]
        if not ends:
            p = skeleton.parents[j]
            while p >= 0 and np.linalg.norm(pos[j] - pos[p]) <= tiny:
                p = skeleton.parents[p]
            ends = [pos[j] + leaf_fraction * (pos[j] - pos[p])] if p >= 0 else [pos[j]]
            if p >= 0:
                guessed.append(len(heads))
        for e in ends:
            heads.append(pos[j])
            tails.append(e)
            owner.append(j)
    h, t = np.asarray(heads), np.asarray(tails)
    if points is not None and guessed:
        t = shape_leaves(points, h, t, guessed)
    return h, t, np.asarray(owner, np.int32)


def shape_leaves(points: npt.ArrayLike, heads: npt.ArrayLike, tails: npt.ArrayLike,
                 leaves: npt.ArrayLike, *, iterations: int = _LEAF_ITERATIONS) -> np.ndarray:
    """Tails of leaf bones pointed into the mesh region each owns (a head's skull and snout, a
    hand, a foot, a tail) instead of along its parent.

    The region of a leaf segment is the set of points nearer to it than to any other segment;
    its tail goes from the head towards the region's centroid, as far as the region's 85th
    percentile along that direction. Repeated ``iterations`` times (the regions follow the
    tails).

    Parameters
    ----------
    points : (V, 3) float
        Rest points, skeleton space.
    heads, tails : (B, 3) float
        Bone segments.
    leaves : sequence of int
        The segments to shape.

    Returns
    -------
    (B, 3) float64
        ``tails`` with the leaves' replaced (unchanged where a region is empty or lies behind
        the head).
    """
    P = np.asarray(points, np.float64)
    h = np.asarray(heads, np.float64)
    t = np.array(tails, np.float64)
    for _ in range(iterations):
        near = segment_distances(P, h, t).argmin(1)
        for b in np.ravel(leaves):
            region = P[near == b]
            if len(region) < 3:
                continue
            v = region.mean(0) - h[b]
            n = float(np.linalg.norm(v))
            if n <= 0:
                continue
            u = v / n
            reach = float(np.percentile((region - h[b]) @ u, _LEAF_PERCENTILE))
            if reach > 0:
                t[b] = h[b] + reach * u
    return t


def sparsify(weights: np.ndarray, max_influences: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Dense (V, J) weights → the ``max_influences`` largest per vertex, negatives clipped,
    renormalized to sum 1: ``(indices (V, K) int32, weights (V, K) float32)``, descending.
    A vertex whose weights are all zero keeps joint ``argmax`` with weight 1."""
    w = np.clip(np.asarray(weights, np.float64), 0.0, None)
    V, J = w.shape
    K = min(int(max_influences), J)
    if K < 1:
        raise InputError(Param("max_influences", max_influences), ": must be at least 1")
    idx = np.argpartition(-w, K - 1, axis=1)[:, :K] if K < J else np.tile(np.arange(J), (V, 1))
    wk = np.take_along_axis(w, idx, 1)
    order = weight_order(wk)  # the kernels' layout order
    idx, wk = np.take_along_axis(idx, order, 1), np.take_along_axis(wk, order, 1)
    s = wk.sum(1, keepdims=True)
    empty = s[:, 0] <= 0
    wk[empty] = 0.0
    wk[empty, 0] = 1.0
    s[empty] = 1.0
    return idx.astype(np.int32), (wk / s).astype(np.float32)


def _check_max_influences(max_influences):
    """ValueError unless ``max_influences`` is a whole number of at least 1 (checked before any
    work)."""
    if isinstance(max_influences, bool) or int(max_influences) != max_influences \
            or max_influences < 1:
        raise InputError(Param("max_influences", max_influences),
                         ": must be a whole number, at least 1")


def _heat_sources(points, faces, heads, tails, visibility, device):
    """``(min_distance (V,), nearest bone (V,), closest (V, B) bool)`` from the kernel."""
    d = resolve_device(device)
    V, B = points.shape[0], heads.shape[0]
    diag = float(np.linalg.norm(np.ptp(points, axis=0))) or 1.0
    pts: wp.array = wp.array(points.astype(np.float32), dtype=wp.vec3, device=d)
    mesh = None
    if visibility and faces.size:
        mesh = wp.Mesh(points=pts, indices=wp.array(faces.astype(np.int32).ravel(), dtype=int,
                                                    device=d))
    min_distance = wp.empty(V, dtype=float, device=d)
    nearest = wp.empty(V, dtype=int, device=d)
    closest = wp.empty((V, B), dtype=wp.int8, device=d)
    BH.heat_sources(mesh=mesh.id if mesh is not None else wp.uint64(0), points=pts,
                    heads=wp.array(heads.astype(np.float32), dtype=wp.vec3, device=d),
                    tails=wp.array(tails.astype(np.float32), dtype=wp.vec3, device=d),
                    epsilon=_NEAR, ray_offset=1e-5 * diag, check_visibility=mesh is not None,
                    min_distance=min_distance, nearest=nearest, closest=closest, device=d)
    return (min_distance.numpy().astype(np.float64), nearest.numpy(),
            closest.numpy().astype(bool))


def bone_heat_weights(points: npt.ArrayLike, faces: npt.ArrayLike, heads: npt.ArrayLike,
                      tails: npt.ArrayLike, joints: npt.ArrayLike, joint_count: int, *,
                      max_influences: int = 8, visibility: bool = True,
                      device: Device = None, timings: dict | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Bone-heat weights of a mesh (see the module docstring).

    Parameters
    ----------
    points : (V, 3) float
        Rest points, in the same space as the bones (skeleton space).
    faces : (T, 3) int
        Triangles; without any, every point takes its nearest bone rigidly.
    heads, tails : (B, 3) float
        Bone segments; ``joints`` (B,) int the joint owning each (``< joint_count``).
    max_influences : int
        Influences kept per vertex (the largest), renormalized.
    visibility : bool
        Heat only from bones visible from the vertex (Baran & Popović); False: from the
        nearest bones regardless.
    timings : dict, optional
        Filled with the seconds of each phase ("sources": distances and rays, "laplacian",
        "factorize", "solve", "sparsify") for benchmarks.

    Returns
    -------
    joint_indices : (V, K) int32
    joint_weights : (V, K) float32
        ``K = min(max_influences, joint_count)``, descending per vertex, non-negative, summing
        to 1.
    """
    import robust_laplacian
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import splu

    P = np.asarray(points, np.float64)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    heads, tails = np.asarray(heads, np.float64), np.asarray(tails, np.float64)
    joints = np.asarray(joints, np.int64)
    V, J = P.shape[0], int(joint_count)
    _check_max_influences(max_influences)
    if P.ndim != 2 or P.shape[1] != 3 or V == 0:
        raise InputError(f"points: expected (V, 3) with V > 0, got {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InputError("points: NaN or infinite coordinates")
    if F.size and (F.min() < 0 or F.max() >= V):
        raise InputError(f"faces: vertex index out of range for {V} points")
    if heads.shape != tails.shape or heads.ndim != 2 or heads.shape[0] != joints.shape[0] \
            or heads.shape[0] == 0:
        raise InputError("bones: heads, tails (B, 3) and joints (B,) must match, B > 0")
    if joints.min() < 0 or joints.max() >= J:
        raise InputError(f"bones: joint index out of range for {J} joints")
    # weld coincident vertices (UV and normal seams split them): heat diffuses across seams
    P_all = P
    P, weld = np.unique(P_all, axis=0, return_inverse=True)
    weld = weld.ravel()
    F = weld[F]
    V = P.shape[0]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    clock = _Clock(timings)
    mind, nearest, closest = _heat_sources(P, F, heads, tails, visibility, device)
    clock("sources")
    diag = float(np.linalg.norm(np.ptp(P, axis=0))) or 1.0
    dense = np.zeros((V, J))
    rigid = np.ones(V, bool)
    used = np.zeros(V, bool)
    used[F.ravel()] = True
    if F.shape[0]:
        rigid = ~used
        sub = np.nonzero(used)[0]
        remap = np.full(V, -1, np.int64)
        remap[sub] = np.arange(sub.size)
        L, M = robust_laplacian.mesh_laplacian(P[sub], remap[F])
        clock("laplacian")
        count = closest[sub].sum(1)
        d2 = np.maximum(mind[sub], 1e-4 * diag) ** 2
        H = count / d2
        # components no visible bone heats: their nearest bone, visible or not
        ncomp, label = connected_components(L, directed=False)
        heated = np.bincount(label, weights=H, minlength=ncomp) > 0
        cold = ~heated[label]
        H[cold] = 1.0 / d2[cold]
        src = np.zeros((sub.size, heads.shape[0]))
        src[~cold] = closest[sub][~cold] / np.maximum(count[~cold], 1)[:, None]
        src[np.nonzero(cold)[0], nearest[sub][cold]] = 1.0
        owners = np.unique(joints)  # only joints owning a bone get heat; the rest stay 0
        per_joint = np.zeros((sub.size, owners.size))
        np.add.at(per_joint.T, np.searchsorted(owners, joints), src.T)
        mh = M.diagonal() * H
        lu = splu((L + sp.diags(mh)).tocsc())
        clock("factorize")
        dense[np.ix_(sub, owners)] = lu.solve(mh[:, None] * per_joint)
        clock("solve")
    dense[rigid, joints[nearest[rigid]]] = 1.0
    result = sparsify(dense[weld], max_influences)
    clock("sparsify")
    return result


class _Clock:
    """``clock(name)`` records the seconds since the previous call into ``timings[name]``."""

    def __init__(self, timings):
        import time
        self._now = time.perf_counter
        self.timings, self.last = timings, self._now()

    def __call__(self, name):
        now = self._now()
        if self.timings is not None:
            self.timings[name] = self.timings.get(name, 0.0) + now - self.last
        self.last = now


def _cache_key(points, faces, heads, tails, joints, joint_count, max_influences, visibility):
    h = hashlib.sha256()
    for a in (np.ascontiguousarray(points, np.float32), np.ascontiguousarray(faces, np.int64),
              np.ascontiguousarray(heads, np.float64), np.ascontiguousarray(tails, np.float64),
              np.ascontiguousarray(joints, np.int64)):
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    h.update(f"{joint_count}/{max_influences}/{bool(visibility)}/v{ALGORITHM_VERSION}".encode())
    return h.hexdigest()


def automatic_weights(points: npt.ArrayLike, faces: npt.ArrayLike, skeleton: Skeleton, *,
                      geom_bind_transform: npt.ArrayLike | None = None,
                      end_sites: list | None = None, joints: npt.ArrayLike | None = None,
                      max_influences: int = 8, visibility: bool = True, cache: bool = True,
                      device: Device = None) -> tuple[np.ndarray, np.ndarray]:
    """Bone-heat weights binding a mesh in its rest pose to ``skeleton``'s bind pose.

    Parameters
    ----------
    points : (V, 3) float
        Rest points in mesh space.
    faces : (T, 3) int
    skeleton : dqskin.Skeleton
        Its ``bind_transforms`` (skeleton space) place the bones (:func:`bone_segments`).
    geom_bind_transform : (4, 4) float, optional
        Mesh space → skeleton space (identity by default).
    end_sites : list of (joint, (3,) float), optional
        BVH End Sites (leaf bone tips, joint-local).
    joints : sequence of int, optional
        The joints that deform (see :func:`bone_segments`); all by default.
    max_influences : int
    visibility : bool
    cache : bool
        Read and write the cache under :func:`dqskin.cache.cache_dir` (see the module
        docstring).

    Returns
    -------
    joint_indices : (V, K) int32
        Indices into ``skeleton.joint_names``.
    joint_weights : (V, K) float32
        Non-negative, summing to 1 per vertex, descending.
    """
    _check_max_influences(max_influences)
    pts = np.asarray(points, np.float64)
    g = np.eye(4) if geom_bind_transform is None else np.asarray(geom_bind_transform, np.float64)
    pts = pts @ g[:3, :3].T + g[:3, 3]
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    heads, tails, owners = bone_segments(skeleton, end_sites=end_sites, joints=joints,
                                         points=pts)
    J = skeleton.joint_count
    path = None
    if cache:
        key = _cache_key(pts, faces, heads, tails, owners, J, max_influences, visibility)
        path = _cache.cache_dir() / "weights" / f"{key}.npz"
        hit = _cached(path, len(pts), J, max_influences)
        if hit is not None:
            return hit
    result = bone_heat_weights(pts, faces, heads, tails, owners, J, max_influences=max_influences,
                               visibility=visibility, device=device)
    if path is not None:
        _cache.store(path, joint_indices=result[0], joint_weights=result[1])
    return result


def _cached(path, vertex_count, joint_count, max_influences):
    """The cached ``(indices, weights)`` at ``path`` if they are what :func:`automatic_weights`
    returns (shapes, dtypes, indices in range, weights finite, non-negative and summing to 1:
    :func:`dqskin.influences.check_influences`), else None (a damaged or foreign entry is a
    miss, computed again)."""
    K = min(int(max_influences), joint_count)
    z = _cache.load(path, {"joint_indices": ((vertex_count, K), np.int32),
                           "joint_weights": ((vertex_count, K), np.float32)})
    if z is None:
        return None
    idx, w = z["joint_indices"], z["joint_weights"]
    try:
        check_influences(idx, w, vertex_count, joint_count)
    except InputError:
        return None
    if idx.size and not np.allclose(w.sum(axis=1, dtype=np.float64), 1.0, rtol=0, atol=1e-4):
        return None
    return idx, w
