"""Skeleton embedding: a skeleton's bind pose placed inside a plain mesh, whatever the mesh's rest
pose (T, A or I), size and position.

The input skeleton (e.g. a capture's, another person's) gives the hierarchy, the names and the
bones' relative lengths; its size, pose and placement are only a starting guess. The mesh gives
the rest:

1. **Extremities.** Geodesic distances over the mesh's edge graph (its parts joined where
   they touch, and each to its nearest other part at their nearest points: a body of separate
   pieces, one per bone, joins as the bones do) from its centre (the middle of its longest shortest
   path); the mesh's
   extremities are picked by farthest-point sampling (the head, the hands, the feet of a biped),
   as many as the skeleton has groups of leaf tips (tips closer than a fifth of its height along
   the bones are one group: a hand's fingers). Each group is matched to an extremity by
   direction from the root and by side (Hungarian assignment): two limbs that branch from one
   joint (the legs from the pelvis, the arms from the chest) have their sides from the
   horizontal offset between their first joints, which a bent or crossed limb in the guess
   does not change, and go to extremities on those sides of the root (by their offsets along
   that side, up to a twentieth of the height: a foot's toes pointing forward count fully).
2. **Scale.** The skeleton is scaled so that its hip joints (the first joints, away from the
   root, of the two limbs with the lowest extremities) are level with the mesh's crotch (the
   highest point of the shortest surface path between the feet), else to the mesh's height; it
   stands on the mesh's floor, its root at the centroid of the mesh's horizontal section there.
3. **Centre lines.** A limb's centre line is the chain of centroids of the rings of geodesic
   distance from its extremity (around a leg, an arm, the neck), up to where the ring merges
   with the body (the centroid jumps; fingers and toes merging near the tip do not count).
4. **Joints.** Limbs are placed highest extremity first (the head, so the spine). A limb that
   ends in one BVH End Site is walked in from the extremity, each joint at its scaled bone
   length along the centre line, down to (not including) the limb's base (a hip, a clavicle),
   the joints between stretched to join; the others are walked out from their parents along the
   centre line (where it ends first, a joint takes its bone's share of what is left of it, with
   the bones below it to the tip); a limb's base, and joints far from any centre line, keep
   their scaled offsets from their parents.
5. **Blobs.** When more than a third of the deforming joints end up outside the mesh (winding
   number below ½: a cartoon whose limbs are short stubs on a round body, its leaf joints at
   the stubs' bases), the guess is instead moved and scaled whole (its pose kept): the first
   joints of its two limbs whose tips lie farthest apart horizontally go to the bases of the
   mesh's two protrusions farthest out on those sides, found by sections normal to that side
   (:mod:`dqskin.protrusion_fit`); that fit is kept when fewer of its joints are outside.
6. **Overrides.** ``joints`` (name → position) replace any joint's position, after the others
   are placed.

The guess's pose matters for the matching and for the joints kept at their scaled offsets: a
standing figure in a T, A or I pose, or any pose within about 10° per joint of the mesh's,
is embedded; with 10–20° per joint most guesses are, some land a spine or a leg several % of
the height off (a bent spine's head direction, a bent leg's scale).

The bind rotations carry the rest-pose difference per joint: joint ``j`` of the result has the
input's bind rotation turned by the rotation ``A_j`` that takes the input's bone directions (to
its children) onto the embedded ones (:func:`dqskin.geometry.best_rotation`; a leaf takes its
parent's). A motion authored on the input skeleton drives the embedded one with world bone
directions unchanged by applying ``A_j⁻¹`` first (:mod:`dqskin.retarget`).

The mesh and the skeleton share their axes (the same up axis, ``up``); only their sizes, positions
and poses differ.
"""

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .geometry import best_rotation, end_site_points, outside_mesh
from .protrusion_fit import protrusion_fit
from .skeleton import Skeleton

__all__ = ["embed_skeleton", "embedding_errors", "skeleton_tips"]

_TIP_GROUP = 0.2  # tips closer than this share of the skeleton's height (along bones): one limb
_RING = 0.01  # level-set width of the centre lines, share of the mesh's height
_LIMB_START = 0.15  # rings merge (fingers, toes) nearer the tip than this share of the height
_NEAR_LINE = 0.05  # a joint walks along a limb's centre line from a parent this near it
_SIDE = 0.05  # an extremity this share of the height off the root's vertical is on one side


def skeleton_tips(skeleton: Skeleton, end_sites: list | None = None, *,
                  joints: npt.ArrayLike | None = None, leaf_fraction: float = 0.5
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The leaf tips of a skeleton's bind pose: each leaf's End Sites, else the leaf extended
    along its parent's bone by ``leaf_fraction`` of that bone.

    Parameters
    ----------
    skeleton : dqskin.Skeleton
    end_sites : list of (joint, (3,) float), optional
        BVH End Sites (joint-local).
    joints : sequence of int, optional
        The joints considered (the deforming ones); leaves are taken within them.

    Returns
    -------
    tips : (N, 3) float64
        Skeleton space.
    owners : (N,) int64
        The leaf joint of each tip.
    """
    bind = skeleton.bind_transforms
    pos = bind[:, :3, 3]
    J = skeleton.joint_count
    keep = np.ones(J, bool) if joints is None else np.isin(np.arange(J), np.ravel(joints))
    has_child = np.zeros(J, bool)
    for j in range(J):
        p = skeleton.parents[j]
        if p >= 0 and keep[j]:
            has_child[p] = True
    sites: dict[int, list] = {}
    for (j, _), x in zip(end_sites or [], end_site_points(bind, end_sites)):
        sites.setdefault(int(j), []).append(x)
    tips, owners = [], []
    for j in (int(k) for k in np.nonzero(keep & ~has_child)[0]):
        if sites.get(int(j)):
            for t in sites[int(j)]:
                tips.append(t)
                owners.append(j)
            continue
        p = int(skeleton.parents[j])
        while p >= 0 and np.linalg.norm(pos[p] - pos[j]) < 1e-9:
            p = int(skeleton.parents[p])
        tips.append(pos[j] + (leaf_fraction * (pos[j] - pos[p]) if p >= 0 else 0.0))
        owners.append(j)
    return np.asarray(tips, np.float64).reshape(-1, 3), np.asarray(owners, np.int64)


def _up_rotation(up):
    """(3, 3) rotation taking axis ``up`` (0, 1, 2) onto +Y (a cyclic permutation)."""
    if up not in (0, 1, 2):
        raise InputError(f"up: expected an axis 0, 1 or 2, got {up!r}")
    return np.roll(np.eye(3), 1 - up, axis=0)


class _Surface:
    """A welded mesh: points, its edge graph (edge lengths), vertex areas, one component."""

    def __init__(self, points, faces):
        import scipy.sparse as sp
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree
        P, inv = np.unique(np.asarray(points, np.float64), axis=0, return_inverse=True)
        F = inv.ravel()[np.asarray(faces, np.int64).reshape(-1, 3)]
        F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
        self.points, self.faces = P, F
        N = len(P)
        e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        w = np.linalg.norm(P[e[:, 0]] - P[e[:, 1]], axis=1)
        g = sp.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(N, N)).tocsr()
        g = g.maximum(g.T)
        # join the parts (an eye, separate limbs): points of different parts closer than a long
        # edge, and each part's nearest point to the largest part
        n, label = connected_components(g, directed=False)
        if n > 1:
            rows, cols, vals = [], [], []
            near = cKDTree(P).query_pairs(float(np.percentile(w, 90)), output_type="ndarray")
            near = near[label[near[:, 0]] != label[near[:, 1]]]
            rows += near[:, 0].tolist()
            cols += near[:, 1].tolist()
            vals += np.maximum(np.linalg.norm(P[near[:, 0]] - P[near[:, 1]], axis=1),
                               1e-12).tolist()
            extra = sp.coo_matrix((vals, (rows, cols)), shape=(N, N)).tocsr()
            g = g.maximum(extra).maximum(extra.T).tocsr()
            g = _join_nearest(g, P)
        self.graph = g
        self.long_edge = float(np.percentile(w, 90)) if len(w) else 0.0
        area = np.zeros(N)
        if len(F):
            a = 0.5 * np.linalg.norm(np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]]),
                                     axis=1)
            for k in range(3):
                np.add.at(area, F[:, k], a / 3)
        self.area = np.maximum(area, 1e-30)

    def centre(self):
        """A central vertex: the middle of the longest shortest path (between the farthest
        point from the bounding box's centre and the farthest from that): a biped's waist."""
        mid = 0.5 * (self.points.min(0) + self.points.max(0))
        d0 = self.geodesic(int(np.argmin(np.linalg.norm(self.points - mid, axis=1))))
        da = self.geodesic(int(np.argmax(np.where(np.isfinite(d0), d0, -1))))
        db = self.geodesic(int(np.argmax(np.where(np.isfinite(da), da, -1))))
        total = da + db
        on_path = total <= np.nanmin(total) * 1.02
        return int(np.argmin(np.where(on_path, np.abs(da - db), np.inf)))

    def geodesic(self, sources):
        from scipy.sparse.csgraph import dijkstra
        return dijkstra(self.graph, directed=False, indices=np.atleast_1d(sources), min_only=True)

    def ring_centroid(self, mask, seed):
        """The area-weighted centroid of the connected part of ``mask``'s vertices holding (or
        nearest to) vertex ``seed``."""
        from scipy.sparse.csgraph import breadth_first_order
        idx = np.nonzero(mask)[0]
        if idx.size == 0:
            return self.points[seed]
        sub = self.graph[idx][:, idx]
        start = int(np.argmin(np.linalg.norm(self.points[idx] - self.points[seed], axis=1)))
        order = breadth_first_order(sub, start, directed=False, return_predecessors=False)
        part = idx[order]
        return np.average(self.points[part], axis=0, weights=self.area[part])


def _join_nearest(g, P):
    """The graph ``g`` with its parts joined, each to its nearest other part (at their nearest
    points), until one part is left (Borůvka's rounds): bones' separate capsules join their
    neighbours, not whatever part is largest."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree
    N = len(P)
    while True:
        n, label = connected_components(g, directed=False)
        if n <= 1:
            return g
        rows, cols, vals = [], [], []
        for c in range(n):
            inside = label == c
            idx, rest = np.nonzero(inside)[0], np.nonzero(~inside)[0]
            d, k = cKDTree(P[rest]).query(P[idx])
            i = int(d.argmin())
            rows.append(idx[i])
            cols.append(rest[k[i]])
            vals.append(max(float(d[i]), 1e-12))
        extra = sp.coo_matrix((vals, (rows, cols)), shape=(N, N)).tocsr()
        g = g.maximum(extra).maximum(extra.T).tocsr()


def _fps(geo_from, seed_dist, count):
    """Farthest-point sampling of ``count`` vertices, starting from the distances to the seed."""
    d = seed_dist.copy()
    picks = []
    for _ in range(count):
        v = int(np.argmax(np.where(np.isfinite(d), d, -1)))
        picks.append(v)
        d = np.minimum(d, geo_from(v))
    return picks


def _tip_groups(skeleton, tips, owners, height):
    """Group tips closer than ``_TIP_GROUP · height`` along the bones; returns lists of tip
    indices."""
    pos = skeleton.bind_transforms[:, :3, 3]
    par = skeleton.parents

    def along(a, b):
        pa, pb = _chain(par, owners[a]), _chain(par, owners[b])
        common = next(j for j in pa if j in set(pb))
        length = 0.0
        for p, tip in ((pa, tips[a]), (pb, tips[b])):
            pts = [tip] + [pos[j] for j in p[:p.index(common) + 1]]
            length += float(sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
        return length

    groups: list[list[int]] = []
    for t in range(len(tips)):
        for g in groups:
            if any(along(t, u) < _TIP_GROUP * height for u in g):
                g.append(t)
                break
        else:
            groups.append([t])
    return groups


def _centre_line(surface, tip_vertex, step, stop):
    """(K, 3) centroids of the rings of geodesic distance from ``tip_vertex`` every ``step``,
    from the tip inwards, up to distance ``stop``: each ring is the connected band of vertices
    within half a step (at least one long edge) of its level, around the geodesic path."""
    d = surface.geodesic(tip_vertex)
    half = max(0.5 * step, surface.long_edge)
    H = float(np.ptp(surface.points[:, 1]))
    jump = max(4 * step, 2 * surface.long_edge)
    line = [surface.points[tip_vertex]]
    k = 1
    while k * step < stop:
        mask = np.abs(d - k * step) <= half
        if mask.any():
            seed = int(np.nonzero(mask)[0][np.argmin(np.abs(d[mask] - k * step))])
            c = surface.ring_centroid(mask, seed)
            if k * step > _LIMB_START * H and np.linalg.norm(c - line[-1]) > jump:
                break  # the ring has merged with the body: the limb ends here
            line.append(c)
        k += 1
    return np.asarray(line)


def _walk(line, start, length):
    """The point of the polyline ``line`` (ordered base → tip) at distance ``length`` from
    ``start``, found going tip-wards from the point of ``line`` nearest ``start``; the tip when
    the line ends first."""
    i0 = int(np.argmin(np.linalg.norm(line - start, axis=1)))
    for i in range(i0, len(line) - 1):
        a, b = line[i], line[i + 1]
        if np.linalg.norm(b - start) >= length:
            # solve |a + u (b - a) - start| = length for u in [0, 1]
            d, f = b - a, a - start
            A, B, C = d @ d, 2 * f @ d, f @ f - length ** 2
            disc = max(B * B - 4 * A * C, 0.0)
            u = (-B + np.sqrt(disc)) / (2 * A) if A > 0 else 0.0
            return a + np.clip(u, 0.0, 1.0) * d
    return None


def embed_skeleton(mesh: tuple[npt.ArrayLike, npt.ArrayLike], skeleton: Skeleton, *,
                   joints: Mapping[str, npt.ArrayLike] | None = None,
                   end_sites: list | None = None, deforming: npt.ArrayLike | None = None,
                   up: int = 1) -> Skeleton:
    """The skeleton with its bind pose placed inside the mesh (see the module docstring).

    Parameters
    ----------
    mesh : (points (V, 3) float, faces (T, 3) int)
        A plain triangle mesh in any rest pose, size and position; its space is the result's.
    skeleton : dqskin.Skeleton
        The joints, names and hierarchy; its bind pose is a starting guess.
    joints : mapping of str to (3,) float, optional
        Joint positions (mesh space) that override the embedding, by joint name.
    end_sites : list of (joint, (3,) float), optional
        BVH End Sites (joint-local leaf tips) of the input skeleton.
    deforming : sequence of int, optional
        The joints that own bones (all by default); the others (a glTF "Armature" node, sockets)
        keep their place relative to the root.
    up : int
        The up axis shared by the mesh and the skeleton (0, 1, 2; Y by default).

    Returns
    -------
    dqskin.Skeleton
        Same names and parents; ``bind_transforms`` (J, 4, 4) in mesh space: translations the
        embedded joints, rotations the input's turned by each joint's rest-pose difference.

    Raises
    ------
    InputError
        (a ValueError) A mesh without triangles or of zero height, an unknown joint name in
        ``joints`` or a position that is not three finite numbers.
    """
    pts = np.asarray(mesh[0], np.float64)
    faces = np.asarray(mesh[1], np.int64).reshape(-1, 3)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(faces) or not np.isfinite(pts).all():
        raise InputError("mesh: expected finite points (V, 3) and triangles (T, 3), T > 0")
    overrides = _check_overrides(joints, skeleton)
    R = _up_rotation(up)
    P = pts @ R.T
    surface = _Surface(P, faces)
    P = surface.points
    lo, hi = P.min(0), P.max(0)
    H = float(hi[1] - lo[1])
    if H <= 0:
        raise InputError("mesh: zero height along the up axis")
    J = skeleton.joint_count
    bind_in = skeleton.bind_transforms
    X_in = bind_in[:, :3, 3] @ R.T
    deform = (np.arange(J) if deforming is None
              else np.array(sorted({int(j) for j in np.ravel(deforming)})))
    is_def = np.isin(np.arange(J), deform)
    tips0, owners = skeleton_tips(skeleton, end_sites, joints=deform)
    site_tips = np.isin(owners, [int(j) for j, _ in end_sites or []])
    tips = tips0 @ R.T
    ref = np.concatenate([X_in[deform], tips])
    h_skel = float(np.ptp(ref[:, 1])) or 1.0
    root = int(deform[0])
    while skeleton.parents[root] >= 0 and is_def[skeleton.parents[root]]:
        root = int(skeleton.parents[root])
    children = [np.nonzero((skeleton.parents == j) & is_def)[0] for j in range(J)]
    groups = _tip_groups(skeleton, tips0, owners, h_skel) if len(tips) else []
    ext = _fps(surface.geodesic, surface.geodesic(surface.centre()), len(groups)) if groups else []
    s = H / h_skel
    legs = _legs(groups, tips, ext, P)
    if legs is not None:  # a biped: the crotch (top of the path between the feet) sets the scale
        (g1, v1), (g2, v2) = legs
        crotch = _crotch(surface, v1, v2)
        hips = [next((j for j in _limb_joints(skeleton, owners[groups[g]], root, children)
                      if np.linalg.norm(X_in[j] - X_in[root]) > 1e-6 * h_skel), root)
                for g in (g1, g2)]
        drop = float(np.mean(X_in[hips, 1])) - ref[:, 1].min()
        if crotch > lo[1] and drop > 0:
            s = (crotch - lo[1]) / drop  # the hip joints level with the crotch
    # scaled, standing on the floor, root at the centre of the mesh's section at its height
    X = (X_in - X_in[root]) * s
    T = (tips - X_in[root]) * s
    y_root = lo[1] + (X_in[root, 1] - ref[:, 1].min()) * s
    section = np.abs(P[:, 1] - y_root) <= max(1.5 * _RING * H, surface.long_edge)
    centre = np.array([0.5 * (lo[0] + hi[0]), y_root, 0.5 * (lo[2] + hi[2])])
    if section.any():
        seed = int(np.argmin(np.linalg.norm(P - centre, axis=1) + np.where(section, 0, np.inf)))
        c = surface.ring_centroid(section, seed)
        centre[[0, 2]] = c[[0, 2]]
    X += centre
    T += centre
    placed = np.zeros(J, bool)
    placed[root] = True
    Xr = X.copy()
    if groups:
        from scipy.optimize import linear_sum_assignment
        gdir = np.array([_unit(T[g].mean(0) - X[root]) for g in groups])
        edir = np.array([_unit(P[v] - X[root]) for v in ext])
        # and by side: a limb's (a leg's, an arm's, whatever their pose) against an
        # extremity's horizontal offset from the root (none for a head)
        side = _limb_sides(skeleton, X, [owners[g] for g in groups], root, children)
        off = np.array([_flat(P[v] - X[root], 0.0) for v in ext])
        rows, cols = linear_sum_assignment(
            -gdir @ edir.T - np.clip(side @ off.T / (_SIDE * H), -1.0, 1.0))
        order = sorted(zip(rows, cols), key=lambda rc: -T[groups[rc[0]]][:, 1].max())
        for gi, ei in order:  # the highest (a head: the spine) first
            line = _centre_line(surface, ext[ei], _RING * H, 0.75 * H)[::-1]  # base → tip
            if len(groups[gi]) == 1 and site_tips[groups[gi]].all():  # a tip on the surface
                _walk_in(skeleton, X, X_in, Xr, placed, line, tips, owners, groups[gi], root, s)
            for j in _limb_joints(skeleton, owners[groups[gi]], root, children, all_=True):
                if placed[j]:
                    continue
                p = skeleton.parents[j]
                length = s * float(np.linalg.norm(X_in[j] - X_in[p]))
                far = np.linalg.norm(line - Xr[p], axis=1).min() > max(length, _NEAR_LINE * H)
                if len(children[p]) > 1 or length < 1e-9 * H or far:
                    Xr[j] = Xr[p] + (X[j] - X[p])  # a limb's base, or off the limb: as scaled
                else:
                    x = _walk(line, Xr[p], length)
                    if x is None:  # the line ends first: the chain below shares what is left
                        rest = s * _reach_to_tip(skeleton.parents, X_in, j, tips,
                                                 owners[groups[gi]], groups[gi])
                        x = _walk_share(line, Xr[p], length / (length + rest))
                    Xr[j] = x
                placed[j] = True
    # the rest: their scaled offsets from their (placed) parents
    for j in range(J):
        if not placed[j]:
            p = skeleton.parents[j]
            Xr[j] = X[j] if p < 0 else Xr[p] + (X[j] - X[p])
    if groups:  # a blob (most joints outside): the guess fitted whole at its limbs' bases
        outside = _outside(Xr[deform], surface)
        if outside > len(deform) / 3:
            chains = [_limb_joints(skeleton, owners[g], root, children) for g in groups]
            fit = protrusion_fit(P, surface.faces, X_in, tips, groups, chains, H)
            if fit is not None and _outside(fit[deform], surface) < outside:
                Xr = fit
    out = Xr @ R  # back to the mesh's axes
    for j, x in overrides.items():
        out[j] = x
    return _with_positions(skeleton, out, deform)


def _walk_in(skeleton, X, X_in, Xr, placed, line, tips, owners, group, root, s):
    """Place the chain to a group's farthest End Site from the extremity inwards, each joint at
    its scaled bone length along the centre line, while the line lasts; the joints between the
    nearest placed ancestor and the first one walked keep their shape, stretched (a
    similarity) to join them."""
    par = skeleton.parents

    def path(j):
        return _chain(par, j, root)[::-1]

    def reach(t):
        p = path(owners[t])
        pts = [X_in[root]] + [X_in[j] for j in p] + [tips[t]]
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())

    t = max(group, key=reach)
    chain = path(owners[t])
    limb = _limb_joints(skeleton, [owners[t]], root,
                        [np.nonzero(par == j)[0] for j in range(len(par))])
    base = next((j for j in limb if np.linalg.norm(X_in[j] - X_in[par[j]]) > 0), None)
    if base is not None:  # the limb's base (a hip, a clavicle) is not walked
        chain = chain[chain.index(base) + 1:]
    back = line[::-1]  # tip → base
    cur, nxt = back[0], tips[t]
    first = None
    for j in reversed(chain):
        if placed[j]:
            break
        length = s * float(np.linalg.norm(nxt - X_in[j]))
        x = _walk(back, cur, length) if length > 0 else cur.copy()
        if x is None:
            break
        Xr[j], placed[j] = x, True
        cur, nxt, first = x, X_in[j], j
    if first is None:
        return
    # the joints between the placed ancestor and ``first``: stretched to join them
    between = []
    a = par[first]
    while a >= 0 and not placed[a]:
        between.append(a)
        a = par[a]
    if a < 0 or not between:
        return
    u, v = X[first] - X[a], Xr[first] - Xr[a]
    nu = np.linalg.norm(u)
    M = (np.linalg.norm(v) / nu if nu > 0 else 1.0) * best_rotation(u[None], v[None])
    for j in between:
        Xr[j], placed[j] = Xr[a] + M @ (X[j] - X[a]), True


def _outside(X, surface):
    """How many of the points ``X`` (N, 3) lie outside the mesh (winding number below ½)."""
    return int(outside_mesh(X, surface.points, surface.faces).sum())


def _flat(v, least=0.3):
    """The horizontal part of ``v``; zero unless longer than ``least · |v|``."""
    h = np.array([v[0], 0.0, v[2]])
    return h if np.linalg.norm(h) > least * np.linalg.norm(v) else np.zeros(3)


def _limb_sides(skeleton, X, leaves, root, children):
    """(G, 3) unit horizontal directions of the limbs' sides: for two limbs that branch from the
    same joint (the legs from the pelvis, the arms from the chest), the horizontal offset
    between their joints (their first, else their means), when mostly horizontal, whatever
    their pose; zero for the others (a neck)."""
    chains = [_limb_joints(skeleton, lv, root, children) for lv in leaves]
    branch = [skeleton.parents[c[0]] if c else -2 for c in chains]
    out = np.zeros((len(chains), 3))
    for g, b in enumerate(branch):
        pair = [h for h, c in enumerate(branch) if c == b and h != g]
        if b == -2 or len(pair) != 1:
            continue
        h = pair[0]
        first = _flat(X[chains[g][0]] - X[chains[h][0]])
        out[g] = _unit(first if first.any()
                       else _flat(X[chains[g]].mean(0) - X[chains[h]].mean(0)))
    return out


def _reach_to_tip(parents, X, j, tips, owners, group):
    """The shortest length along the bones from joint ``j`` down to a tip of ``group`` (0 when
    none lies below it)."""
    best = np.inf
    for t, o in zip(group, owners):
        length, k = float(np.linalg.norm(tips[t] - X[o])), int(o)
        while k != j and k >= 0:
            length += float(np.linalg.norm(X[k] - X[parents[k]])) if parents[k] >= 0 else 0.0
            k = int(parents[k])
        if k == j:
            best = min(best, length)
    return 0.0 if not np.isfinite(best) else best


def _walk_share(line, start, share):
    """The point ``share`` (0–1) of the way along the polyline ``line`` (base → tip) from its
    point nearest ``start`` to its tip."""
    i0 = int(np.argmin(np.linalg.norm(line - start, axis=1)))
    pts = np.concatenate([start[None], line[i0 + 1:]]) if i0 + 1 < len(line) else line[-1:]
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    if not len(seg) or seg.sum() <= 0:
        return line[-1].copy()
    at = share * seg.sum()
    k = int(np.searchsorted(np.cumsum(seg), at))
    k = min(k, len(seg) - 1)
    before = float(np.cumsum(seg)[k - 1]) if k > 0 else 0.0
    u = (at - before) / seg[k] if seg[k] > 0 else 0.0
    return pts[k] + np.clip(u, 0.0, 1.0) * (pts[k + 1] - pts[k])


def _unit(v):
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _limb_joints(skeleton, leaf_joints, root, children, all_=False):
    """The joints on the paths from ``root`` (excluded) to ``leaf_joints``, parents first; unless
    ``all_``, only those below the last joint that also leads elsewhere (the limb's branch
    point: its first joint is the limb's base)."""
    paths = [_chain(skeleton.parents, leaf, root)[::-1]
             for leaf in sorted(set(int(j) for j in leaf_joints))]
    chain: set[int] = set()
    for p in paths:
        start = 0
        if not all_:
            for i, j in enumerate(p[:-1]):
                if len(children[j]) > 1:
                    start = i + 1
        chain.update(p[start:])
    return sorted(chain)


def _chain(parents, j, stop=-1):
    """Joint ``j`` and its ancestors up to (not including) ``stop`` (-1: to the root), ``j``
    first."""
    out = []
    j = int(j)
    while j >= 0 and j != stop:
        out.append(j)
        j = int(parents[j])
    return out


def _legs(groups, tips, ext, P):
    """The two groups whose extremities are lowest, as ((group, vertex), (group, vertex)), when
    both are in the lower third of the mesh (a biped's feet), else None."""
    if len(groups) < 3:
        return None
    from scipy.optimize import linear_sum_assignment
    lo, H = P[:, 1].min(), np.ptp(P[:, 1])
    low_g = sorted(range(len(groups)), key=lambda g: tips[groups[g]][:, 1].min())[:2]
    low_v = sorted(ext, key=lambda v: P[v, 1])[:2]
    if max(P[v, 1] for v in low_v) > lo + H / 3:
        return None
    # left/right by the horizontal offsets
    a = np.array([tips[groups[g]].mean(0)[[0, 2]] for g in low_g])
    b = np.array([P[v][[0, 2]] for v in low_v])
    a, b = a - a.mean(0), b - b.mean(0)
    r, c = linear_sum_assignment(-a @ b.T)
    return tuple((low_g[i], low_v[k]) for i, k in zip(r, c))


def _crotch(surface, v1, v2):
    """The height of the highest point of the shortest surface path between two vertices."""
    from scipy.sparse.csgraph import dijkstra
    _, pred = dijkstra(surface.graph, directed=False, indices=v1, return_predecessors=True)
    path, v = [], v2
    while v >= 0:
        path.append(v)
        v = pred[v]
    return float(surface.points[path, 1].max())


def _check_overrides(joints, skeleton):
    out: dict[int, np.ndarray] = {}
    if not joints:
        return out
    index = {n: k for k, n in enumerate(skeleton.joint_names)}
    for name, x in joints.items():
        if name not in index:
            raise InputError(f"joints: {name!r} is not a joint of the skeleton (its joints: "
                             f"{', '.join(skeleton.joint_names[:6])} …)")
        v = np.asarray(x, np.float64)
        if v.shape != (3,) or not np.isfinite(v).all():
            raise InputError(f"joints: {name!r}: expected three finite numbers, got {x!r}")
        out[index[name]] = v
    return out


def _with_positions(skeleton, X, deform):
    """The skeleton with bind translations ``X`` and rotations turned by the per-joint rotation
    taking its bones onto the new ones."""
    bind = skeleton.bind_transforms
    X0 = bind[:, :3, 3]
    J = skeleton.joint_count
    children = [np.nonzero(skeleton.parents == j)[0] for j in range(J)]
    turn = np.tile(np.eye(3), (J, 1, 1))
    for j in range(J):
        a, b = [], []
        for c in _reach(children, X0, j):
            a.append(X0[c] - X0[j])
            b.append(X[c] - X[j])
        if a:
            turn[j] = best_rotation(np.asarray(a), np.asarray(b))
        elif skeleton.parents[j] >= 0:
            turn[j] = turn[skeleton.parents[j]]
    new = bind.copy()
    new[:, :3, :3] = turn @ bind[:, :3, :3]
    new[:, :3, 3] = X
    return Skeleton(skeleton.joint_names, skeleton.parents, new, name=skeleton.name,
                    world_transform=skeleton.world_transform)


def _reach(children, X0, j, tiny=1e-9):
    """Children of ``j`` away from it, through children at its own place."""
    out = []
    for c in children[j]:
        if np.linalg.norm(X0[c] - X0[j]) > tiny:
            out.append(int(c))
        else:
            out += _reach(children, X0, c, tiny) if len(children[c]) else []
    return out


def embedding_errors(embedded: npt.ArrayLike, truth: npt.ArrayLike, height: float
                     ) -> tuple[float, float, np.ndarray]:
    """``(mean, worst, per joint)`` distances between embedded and true joint positions (N, 3),
    in % of ``height``."""
    d = np.linalg.norm(np.asarray(embedded, np.float64) - np.asarray(truth, np.float64), axis=1)
    d = 100.0 * d / height
    return float(d.mean()), float(d.max()), d
