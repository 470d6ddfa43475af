"""Skinning-artifact metrics per mesh and per frame: volume, edge strain, vertex distance, and the
candy-wrapper / bulge measures near joints (rings of equal weight share, measured in their own
frame) with each joint's bend and twist.

Shapes: ``points`` are ``(V, 3)`` or ``(F, V, 3)`` (F frames); results carry the frame axis only
when the input does. Reference arrays (``rest_points``, ``reference_points``, ...) are ``(V, 3)``
(shared by all frames) or ``(F, V, 3)``. Faces are ``(T, 3)`` int triangles; their winding defines
the outward side (counter-clockwise seen from outside). Compare quantities in one space: skinned
points are in skeleton (bind) space, so pass rest points through the geom-bind transform first.
Per-element work runs in Warp kernels (:mod:`dqskin.kernels.metrics`) on ``device`` (CUDA when
present, else CPU) in float32; sums, ring moments and ratios are taken in float64 NumPy.
"""

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import warp as wp

from . import quat
from ._warp import Device, resolve_device
from .errors import InputError
from .influences import Influences, check_joint_range
from .kernels import metrics as KM
from .linalg import polar
from .shapes import frames_of
from .skeleton import check_parents
from .topology import check_faces

__all__ = ["METRICS", "PAIR_SHARE", "RING_WIDTH", "RingSections", "bone_directions",
           "character_height",
           "dominant_pair_regions", "edge_strain", "joint_bend_twist", "joint_rings", "mesh_edges",
           "ring_sections", "vertex_distance", "volume", "volume_ratio", "worst"]


def _vec3s(a, device):
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=device)


def _floats(shape, device):
    return wp.empty(shape, dtype=float, device=device)


def _result(a: np.ndarray, batched: bool) -> np.ndarray:
    return a if batched else a[0]


def volume(points: npt.ArrayLike, faces: npt.ArrayLike, *,
           device: Device = None) -> float | np.ndarray:
    """Signed volume enclosed by a triangle mesh (divergence theorem).

    ``V = Σ_t (a−o)·((b−o)×(c−o)) / 6`` over the triangles, with ``o`` the frame's bounding-box
    centre. Positive for a closed mesh wound outward; meaningless for an open mesh (see
    :func:`volume_ratio`).

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    faces : (T, 3) int

    Returns
    -------
    float or (F,) float64
    """
    d = resolve_device(device)
    pts, batched = frames_of("points", points, finite=True)
    f = check_faces(faces, pts.shape[1])
    origins = 0.5 * (pts.min(axis=1) + pts.max(axis=1))
    vols = _floats((pts.shape[0], f.shape[0]), d)
    KM.volumes(points=_vec3s(pts, d), faces=wp.array(f, dtype=wp.vec3i, device=d),
              origins=_vec3s(origins, d), out=vols, device=d)
    v = vols.numpy().astype(np.float64).sum(axis=1)
    return v if batched else float(v[0])


def _weld(faces, points):
    """Faces with vertices at bit-identical positions merged onto one index."""
    _, inverse = np.unique(np.asarray(points, dtype=np.float64), axis=0, return_inverse=True)
    return inverse.reshape(-1)[faces]


def _closure_problem(faces, points):
    """Why the mesh of ``faces`` (T, 3), welded at bit-identical ``points`` (V, 3), is not closed,
    edge-manifold and consistently wound; None if every edge is shared by exactly two faces
    traversing it in opposite directions (degenerate faces with a repeated vertex are ignored)."""
    f = _weld(faces.astype(np.int64), points)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    if f.shape[0] == 0:
        return "no non-degenerate faces"
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    boundary, nonmanifold = int(np.sum(counts == 1)), int(np.sum(counts > 2))
    if boundary:
        return f"open mesh: {boundary} boundary edges"
    if nonmanifold:
        return f"non-manifold mesh: {nonmanifold} edges shared by more than two faces"
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    flipped = int(np.sum(dcounts > 1))
    if flipped:
        return f"inconsistent winding: {flipped} edges traversed twice in the same direction"
    return None


def volume_ratio(points: npt.ArrayLike, rest_points: npt.ArrayLike, faces: npt.ArrayLike, *,
                 device: Device = None) -> tuple[float | np.ndarray | None, str | None]:
    """Enclosed volume relative to the rest volume, for closed meshes.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
        Posed points.
    rest_points : (V, 3) float
        Rest points in the same space.
    faces : (T, 3) int
        Must form a closed mesh: every undirected edge shared by exactly two faces that traverse
        it in opposite directions (degenerate faces with a repeated vertex are ignored), after
        merging vertices at bit-identical rest positions (seams of UV- or normal-split meshes).

    Returns
    -------
    ratios : float, (F,) float64 or None
        ``volume(points) / volume(rest_points)``; None when the ratio is undefined.
    reason : str or None
        Why ``ratios`` is None (open, non-manifold or inconsistently wound mesh; zero rest
        volume), else None.
    """
    rest, _ = frames_of("rest_points", rest_points, 1, finite=True)
    f = check_faces(faces, rest.shape[1])
    problem = _closure_problem(f, rest[0])
    if problem:
        return None, problem
    rest_volume = float(volume(rest[0], f, device=device))  # one frame: a float
    scale = character_height(rest[0])
    if not abs(rest_volume) > 1e-9 * scale ** 3:
        return None, f"rest volume is zero ({rest_volume:g})"
    frames_of("points", points, count=rest.shape[1], finite=True)
    return volume(points, f, device=device) / rest_volume, None


def mesh_edges(faces: npt.ArrayLike) -> np.ndarray:
    """Unique undirected edges of a triangle mesh.

    Parameters
    ----------
    faces : (T, 3) int

    Returns
    -------
    (E, 2) int32
        Vertex pairs ``(a, b)`` with ``a < b``, sorted lexicographically.
    """
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces: expected (T, 3) triangles, got {f.shape}")
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0).astype(np.int32)


def edge_strain(points: npt.ArrayLike, rest_points: npt.ArrayLike, edges: npt.ArrayLike, *,
                device: Device = None) -> np.ndarray:
    """Engineering strain of each edge, ``|p_a − p_b| / |r_a − r_b| − 1``.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    rest_points : (V, 3) or (F, V, 3) float
    edges : (E, 2) int
        E.g. :func:`mesh_edges`.

    Returns
    -------
    (E,) or (F, E) float32
        0 for unchanged length, > 0 stretched, < 0 compressed; NaN for zero-length rest edges.
    """
    d = resolve_device(device)
    pts, batched = frames_of("points", points, finite=True)
    rest, _ = frames_of("rest_points", rest_points, *pts.shape[:2], finite=True)
    e = np.asarray(edges)
    if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
        raise InputError(f"edges: expected (E, 2) integers, got {e.dtype} {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= pts.shape[1]):
        raise InputError(f"edges: vertex index out of range [0, {pts.shape[1]})")
    strain = _floats((pts.shape[0], e.shape[0]), d)
    KM.edge_strain(points=_vec3s(pts, d), rest_points=_vec3s(rest, d),
                  edges=wp.array(e.astype(np.int32), dtype=wp.vec2i, device=d), out=strain,
                  device=d)
    return _result(strain.numpy(), batched)


def character_height(points: npt.ArrayLike) -> float:
    """The size distances are given as a share of: the largest extent of the bounding box of
    ``points`` (a character's height when standing, its span when lying or reaching out).

    Parameters
    ----------
    points : (V, 3) float
        A character's points in one pose (its rest pose), all its meshes together.

    Returns
    -------
    float
        In the points' length unit; 0.0 for no points.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return float(np.ptp(p, axis=0).max()) if len(p) else 0.0


def vertex_distance(points: npt.ArrayLike, reference_points: npt.ArrayLike, *,
                    device: Device = None) -> np.ndarray:
    """Distance between corresponding vertices, e.g. of two skinning methods' results.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    reference_points : (V, 3) or (F, V, 3) float

    Returns
    -------
    (V,) or (F, V) float32, in the points' units.
    """
    d = resolve_device(device)
    pts, batched = frames_of("points", points, finite=True)
    ref, _ = frames_of("reference_points", reference_points, *pts.shape[:2], finite=True)
    dist = _floats(pts.shape[:2], d)
    KM.distances(points=_vec3s(pts, d), reference=_vec3s(ref, d), out=dist, device=d)
    return _result(dist.numpy(), batched)


def _parents(parents, count):
    """:func:`dqskin.skeleton.check_parents`, plus the joint count when ``count >= 0``."""
    par = check_parents(parents).astype(np.int64)
    if count >= 0 and par.shape[0] != count:
        raise InputError(f"parents: expected ({count},) integers, got {par.shape}")
    return par


PAIR_SHARE = 0.9
"""Share of a vertex's weight its joint and parent must hold for the vertex to be in the joint's
region (:func:`dominant_pair_regions`): a third joint moving the rest would distort its ring."""


def dominant_pair_regions(joint_indices: npt.ArrayLike, joint_weights: npt.ArrayLike,
                          parents: npt.ArrayLike, *, min_weight: float = 0.05,
                          min_pair: float = PAIR_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """Assign vertices to the joint they bend around: the vertex's two largest weights belong to a
    joint ``j`` and its parent, the smaller of the two is at least ``min_weight`` and together
    they hold at least ``min_pair`` of the vertex's total weight (other joints barely move it).

    Parameters
    ----------
    joint_indices, joint_weights : (V, K)
        K ≥ 2 influence slots (ties keep the earlier slot).
    parents : (J,) int
    min_weight : float
    min_pair : float
        In [0, 1].

    Returns
    -------
    regions : (V,) int32
        The child joint ``j`` of the pair (index into ``parents``), or -1.
    fraction : (V,) float64
        The child's share of the pair, ``w_j / (w_j + w_parent)`` in (0, 1); NaN outside the
        regions.
    """
    inf = Influences(joint_indices, joint_weights)  # the kernels' layout: largest weight first
    idx = inf.indices.reshape(inf.vertex_count, -1)
    w = np.asarray(joint_weights, dtype=np.float64).reshape(inf.order.shape)
    par = _parents(parents, -1)
    regions = np.full(idx.shape[0], -1, dtype=np.int32)
    fraction = np.full(idx.shape[0], np.nan)
    if inf.influence_count < 2 or inf.vertex_count == 0:
        return regions, fraction
    check_joint_range(inf.joint_count_min - 1, par.shape[0])
    (a, b) = idx[:, :2].T
    wa, wb = np.take_along_axis(w, inf.order[:, :2], 1).T
    strong = (wb >= min_weight) & (wa + wb >= min_pair * w.sum(axis=1))
    a_child = strong & (par[a] == b)
    b_child = strong & (par[b] == a)
    regions[a_child], fraction[a_child] = a[a_child], (wa / (wa + wb))[a_child]
    regions[b_child], fraction[b_child] = b[b_child], (wb / (wa + wb))[b_child]
    return regions, fraction


RING_WIDTH = 1 / 32
"""Width, in the child's weight share, of the rings of :func:`joint_rings`; ring ``k`` holds the
shares within ``RING_WIDTH / 2`` of ``k · RING_WIDTH`` (so the share ½ is a ring centre)."""


def joint_rings(joint_indices: npt.ArrayLike, joint_weights: npt.ArrayLike, parents: npt.ArrayLike,
                *, ring_width: float = RING_WIDTH, min_weight: float = 0.05,
                min_pair: float = PAIR_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """Cut each joint's region into rings of equal weight share: the level sets of the blend.

    A vertex belongs to joint ``j`` when its two largest weights are ``j`` and ``j``'s parent
    (:func:`dominant_pair_regions`); its ring is its child share ``w_j / (w_j + w_parent)``
    rounded to a multiple of ``ring_width``. Vertices of one ring get (nearly) the same blend of
    the same two transforms, so a method that keeps the flesh intact moves each ring rigidly,
    however far the joint bends.

    Parameters
    ----------
    joint_indices, joint_weights : (V, K)
    parents : (J,) int
    ring_width : float
        In (0, 1]; ``1 / ring_width`` should be an even integer, so ½ is a ring centre.
    min_weight, min_pair : float
        As :func:`dominant_pair_regions`.

    Returns
    -------
    rings : (V,) int32
        ``j · R + k`` for ring ``k`` of joint ``j``, ``R = round(1 / ring_width) + 1`` rings per
        joint, or -1 outside every region.
    ring_share : (R,) float64
        The child share at the centre of each ring, ``k · ring_width``.
    """
    if not 0 < ring_width <= 1:
        raise InputError(f"ring_width: expected a share in (0, 1], got {ring_width!r}")
    count = int(round(1 / ring_width)) + 1
    regions, share = dominant_pair_regions(joint_indices, joint_weights, parents,
                                           min_weight=min_weight, min_pair=min_pair)
    rings = np.full(regions.shape, -1, dtype=np.int32)
    inside = regions >= 0
    k = np.clip(np.floor(share[inside] / ring_width + 0.5), 0, count - 1).astype(np.int32)
    rings[inside] = regions[inside] * count + k
    return rings, np.arange(count) * float(ring_width)


@dataclass
class RingSections:
    """Section and bulge measures of vertex rings (see :func:`ring_sections`).

    Attributes
    ----------
    section_ratio : (F, N) float64
        Per ring: √(posed section area / rest section area), the ratio of equivalent radii.
        1 intact, 0 collapsed to a line or point (candy wrapper). NaN for rings with too few
        vertices or a degenerate rest section.
    bulge_ratio : (F, N) float64
        Per ring: the largest per-vertex ratio of posed to rest distance from the ring's centroid
        (> 1 bulges out); NaN as ``section_ratio``.
    vertex_ratio : (F, V) float64
        Per-vertex posed / rest distance from its ring's centroid; NaN outside valid rings and
        for vertices nearer the centroid than ``min_radius`` × the ring's RMS radius.
    """

    section_ratio: np.ndarray
    bulge_ratio: np.ndarray
    vertex_ratio: np.ndarray


def _ring_moments(points, rings, members, count):
    """Centroids (F, N, 3), covariances (F, N, 3, 3) and counts (N,) of ``points`` (F, V, 3)
    over the ring ids ``rings[members]`` (float64 sums)."""
    ids = rings[members].astype(np.int64)
    n = np.bincount(ids, minlength=count).astype(np.float64)
    safe = np.maximum(n, 1.0)
    frames = points.shape[0]
    p = points[:, members].astype(np.float64)
    centroid = np.stack([np.stack([np.bincount(ids, weights=p[f, :, a], minlength=count)
                                   for a in range(3)], -1) for f in range(frames)]) / safe[:, None]
    d = p - centroid[:, ids]
    cov = np.empty((frames, count, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            s = np.stack([np.bincount(ids, weights=d[f, :, a] * d[f, :, b], minlength=count)
                          for f in range(frames)]) / safe
            cov[:, :, a, b] = cov[:, :, b, a] = s
    return centroid, cov, n, d


def ring_sections(rest_points: npt.ArrayLike, points: npt.ArrayLike, rings: npt.ArrayLike,
                  ring_count: int, *, min_vertices: int = 4,
                  min_radius: float = 0.25) -> RingSections:
    """Cross-section and bulge of vertex rings (e.g. :func:`joint_rings`), measured in each
    ring's own frame: both measures are invariant to any rigid motion of the ring.

    For each ring, the covariance of its vertices about their centroid has eigenvalues
    ``λ1 ≥ λ2 ≥ λ3``; ``√(λ1 λ2)`` is proportional to the area of the ring's best-fit ellipse
    (its cross-section). Then

    * ``section_ratio = (√(λ1 λ2)_posed / √(λ1 λ2)_rest)^½``: for a circular ring of weight
      share ``w`` under LBS, ``k = √(1 − 2w(1−w)(1 − cos θ))`` in a twist by θ (both axes shrink
      by ``k``) and ``√k`` in a bend by θ (one axis shrinks by ``k``); 1 for any rigid motion, so
      1 for DQS in both;
    * ``bulge_ratio`` = the largest ``|p − c|_posed / |p − c|_rest`` over the ring's vertices at
      least ``min_radius`` × its RMS radius from the centroid ``c``: ≤ 1 for LBS on a circular
      ring in a twist or a bend, 1 for DQS.

    Parameters
    ----------
    rest_points : (V, 3) float
    points : (V, 3) or (F, V, 3) float
        Posed points, any space (the measures ignore rigid motions).
    rings : (V,) int
        Ring of each vertex in [0, ring_count), or -1 for none.
    ring_count : int
    min_vertices : int
        Rings with fewer vertices get NaN (3 points always lie on a plane).
    min_radius : float

    Returns
    -------
    RingSections
        Arrays with a leading frame axis (F = 1 for (V, 3) points).
    """
    pts, _ = frames_of("points", points, finite=True)
    frames, count = pts.shape[:2]
    rest, _ = frames_of("rest_points", rest_points, 1, count, finite=True)
    r = np.asarray(rings)
    if r.shape != (count,) or not np.issubdtype(r.dtype, np.integer):
        raise InputError(f"rings: expected ({count},) integers, got {r.dtype} {r.shape}")
    if int(ring_count) != ring_count or ring_count < 0:
        raise InputError(f"ring_count: expected a count >= 0, got {ring_count!r}")
    if r.size and (r.min() < -1 or r.max() >= ring_count):
        raise InputError(f"rings: value out of range [-1, {ring_count})")
    members = np.flatnonzero(r >= 0)
    _, cov0, n, d0 = _ring_moments(rest, r, members, ring_count)
    _, cov, _, d = _ring_moments(pts, r, members, ring_count)
    lam0 = np.linalg.eigvalsh(cov0[0])  # ascending
    lam = np.maximum(np.linalg.eigvalsh(cov), 0.0)
    area0 = np.sqrt(np.maximum(lam0[:, 2] * lam0[:, 1], 0.0))
    valid = (n >= min_vertices) & (lam0[:, 1] > 1e-8 * lam0[:, 2]) & (lam0[:, 2] > 0)
    section = np.full((frames, ring_count), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        section[:, valid] = np.sqrt(np.sqrt(lam[:, valid, 2] * lam[:, valid, 1])
                                    / area0[valid])
    ids = r[members]
    rho0 = np.linalg.norm(d0[0], axis=-1)
    rms0 = np.sqrt(np.bincount(ids, weights=rho0 ** 2, minlength=ring_count)
                   / np.maximum(n, 1))
    far = valid[ids] & (rho0 >= min_radius * rms0[ids]) & (rho0 > 0)
    vertex_ratio = np.full((frames, count), np.nan)
    ratio = np.linalg.norm(d[:, far], axis=-1) / rho0[far]
    vertex_ratio[:, members[far]] = ratio
    bulge = np.full((frames, ring_count), -np.inf)
    for f in range(frames):
        np.maximum.at(bulge[f], ids[far], ratio[f])
    bulge[~np.isfinite(bulge)] = np.nan
    return RingSections(section_ratio=section, bulge_ratio=bulge, vertex_ratio=vertex_ratio)


def bone_directions(bind_positions: npt.ArrayLike, parents: npt.ArrayLike) -> np.ndarray:
    """Unit bind-space direction of the bone each joint drives: toward the mean of its
    children's positions, or along its parent bone for a leaf (zero for a lone root).

    Parameters
    ----------
    bind_positions : (J, 3) float
    parents : (J,) int

    Returns
    -------
    (J, 3) float64
    """
    pos = np.asarray(bind_positions, dtype=np.float64)
    par = _parents(parents, pos.shape[0] if pos.ndim == 2 else -1)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise InputError(f"bind_positions: expected ({par.shape[0]}, 3), got {pos.shape}")
    child_sum = np.zeros_like(pos)
    children = np.zeros(pos.shape[0])
    has = par >= 0
    np.add.at(child_sum, par[has], pos[has])
    np.add.at(children, par[has], 1)
    d = np.where(children[:, None] > 0, child_sum / np.maximum(children, 1)[:, None] - pos, 0.0)
    leaf = (children == 0) & has
    d[leaf] = pos[leaf] - pos[par[leaf]]
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, norm, out=np.zeros_like(d), where=norm > 0)


def joint_bend_twist(skinning_transforms: npt.ArrayLike, bind_positions: npt.ArrayLike,
                     parents: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Bend and twist of each joint relative to its parent, in degrees.

    The relative rotation ``R = R_parent⁻¹ R_joint`` of the skinning transforms' rotations (their
    polar factors; identity in the bind pose) is split into a twist about the joint's bone
    (:func:`bone_directions`) and a swing: ``R = swing · twist``. The bend is the swing angle.

    Parameters
    ----------
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
    bind_positions : (J, 3) float
    parents : (J,) int

    Returns
    -------
    bend, twist : (J,) or (F, J) float64
        Degrees in [0, 180]; NaN for roots.
    """
    x = np.asarray(skinning_transforms, dtype=np.float64)
    par = _parents(parents, -1)
    if x.ndim not in (3, 4) or x.shape[-3:] != (par.shape[0], 4, 4):
        raise InputError(f"skinning_transforms: expected ({par.shape[0]}, 4, 4) or (F, "
                         f"{par.shape[0]}, 4, 4), got {x.shape}")
    axis = bone_directions(bind_positions, par)
    rot, _ = polar(x[..., :3, :3])
    parent_rot = rot[..., np.where(par >= 0, par, np.arange(par.shape[0])), :, :]
    q = quat.from_matrix(np.swapaxes(parent_rot, -1, -2) @ rot)  # w ≥ 0
    w, v = q[..., 0], q[..., 1:]
    along = np.einsum("...ja,ja->...j", v, axis)
    twist = 2 * np.degrees(np.arctan2(np.abs(along), w))
    bend = 2 * np.degrees(np.arctan2(np.linalg.norm(v - along[..., None] * axis, axis=-1),
                                     np.hypot(w, along)))
    root = par < 0
    bend[..., root] = np.nan
    twist[..., root] = np.nan
    return bend, twist


METRICS = ("volume_ratio", "min_section_ratio", "max_bulge_ratio")
"""Per-frame metrics of ``dqskin compare``'s ``metrics.json``. The summary judges each by its worst
value (:func:`worst`): the volume ratio furthest from 1, the smallest section ratio, the largest
bulge ratio."""


def worst(metric: str, values: npt.ArrayLike) -> tuple[int, float] | None:
    """The worst finite value of a metric.

    Parameters
    ----------
    metric : str
        One of :data:`METRICS`.
    values : (N,) float
        NaN for undefined values.

    Returns
    -------
    (index, severity) or None
        Index of the worst value and how bad it is: ``|v − 1|`` for the volume ratio, ``1 − v``
        for the smallest section ratio, ``v − 1`` for the largest bulge ratio (negative: no
        collapse, no bulge). None when no value is finite.
    """
    v = np.asarray(values, dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(v))
    if not ok.size:
        return None
    if metric == "min_section_ratio":
        k = ok[np.argmin(v[ok])]
        return k, 1.0 - v[k]
    if metric == "max_bulge_ratio":
        k = ok[np.argmax(v[ok])]
        return k, v[k] - 1.0
    k = ok[np.argmax(np.abs(v[ok] - 1.0))]
    return k, abs(v[k] - 1.0)
