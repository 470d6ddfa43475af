"""Skinning-artifact metrics per mesh and per frame: volume, local volume, strain, normals, and the
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
from .kernels import metrics as K
from .skeleton import check_parents
from .skinning import check_influences
from .topology import check_faces, incidence

__all__ = ["JointSections", "bone_segments", "dominant_pair_regions", "edge_strain", "is_closed",
           "joint_axes", "joint_axis_apex", "joint_sections", "local_volume_ratio", "mesh_edges",
           "normal_deviation", "vertex_distance", "vertex_edge_strain", "volume", "volume_ratio"]


def _frames(name, points, vertex_count=None):
    """``(V, 3)`` or ``(F, V, 3)`` → float64 ``(F, V, 3)`` and whether a frame axis was given."""
    a = np.asarray(points, dtype=np.float64)
    if a.ndim not in (2, 3) or a.shape[-1] != 3:
        raise ValueError(f"{name}: expected (V, 3) or (F, V, 3), got {a.shape}")
    if vertex_count is not None and a.shape[-2] != vertex_count:
        raise ValueError(f"{name}: expected {vertex_count} points, got {a.shape[-2]}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: NaN or infinite coordinate")
    return (a, True) if a.ndim == 3 else (a[None], False)


def _reference(name, points, frames, vertex_count):
    a, _ = _frames(name, points, vertex_count)
    if a.shape[0] not in (1, frames):
        raise ValueError(f"{name}: expected (V, 3) or ({frames}, V, 3), got {a.shape}")
    return a


def _vec3s(a, device):
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=device)


def _launch(kernel, dim, inputs, outputs, device):
    wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)
    return [o.numpy() for o in outputs]


def _result(a, batched):
    return a if batched else a[0]


def volume(points, faces, *, device=None):
    """Signed volume enclosed by a triangle mesh (divergence theorem).

    ``V = Σ_t (a−o)·((b−o)×(c−o)) / 6`` over the triangles, with ``o`` the frame's bounding-box
    centre. Positive for a closed mesh wound outward; meaningless for an open mesh (see
    :func:`is_closed`).

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    faces : (T, 3) int

    Returns
    -------
    float or (F,) float64
    """
    d = resolve_device(device)
    pts, batched = _frames("points", points)
    f = check_faces(faces, pts.shape[1])
    origins = 0.5 * (pts.min(axis=1) + pts.max(axis=1))
    (vols,) = _launch(K.face_volume_kernel, (pts.shape[0], f.shape[0]),
                      [_vec3s(pts, d), wp.array(f, dtype=wp.vec3i, device=d), _vec3s(origins, d)],
                      [wp.empty((pts.shape[0], f.shape[0]), dtype=float, device=d)], d)
    v = vols.astype(np.float64).sum(axis=1)
    return v if batched else float(v[0])


def _weld(faces, points):
    """Faces with vertices at bit-identical positions merged onto one index."""
    _, inverse = np.unique(np.asarray(points, dtype=np.float64), axis=0, return_inverse=True)
    return inverse.reshape(-1)[faces]


def _closure_problem(faces, points=None):
    """None if every edge is shared by exactly two faces traversing it in opposite directions."""
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces: expected (T, 3) integer triangles, got {f.dtype} {f.shape}")
    f = f.astype(np.int64)
    if points is not None:
        p = np.asarray(points)
        if p.ndim != 2 or p.shape[1] != 3 or (f.size and f.max() >= p.shape[0]):
            raise ValueError(f"points: expected (V, 3) covering the face indices, got {p.shape}")
        f = _weld(f, p)
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


def is_closed(faces, points=None):
    """Whether a triangle mesh is closed, edge-manifold and consistently wound.

    Every undirected edge must be shared by exactly two faces that traverse it in opposite
    directions (degenerate faces with a repeated vertex are ignored).

    Parameters
    ----------
    faces : (T, 3) int
    points : (V, 3) float, optional
        If given, vertices at bit-identical positions are merged first (seams of UV- or
        normal-split meshes).
    """
    return _closure_problem(faces, points) is None


def volume_ratio(points, rest_points, faces, *, device=None):
    """Enclosed volume relative to the rest volume, for closed meshes.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
        Posed points.
    rest_points : (V, 3) float
        Rest points in the same space. Vertices at bit-identical rest positions are merged for the
        closedness test (:func:`is_closed`).
    faces : (T, 3) int

    Returns
    -------
    ratios : float, (F,) float64 or None
        ``volume(points) / volume(rest_points)``; None when the ratio is undefined.
    reason : str or None
        Why ``ratios`` is None (open, non-manifold or inconsistently wound mesh; zero rest
        volume), else None.
    """
    rest, _ = _frames("rest_points", rest_points)
    if rest.shape[0] != 1:
        raise ValueError(f"rest_points: expected (V, 3), got {np.shape(rest_points)}")
    f = check_faces(faces, rest.shape[1])
    problem = _closure_problem(f, rest[0])
    if problem:
        return None, problem
    rest_volume = volume(rest[0], f, device=device)
    scale = np.ptp(rest[0], axis=0).max() if rest.shape[1] else 0.0
    if not abs(rest_volume) > 1e-9 * scale ** 3:
        return None, f"rest volume is zero ({rest_volume:g})"
    _frames("points", points, rest.shape[1])
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
    pts, batched = _frames("points", points)
    rest = _reference("rest_points", rest_points, pts.shape[0], pts.shape[1])
    e = np.asarray(edges)
    if e.ndim != 2 or e.shape[1] != 2 or not np.issubdtype(e.dtype, np.integer):
        raise ValueError(f"edges: expected (E, 2) integers, got {e.dtype} {e.shape}")
    if e.size and (e.min() < 0 or e.max() >= pts.shape[1]):
        raise ValueError(f"edges: vertex index out of range [0, {pts.shape[1]})")
    (strain,) = _launch(K.edge_strain_kernel, (pts.shape[0], e.shape[0]),
                        [_vec3s(pts, d), _vec3s(rest, d),
                         wp.array(e.astype(np.int32), dtype=wp.vec2i, device=d)],
                        [wp.empty((pts.shape[0], e.shape[0]), dtype=float, device=d)], d)
    return _result(strain, batched)


def vertex_edge_strain(points, rest_points, faces, *, device=None):
    """Per vertex, the strain of its most strained incident edge (largest ``|strain|``, signed).

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    rest_points : (V, 3) or (F, V, 3) float
    faces : (T, 3) int

    Returns
    -------
    (V,) or (F, V) float32
        See :func:`edge_strain`; NaN for vertices without a valid edge.
    """
    d = resolve_device(device)
    pts, batched = _frames("points", points)
    f = check_faces(faces, pts.shape[1])
    edges = mesh_edges(f)
    strain = edge_strain(pts, rest_points, edges, device=d)
    offsets, items = incidence(edges, pts.shape[1])
    (out,) = _launch(K.vertex_extreme_kernel, (pts.shape[0], pts.shape[1]),
                     [wp.array(strain, dtype=float, device=d),
                      wp.array(offsets, dtype=wp.int32, device=d),
                      wp.array(items, dtype=wp.int32, device=d)],
                     [wp.empty((pts.shape[0], pts.shape[1]), dtype=float, device=d)], d)
    return _result(out, batched)


def _normals(pts, faces, per, device):
    """Area-weighted face normals, or unit vertex normals, as a device array (F, T|V)."""
    frames, count = pts.shape[0], pts.shape[1]
    fn = wp.empty((frames, faces.shape[0]), dtype=wp.vec3, device=device)
    wp.launch(K.face_normal_kernel, dim=fn.shape,
              inputs=[_vec3s(pts, device), wp.array(faces, dtype=wp.vec3i, device=device)],
              outputs=[fn], device=device)
    if per == "face":
        return fn
    offsets, items = incidence(faces, count)
    vn = wp.empty((frames, count), dtype=wp.vec3, device=device)
    wp.launch(K.vertex_normal_kernel, dim=vn.shape,
              inputs=[fn, wp.array(offsets, dtype=wp.int32, device=device),
                      wp.array(items, dtype=wp.int32, device=device)],
              outputs=[vn], device=device)
    return vn


def normal_deviation(points, faces, reference_points=None, *, reference_normals=None,
                     per="vertex", device=None):
    """Angle between the surface normals of ``points`` and reference normals.

    The reference is either another pose of the same mesh (``reference_points``: e.g. the other
    skinning method, or the rest pose moved rigidly), whose normals are computed the same way, or
    given directions (``reference_normals``: e.g. rest normals skinned with
    :func:`dqskin.skin_normals`).

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    faces : (T, 3) int
    reference_points : (V, 3) or (F, V, 3) float, optional
    reference_normals : (N, 3) or (F, N, 3) float, optional
        N = V for ``per="vertex"``, T for ``per="face"``; need not be unit length.
    per : {"vertex", "face"}
        Face normals (right-hand winding) or unit area-weighted vertex normals.

    Returns
    -------
    (N,) or (F, N) float32
        Radians in [0, π]; NaN where a normal has zero length.
    """
    if per not in ("vertex", "face"):
        raise ValueError(f'per must be "vertex" or "face", got {per!r}')
    if (reference_points is None) == (reference_normals is None):
        raise ValueError("give exactly one of reference_points and reference_normals")
    d = resolve_device(device)
    pts, batched = _frames("points", points)
    f = check_faces(faces, pts.shape[1])
    normals = _normals(pts, f, per, d)
    count = normals.shape[1]
    if reference_points is not None:
        ref = _normals(_reference("reference_points", reference_points, pts.shape[0],
                                  pts.shape[1]), f, per, d)
    else:
        r = np.asarray(reference_normals, dtype=np.float64)
        r = r[None] if r.ndim == 2 else r
        if r.ndim != 3 or r.shape[0] not in (1, pts.shape[0]) or r.shape[1:] != (count, 3):
            raise ValueError(f"reference_normals: expected ({count}, 3) or ({pts.shape[0]}, "
                             f"{count}, 3) for per={per!r}, got {np.shape(reference_normals)}")
        ref = _vec3s(r, d)
    (angles,) = _launch(K.angle_kernel, normals.shape, [normals, ref],
                        [wp.empty(normals.shape, dtype=float, device=d)], d)
    return _result(angles, batched)


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
    pts, batched = _frames("points", points)
    ref = _reference("reference_points", reference_points, pts.shape[0], pts.shape[1])
    (dist,) = _launch(K.distance_kernel, pts.shape[:2], [_vec3s(pts, d), _vec3s(ref, d)],
                      [wp.empty(pts.shape[:2], dtype=float, device=d)], d)
    return _result(dist, batched)


def local_volume_ratio(points, rest_points, faces, apex, rest_apex, *, min_elevation=0.25,
                       device=None):
    """Per-vertex volume change of the cone from an inner apex to the vertex's one-ring.

    For vertex ``v`` with apex ``q_v`` (a point inside the body that moves with it, e.g. its
    dominant joint's bone axis, :func:`joint_axis_apex`), the one-ring cone volume is
    ``C_v = Σ_{t ∋ v} (a−q_v)·((b−q_v)×(c−q_v)) / 6`` over the faces ``t = (a, b, c)`` around
    ``v``: the volume of flesh between the apex and that skin patch. The result is
    ``C_v(posed) / C_v(rest)``: 1 under rigid motion of the patch with its apex, ``s³`` under a
    uniform scale ``s`` about the apex, ``k²`` where a limb's cross-section shrinks by ``k``
    about an axis through the apex (candy wrapper). Works on open meshes. The ratio is left
    undefined (NaN) where the rest apex does not lie clearly behind the patch: the cone's mean
    height ``3·C_v / area`` must be at least ``min_elevation × |v − q_v|``.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
    rest_points : (V, 3) float
    faces : (T, 3) int
    apex : (V, 3) or (F, V, 3) float
        Posed apex per vertex.
    rest_apex : (V, 3) float
        Rest apex per vertex.
    min_elevation : float
        In [0, 1]: 1 asks for the apex straight under the patch, 0 accepts any positive volume.

    Returns
    -------
    (V,) or (F, V) float64
        NaN where the rest cone is too flat or inverted (see above).
    """
    d = resolve_device(device)
    pts, batched = _frames("points", points)
    count = pts.shape[1]
    rest = _reference("rest_points", rest_points, 1, count)
    f = check_faces(faces, count)
    q = _reference("apex", apex, pts.shape[0], count)
    q0 = _reference("rest_apex", rest_apex, 1, count)
    offsets, items = incidence(f, count)
    topo = [wp.array(f, dtype=wp.vec3i, device=d), wp.array(offsets, dtype=wp.int32, device=d),
            wp.array(items, dtype=wp.int32, device=d)]

    def cones(p, a):
        c, area = _launch(K.fan_volume_kernel, p.shape[:2], [_vec3s(p, d), _vec3s(a, d)] + topo,
                          [wp.empty(p.shape[:2], dtype=float, device=d) for _ in range(2)], d)
        return c.astype(np.float64), area.astype(np.float64)

    c0, area0 = cones(rest, q0)
    distance = np.linalg.norm(rest[0] - q0[0], axis=1)
    usable = (c0[0] > 0) & (3 * c0[0] >= min_elevation * area0[0] * distance)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(usable, cones(pts, q)[0] / c0, np.nan)
    return _result(ratio, batched)


def _influences(joint_indices, joint_weights):
    idx, _ = check_influences(joint_indices, joint_weights)
    return idx, np.asarray(joint_weights, dtype=np.float64).reshape(idx.shape)


def joint_axis_apex(rest_points, joint_indices, joint_weights, bind_positions, parents,
                    skinning_transforms):
    """Per-vertex apex on the dominant joint's bone axis, at rest and posed
    (for :func:`local_volume_ratio`).

    A vertex's dominant joint ``j`` is its largest-weight influence (earliest slot on ties). The
    axis of ``j`` is the line through its bind position along the normalized sum of the unit
    directions to its children, or from its parent for a leaf. The rest apex is the orthogonal
    projection of the rest point onto that axis (the joint itself for a childless root, or where
    the directions cancel); the posed apex is the rest apex moved by ``j``'s skinning transform, so
    it follows the joint rigidly.

    Parameters
    ----------
    rest_points : (V, 3) float
        Bind-space rest points.
    joint_indices, joint_weights : (V, K)
    bind_positions : (J, 3) float
        Bind-space joint positions (translation of the world bind transforms).
    parents : (J,) int
        Parent joint, -1 for roots, parents before children.
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        Bind-relative joint transforms, column-vector convention.

    Returns
    -------
    rest_apex : (V, 3) float64
    apex : (V, 3) or (F, V, 3) float64
    """
    rest, _ = _frames("rest_points", rest_points)
    if rest.shape[0] != 1:
        raise ValueError(f"rest_points: expected (V, 3), got {np.shape(rest_points)}")
    rest = rest[0]
    idx, w = _influences(joint_indices, joint_weights)
    if idx.shape[0] != rest.shape[0]:
        raise ValueError(f"joint_indices: expected {rest.shape[0]} rows, got {idx.shape[0]}")
    pos = np.asarray(bind_positions, dtype=np.float64)
    par = _parents(parents, pos.shape[0] if pos.ndim == 2 else -1)
    if pos.shape != (par.shape[0], 3):
        raise ValueError(f"bind_positions: expected ({par.shape[0]}, 3), got {pos.shape}")
    x = np.asarray(skinning_transforms, dtype=np.float64)
    if x.shape[-3:] != (par.shape[0], 4, 4) or x.ndim not in (3, 4):
        raise ValueError(f"skinning_transforms: expected ({par.shape[0]}, 4, 4) or (F, "
                         f"{par.shape[0]}, 4, 4), got {x.shape}")
    directions = np.zeros_like(pos)
    child = np.flatnonzero(par >= 0)
    bone = pos[child] - pos[par[child]]
    length = np.linalg.norm(bone, axis=1, keepdims=True)
    unit = np.divide(bone, length, out=np.zeros_like(bone), where=length > 0)
    np.add.at(directions, par[child], unit)
    leaf = np.linalg.norm(directions, axis=1) == 0
    directions[leaf & (par >= 0)] = unit[np.searchsorted(child, np.flatnonzero(leaf & (par >= 0)))]
    norm = np.linalg.norm(directions, axis=1, keepdims=True)
    directions = np.divide(directions, norm, out=np.zeros_like(directions), where=norm > 1e-9)
    dominant = idx[np.arange(idx.shape[0]), np.argmax(w, axis=1)]
    if dominant.size and (dominant.min() < 0 or dominant.max() >= par.shape[0]):
        raise ValueError(f"joint_indices: index out of range [0, {par.shape[0]})")
    origin, u = pos[dominant], directions[dominant]
    rest_apex = origin + np.sum((rest - origin) * u, axis=1, keepdims=True) * u
    m = x[..., dominant, :, :]
    apex = np.einsum("...vij,vj->...vi", m[..., :3, :3], rest_apex) + m[..., :3, 3]
    return rest_apex, apex


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
    idx, w = _influences(joint_indices, joint_weights)
    par = _parents(parents, -1)
    regions = np.full(idx.shape[0], -1, dtype=np.int32)
    if idx.shape[1] < 2 or idx.shape[0] == 0:
        return regions
    if idx.min() < 0 or idx.max() >= par.shape[0]:
        raise ValueError(f"joint_indices: index out of range [0, {par.shape[0]})")
    order = np.argsort(-w, axis=1, kind="stable")[:, :2]
    rows = np.arange(idx.shape[0])[:, None]
    (a, b), wb = idx[rows, order].T, w[rows, order][:, 1]
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
    pts, _ = _frames("points", points)
    frames, count = pts.shape[:2]
    rest = _reference("rest_points", rest_points, 1, count)
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
        f = p.shape[0]
        return (a.astype(np.float64) for a in _launch(
            K.axis_coordinates_kernel, (f, count),
            [_vec3s(p, d), reg_w, _vec3s(seg[:, :, 1], d), _vec3s(seg[:, :, 1] - seg[:, :, 0], d)],
            [wp.empty((f, count), dtype=float, device=d) for _ in range(2)], d))

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
