"""Per-face, per-edge and per-vertex kernels of the artifact metrics, batched over frames.

Launch grids are ``(frames, items)``. Point arrays are ``(F, V)`` of ``wp.vec3``; a reference array
with one frame (``shape[0] == 1``) is broadcast over all frames. Faces are ``wp.vec3i`` triangles,
edges ``wp.vec2i``; vertex → face / vertex → edge adjacency is CSR (``offsets (V+1,)``, ``items``).
Undefined values (zero-length references, vertices outside any region) are written as NaN.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # forward-only kernels



@wp.func
def ref_frame(f: int, frames: int):
    """Frame of a reference array: ``f``, or 0 when the reference has a single frame."""
    return wp.min(f, frames - 1)


@wp.func
def nan():
    return wp.nan


@wp.kernel
def face_volume_kernel(
    points: wp.array2d(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    origins: wp.array(dtype=wp.vec3),
    # output
    volumes: wp.array2d(dtype=float),
):
    """Signed volume of the tetrahedron (origin, a, b, c): ``(a−o)·((b−o)×(c−o)) / 6``."""
    f, t = wp.tid()
    tri = faces[t]
    o = origins[f]
    a = points[f, tri[0]] - o
    b = points[f, tri[1]] - o
    c = points[f, tri[2]] - o
    volumes[f, t] = wp.dot(a, wp.cross(b, c)) / 6.0


@wp.kernel
def face_normal_kernel(
    points: wp.array2d(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    # output
    normals: wp.array2d(dtype=wp.vec3),
):
    """Area-weighted face normal ``(b − a) × (c − a)`` (twice the area, right-hand winding)."""
    f, t = wp.tid()
    tri = faces[t]
    a = points[f, tri[0]]
    normals[f, t] = wp.cross(points[f, tri[1]] - a, points[f, tri[2]] - a)


@wp.kernel
def vertex_normal_kernel(
    face_normals: wp.array2d(dtype=wp.vec3),
    vf_offsets: wp.array(dtype=wp.int32),
    vf_faces: wp.array(dtype=wp.int32),
    # output
    normals: wp.array2d(dtype=wp.vec3),
):
    """Unit vertex normal: normalized sum of the area-weighted normals of the incident faces."""
    f, v = wp.tid()
    n = wp.vec3(0.0)
    for k in range(vf_offsets[v], vf_offsets[v + 1]):
        n += face_normals[f, vf_faces[k]]
    normals[f, v] = wp.normalize(n)


@wp.kernel
def angle_kernel(
    vectors: wp.array2d(dtype=wp.vec3),
    reference: wp.array2d(dtype=wp.vec3),
    # output
    angles: wp.array2d(dtype=float),
):
    """Angle in radians between two vectors, ``atan2(|a×b|, a·b)``; NaN if either is zero."""
    f, i = wp.tid()
    a = vectors[f, i]
    b = reference[ref_frame(f, reference.shape[0]), i]
    if wp.length(a) == 0.0 or wp.length(b) == 0.0:
        angles[f, i] = nan()
    else:
        angles[f, i] = wp.atan2(wp.length(wp.cross(a, b)), wp.dot(a, b))


@wp.kernel
def edge_strain_kernel(
    points: wp.array2d(dtype=wp.vec3),
    rest_points: wp.array2d(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec2i),
    # output
    strain: wp.array2d(dtype=float),
):
    """Engineering strain ``|p_a − p_b| / |r_a − r_b| − 1``; NaN for zero-length rest edges."""
    f, e = wp.tid()
    ab = edges[e]
    rf = ref_frame(f, rest_points.shape[0])
    rest = wp.length(rest_points[rf, ab[0]] - rest_points[rf, ab[1]])
    if rest == 0.0:
        strain[f, e] = nan()
    else:
        strain[f, e] = wp.length(points[f, ab[0]] - points[f, ab[1]]) / rest - 1.0


@wp.kernel
def vertex_extreme_kernel(
    values: wp.array2d(dtype=float),
    offsets: wp.array(dtype=wp.int32),
    items: wp.array(dtype=wp.int32),
    # output
    extremes: wp.array2d(dtype=float),
):
    """Per vertex, the incident value of largest magnitude (sign kept); NaN when none is finite."""
    f, v = wp.tid()
    best = float(0.0)
    found = int(0)
    for k in range(offsets[v], offsets[v + 1]):
        x = values[f, items[k]]
        if wp.isfinite(x):
            if found == 0 or wp.abs(x) > wp.abs(best):
                best = x
            found = 1
    if found == 0:
        best = nan()
    extremes[f, v] = best


@wp.kernel
def distance_kernel(
    points: wp.array2d(dtype=wp.vec3),
    reference: wp.array2d(dtype=wp.vec3),
    # output
    distances: wp.array2d(dtype=float),
):
    """Euclidean distance between corresponding points."""
    f, v = wp.tid()
    distances[f, v] = wp.length(points[f, v] - reference[ref_frame(f, reference.shape[0]), v])


@wp.kernel
def fan_volume_kernel(
    points: wp.array2d(dtype=wp.vec3),
    apex: wp.array2d(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    vf_offsets: wp.array(dtype=wp.int32),
    vf_faces: wp.array(dtype=wp.int32),
    # outputs
    volumes: wp.array2d(dtype=float),
    areas: wp.array2d(dtype=float),
):
    """Signed volume of the cone from the vertex's apex to its one-ring faces,
    ``Σ_{t ∋ v} (a−q)·((b−q)×(c−q)) / 6``, and the one-ring area ``Σ_{t ∋ v} |(b−a)×(c−a)| / 2``."""
    f, v = wp.tid()
    q = apex[ref_frame(f, apex.shape[0]), v]
    total = float(0.0)
    area = float(0.0)
    for k in range(vf_offsets[v], vf_offsets[v + 1]):
        tri = faces[vf_faces[k]]
        a = points[f, tri[0]] - q
        b = points[f, tri[1]] - q
        c = points[f, tri[2]] - q
        total += wp.dot(a, wp.cross(b, c))
        area += wp.length(wp.cross(b - a, c - a))
    volumes[f, v] = total / 6.0
    areas[f, v] = area / 2.0


@wp.kernel
def axis_coordinates_kernel(
    points: wp.array2d(dtype=wp.vec3),
    regions: wp.array(dtype=wp.int32),
    origins: wp.array2d(dtype=wp.vec3),
    directions: wp.array2d(dtype=wp.vec3),
    # outputs
    axial: wp.array2d(dtype=float),
    radial: wp.array2d(dtype=float),
):
    """Cylindrical coordinates about the vertex's region axis (line through ``origins[f, r]``
    along ``directions[f, r]``): signed axial coordinate and radial distance. NaN when the vertex
    has no region (``-1``) or the axis direction has zero length."""
    f, v = wp.tid()
    r = regions[v]
    if r < 0:
        axial[f, v] = nan()
        radial[f, v] = nan()
        return
    d = directions[f, r]
    if wp.length(d) == 0.0:
        axial[f, v] = nan()
        radial[f, v] = nan()
        return
    u = wp.normalize(d)
    p = points[f, v] - origins[f, r]
    s = wp.dot(p, u)
    axial[f, v] = s
    radial[f, v] = wp.length(p - s * u)
