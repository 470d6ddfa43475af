"""Heat sources of bone-heat weights (Baran & Popović 2007, as Blender's "automatic weights"):
for every vertex, its distance to the nearest bone segment and which bones are that near *and*
visible from it (the straight segment from the vertex to the bone's closest point does not cross
the surface, cast against a ``wp.Mesh`` BVH).

One thread per vertex loops over the bones: distances to every segment, then a ray only to the
bones within ``1 + epsilon`` of the minimum (usually one), so the cost is ``V·B`` distance
evaluations and about ``V`` rays.
"""

import warp as wp

from .._warp import Device
from .grid import launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.func
def segment_closest(p: wp.vec3, head: wp.vec3, tail: wp.vec3):
    """Closest point to ``p`` on the segment ``head``–``tail`` (a point when they coincide)."""
    d = tail - head
    length2 = wp.dot(d, d)
    u = float(0.0)
    if length2 > 0.0:
        u = wp.clamp(wp.dot(p - head, d) / length2, 0.0, 1.0)
    return head + u * d


@wp.kernel
def heat_sources_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    heads: wp.array(dtype=wp.vec3),
    tails: wp.array(dtype=wp.vec3),
    epsilon: float,
    ray_offset: float,
    check_visibility: int,
    row_offset: int,
    # outputs
    min_distance: wp.array(dtype=float),
    nearest: wp.array(dtype=int),
    closest: wp.array2d(dtype=wp.int8),
):
    v = wp.tid() + row_offset
    p = points[v]
    best = float(1.0e30)
    best_bone = int(0)
    for b in range(heads.shape[0]):
        dist = wp.length(segment_closest(p, heads[b], tails[b]) - p)
        if dist < best:
            best = dist
            best_bone = b
    min_distance[v] = best
    nearest[v] = best_bone
    limit = best * (1.0 + epsilon)
    for b in range(heads.shape[0]):
        c = segment_closest(p, heads[b], tails[b])
        dist = wp.length(c - p)
        seen = int(0)
        if dist <= limit:
            seen = 1
            if check_visibility != 0 and dist > 2.0 * ray_offset:
                d = (c - p) / dist
                q = wp.mesh_query_ray(mesh, p + ray_offset * d, d, dist - 2.0 * ray_offset)
                if q.result:
                    seen = 0
        closest[v, b] = wp.int8(seen)


# ---------------------------------------------------------------------------------------------
# launcher: keyword arguments, chunked over the CPU cores by dqskin.kernels.grid


def heat_sources(*, mesh: wp.uint64, points: wp.array, heads: wp.array, tails: wp.array,
                 epsilon: float, ray_offset: float, check_visibility: bool,
                 min_distance: wp.array, nearest: wp.array, closest: wp.array,
                 device: Device) -> None:
    """Fill ``min_distance`` (V,) float, ``nearest`` (V,) int (the nearest bone) and ``closest``
    (V, B) int8 (1: within ``1 + epsilon`` of the nearest distance and visible) for ``points``
    (V,) ``wp.vec3`` and bone segments ``heads``/``tails`` (B,) ``wp.vec3``; ``mesh`` is the
    ``wp.Mesh`` id rays are cast against (visibility only with ``check_visibility``)."""
    launch_rows(heat_sources_kernel, points.shape[0],
                [mesh, points, heads, tails, float(epsilon), float(ray_offset),
                 int(check_visibility)], [min_distance, nearest, closest], device, min_chunk=2048)
