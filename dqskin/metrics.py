"""Skinning-artifact metrics per mesh and per frame: volume, edge strain, vertex distance, and the
candy-wrapper / bulge measures near joints.

Shapes: ``points`` are ``(V, 3)`` or ``(F, V, 3)`` (F frames); results carry the frame axis only
when the input does. Reference arrays (``rest_points``, ``reference_points``, ...) are ``(V, 3)``
(shared by all frames) or ``(F, V, 3)``. Faces are ``(T, 3)`` int triangles; their winding defines
the outward side (counter-clockwise seen from outside). Compare quantities in one space: skinned
points are in skeleton (bind) space, so pass rest points through the geom-bind transform first.
Per-element work runs in Warp kernels (:mod:`dqskin.kernels.metrics`) on ``device`` (CUDA when
present, else CPU) in float32; sums and ratios are taken in float64.
"""

import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from ._warp import resolve_device
from .influences import Influences
from .kernels import metrics as K
from .shapes import frames_of
from .skeleton import check_parents
from .topology import check_faces

__all__ = ["METRICS", "JointSections", "bone_segments", "dominant_pair_regions", "edge_strain",
           "joint_axes", "joint_sections", "mesh_edges", "vertex_distance", "volume",
           "volume_ratio", "worst"]


def _vec3s(a, device):
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=device)


def _floats(shape, device):
    return wp.empty(shape, dtype=float, device=device)


def _result(a, batched):
    return a if batched else a[0]


def volume(points, faces, *, device=None):
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
    K.volumes(points=_vec3s(pts, d), faces=wp.array(f, dtype=wp.vec3i, device=d),
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


def volume_ratio(points, rest_points, faces, *, device=None):
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
    rest_volume = volume(rest[0], f, device=device)
    scale = np.ptp(rest[0], axis=0).max() if rest.shape[1] else 0.0
    if not abs(rest_volume) > 1e-9 * scale ** 3:
        return None, f"rest volume is zero ({rest_volume:g})"
    frames_of("points", points, count=rest.shape[1], finite=True)
    return volume(points, f, device=device) / rest_volume, None


def mesh_edges(faces):
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
        raise ValueError(f"faces: expected (T, 3) triangles, got {f.shape}")
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0).astype(np.int32)


def edge_strain(points, rest_points, edges, *, device=None):
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
        raise ValueError(f"edges: expected (E, 2) integers, got {e.dtype} {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= pts.shape[1]):
        raise ValueError(f"edges: vertex index out of range [0, {pts.shape[1]})")
    strain = _floats((pts.shape[0], e.shape[0]), d)
    K.edge_strain(points=_vec3s(pts, d), rest_points=_vec3s(rest, d),
                  edges=wp.array(e.astype(np.int32), dtype=wp.vec2i, device=d), out=strain,
                  device=d)
    return _result(strain.numpy(), batched)


def vertex_distance(points, reference_points, *, device=None):
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
    K.distances(points=_vec3s(pts, d), reference=_vec3s(ref, d), out=dist, device=d)
    return _result(dist.numpy(), batched)


def _parents(parents, count):
    """:func:`dqskin.skeleton.check_parents`, plus the joint count when ``count >= 0``."""
    par = check_parents(parents).astype(np.int64)
    if count >= 0 and par.shape[0] != count:
        raise ValueError(f"parents: expected ({count},) integers, got {par.shape}")
    return par


def bone_segments(joint_positions, parents):
    """Axis segment of the bone ending at each joint: ``(parent position, joint position)``.

    Parameters
    ----------
    joint_positions : (J, 3) or (F, J, 3) float
        E.g. the translation column of world (or bind) transforms, ``xf[..., :3, 3]``.
    parents : (J,) int
        Parent joint, ``-1`` for roots (whose segment degenerates to the joint itself).

    Returns
    -------
    (J, 2, 3) or (F, J, 2, 3) float64
        Rows ``(head, tail)``; ``tail`` is the joint, the axis runs head → tail.
    """
    pos = np.asarray(joint_positions, dtype=np.float64)
    par = _parents(parents, -1)
    if pos.ndim not in (2, 3) or pos.shape[-1] != 3 or pos.shape[-2] != par.shape[0]:
        raise ValueError(f"joint_positions: expected ({par.shape[0]}, 3) or (F, {par.shape[0]}, "
                         f"3) for {par.shape[0]} parents, got {pos.shape}")
    head = pos[..., np.where(par >= 0, par, np.arange(par.shape[0])), :]
    return np.stack([head, pos], axis=-2)


def joint_axes(bind_positions, parents, skinning_transforms):
    """Axes of :func:`joint_sections` for every joint of a skeleton.

    Joint ``j``'s rest axis is its parent bone, ``(bind position of the parent, bind position of
    j)`` (:func:`bone_segments`). Posed, the parent side is that segment moved by the parent's
    skinning transform (the posed parent bone) and the child side the same segment moved by
    ``j``'s own skinning transform. A twist about the bone leaves both on the bone line; a bend
    turns the child side with the flesh it carries. Roots get degenerate axes (NaN measures).

    Parameters
    ----------
    bind_positions : (J, 3) float
        Bind-space joint positions (translation of the world bind transforms).
    parents : (J,) int
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        Bind-relative joint transforms, column-vector convention.

    Returns
    -------
    rest_segments : (J, 2, 3) float64
    segments, child_segments : (J, 2, 3) or (F, J, 2, 3) float64
    """
    pos = np.asarray(bind_positions, dtype=np.float64)
    rest = bone_segments(pos, parents)
    par = _parents(parents, pos.shape[0])
    x = np.asarray(skinning_transforms, dtype=np.float64)
    if x.ndim not in (3, 4) or x.shape[-3:] != (par.shape[0], 4, 4):
        raise ValueError(f"skinning_transforms: expected ({par.shape[0]}, 4, 4) or (F, "
                         f"{par.shape[0]}, 4, 4), got {x.shape}")

    def moved(m):
        return np.einsum("...jab,jkb->...jka", m[..., :3, :3], rest) + m[..., None, :3, 3]

    parent_x = x[..., np.where(par >= 0, par, np.arange(par.shape[0])), :, :]
    return rest, moved(parent_x), moved(x)


def dominant_pair_regions(joint_indices, joint_weights, parents, *, min_weight=0.05):
    """Assign vertices to the joint they bend around: the vertex's two largest weights belong to a
    joint ``j`` and its parent, and the smaller of the two is at least ``min_weight``.

    Parameters
    ----------
    joint_indices, joint_weights : (V, K)
        K ≥ 2 influence slots (ties keep the earlier slot).
    parents : (J,) int
    min_weight : float

    Returns
    -------
    (V,) int32
        The child joint ``j`` of the pair (index into ``parents``), or -1.
    """
    inf = Influences(joint_indices, joint_weights)  # the kernels' layout: largest weight first
    idx = inf.indices.reshape(inf.vertex_count, -1)
    w = np.asarray(joint_weights, dtype=np.float64).reshape(inf.order.shape)
    par = _parents(parents, -1)
    regions = np.full(idx.shape[0], -1, dtype=np.int32)
    if inf.influence_count < 2 or inf.vertex_count == 0:
        return regions
    if inf.joint_count_min > par.shape[0]:
        raise ValueError(f"joint_indices: index out of range [0, {par.shape[0]})")
    (a, b), wb = idx[:, :2].T, np.take_along_axis(w, inf.order[:, 1:2], 1)[:, 0]
    strong = wb >= min_weight
    regions[strong & (par[a] == b)] = a[strong & (par[a] == b)]
    regions[strong & (par[b] == a)] = b[strong & (par[b] == a)]
    return regions


@dataclass
class JointSections:
    """Cross-section measures of the regions around joints (see :func:`joint_sections`).

    Attributes
    ----------
    min_section_ratio : (F, B) float64
        Smallest slice ratio: 1 intact, 0 fully collapsed (candy wrapper). NaN for empty regions.
    max_bulge_ratio : (F, B) float64
        Largest per-vertex radial ratio (posed / rest distance to the axis): > 1 bulges.
    slice_ratio : (F, B, S) float64
        Mean posed radial distance / mean rest radial distance of the vertices in each slice; NaN
        for empty slices.
    slice_axial : (B, S) float64
        Rest axial coordinate of each slice centre, from the joint (segment tail) along the axis.
    vertex_ratio : (F, V) float64
        Per-vertex posed / rest radial distance; NaN outside the regions or near the axis.
    """

    min_section_ratio: np.ndarray
    max_bulge_ratio: np.ndarray
    slice_ratio: np.ndarray
    slice_axial: np.ndarray
    vertex_ratio: np.ndarray


def _segments(name, seg, frames, count):
    s = np.asarray(seg, dtype=np.float64)
    s = s[None] if s.ndim == 3 else s
    if s.ndim != 4 or s.shape[0] not in (1, frames) or s.shape[1:] != (count, 2, 3):
        raise ValueError(f"{name}: expected ({count}, 2, 3) or ({frames}, {count}, 2, 3), got "
                         f"{np.shape(seg)}")
    if not np.all(np.isfinite(s)):
        raise ValueError(f"{name}: NaN or infinite coordinate")
    return np.broadcast_to(s, (frames,) + s.shape[1:])


def joint_sections(rest_points, points, rest_segments, segments, regions, *, child_segments=None,
                   slices=16, min_radius=0.25, device=None):
    """Candy-wrapper collapse and bulging of the flesh around joints.

    Each region ``b`` (usually a joint, vertices from :func:`dominant_pair_regions`) has an axis:
    the line through its segment ``(head, tail)`` (usually the parent bone, parent joint → joint;
    see :func:`joint_axes`), at rest and per posed frame. Every member vertex gets cylindrical
    coordinates about its region's axis: the axial coordinate ``s`` (from the tail, along
    head → tail) and the radial distance ``ρ``, at rest and posed. Members beyond the joint
    (rest ``s > 0``) use ``child_segments`` as their posed axis when given (the rest axis carried by
    the joint itself), so bending does not count as bulging. The members are cut by their *rest*
    ``s`` into ``slices`` equal slices spanning their rest range, so a slice holds the same
    vertices in every frame.

    * slice ratio = mean posed ``ρ`` / mean rest ``ρ`` over the slice's vertices;
    * ``min_section_ratio`` = smallest slice ratio (for a twist by θ with linear weights under
      LBS, ``√(1 − 2w(1−w)(1−cos θ))`` at the slice of weight ``w``; DQS keeps 1);
    * ``max_bulge_ratio`` = largest per-vertex ``ρ_posed / ρ_rest`` over the members whose rest
      ``ρ`` is at least ``min_radius`` × the region's mean rest ``ρ``.

    Without ``child_segments`` the single straight axis suits twists (candy wrapper) only; with
    them, bends are measured on each side in the frame of the bone that carries the flesh. Right
    at a strongly bent joint the two frames disagree and the measures are indicative.

    Parameters
    ----------
    rest_points : (V, 3) float
    points : (V, 3) or (F, V, 3) float
        Posed points, same space as the posed segments.
    rest_segments : (B, 2, 3) float
    segments : (B, 2, 3) or (F, B, 2, 3) float
        Posed segments. A zero-length segment makes its region's measures NaN.
    regions : (V,) int
        Region of each vertex in [0, B), or -1 for none.
    child_segments : (B, 2, 3) or (F, B, 2, 3) float, optional
        Posed axis of the members with rest ``s > 0``; ``segments`` by default.
    slices : int
    min_radius : float
        Fraction of the region's mean rest radius below which vertices are left out of the
        per-vertex ratios (near the axis the ratio is ill-conditioned).

    Returns
    -------
    JointSections
        Arrays with a leading frame axis (F = 1 for (V, 3) points).
    """
    d = resolve_device(device)
    pts, _ = frames_of("points", points, finite=True)
    frames, count = pts.shape[:2]
    rest, _ = frames_of("rest_points", rest_points, 1, count, finite=True)
    reg = np.asarray(regions)
    if reg.shape != (count,) or not np.issubdtype(reg.dtype, np.integer):
        raise ValueError(f"regions: expected ({count},) integers, got {reg.dtype} {reg.shape}")
    rseg0 = np.asarray(rest_segments, dtype=np.float64)
    if rseg0.ndim != 3 or rseg0.shape[1:] != (2, 3):
        raise ValueError(f"rest_segments: expected (B, 2, 3), got {rseg0.shape}")
    nb = rseg0.shape[0]
    rseg = _segments("rest_segments", rseg0, 1, nb)
    pseg = _segments("segments", segments, frames, nb)
    if reg.size and (reg.min() < -1 or reg.max() >= nb):
        raise ValueError(f"regions: value out of range [-1, {nb})")
    if int(slices) != slices or slices < 1:
        raise ValueError(f"slices: expected a positive integer, got {slices!r}")
    reg_w = wp.array(reg.astype(np.int32), dtype=wp.int32, device=d)

    def cylindrical(p, seg):
        axial, radial = (_floats((p.shape[0], count), d) for _ in range(2))
        K.axis_coordinates(points=_vec3s(p, d), regions=reg_w, origins=_vec3s(seg[:, :, 1], d),
                           directions=_vec3s(seg[:, :, 1] - seg[:, :, 0], d), axial=axial,
                           radial=radial, device=d)
        return axial.numpy().astype(np.float64), radial.numpy().astype(np.float64)

    s0, rho0 = (a[0] for a in cylindrical(rest, rseg))
    _, rho = cylindrical(pts, pseg)
    if child_segments is not None:
        _, rho_child = cylindrical(pts, _segments("child_segments", child_segments, frames, nb))
        rho = np.where(s0 > 0, rho_child, rho)
    members = np.flatnonzero(np.isfinite(rho0))
    mreg = reg[members].astype(np.int64)
    sm = s0[members]
    lo = np.full(nb, np.inf)
    hi = np.full(nb, -np.inf)
    np.minimum.at(lo, mreg, sm)
    np.maximum.at(hi, mreg, sm)
    span = np.where(hi > lo, hi - lo, 1.0)
    bins = np.clip(np.floor((sm - lo[mreg]) / span[mreg] * slices), 0, slices - 1).astype(np.int64)
    key = mreg * slices + bins
    size = nb * slices
    n = np.bincount(key, minlength=size)
    rest_mean = np.bincount(key, weights=rho0[members], minlength=size)
    posed_mean = np.stack([np.bincount(key, weights=rho[f, members], minlength=size)
                           for f in range(frames)])
    with np.errstate(divide="ignore", invalid="ignore"):
        slice_ratio = np.where((n > 0) & (rest_mean > 0), posed_mean / rest_mean, np.nan)
        region_mean = (np.bincount(mreg, weights=rho0[members], minlength=nb)
                       / np.bincount(mreg, minlength=nb))
    slice_ratio = slice_ratio.reshape(frames, nb, slices)
    far = members[rho0[members] >= min_radius * region_mean[mreg]]
    vertex_ratio = np.full((frames, count), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex_ratio[:, far] = rho[:, far] / rho0[far]
    bulge = np.full((frames, nb), -np.inf)
    for f in range(frames):
        np.fmax.at(bulge[f], reg[far], vertex_ratio[f, far])
    bulge[~np.isfinite(bulge)] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: empty or degenerate
        min_section = np.nanmin(slice_ratio, axis=2)
    width = np.where(np.isfinite(lo), span / slices, np.nan)
    slice_axial = np.where(np.isfinite(lo), lo, np.nan)[:, None] + (
        np.arange(slices) + 0.5)[None] * width[:, None]
    return JointSections(min_section_ratio=min_section, max_bulge_ratio=bulge,
                         slice_ratio=slice_ratio, slice_axial=slice_axial,
                         vertex_ratio=vertex_ratio)


METRICS = ("volume_ratio", "min_section_ratio", "max_bulge_ratio")
"""Per-frame metrics of ``dqskin compare``'s ``metrics.json``. The summary judges each by its worst
value (:func:`worst`): the volume ratio furthest from 1, the smallest section ratio, the largest
bulge ratio."""


def worst(metric, values):
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
