"""Per-face, per-edge and per-vertex kernels of the artifact metrics, batched over frames.

Point arrays are ``(F, V)`` of ``wp.vec3``; a reference array with one frame (``shape[0] == 1``) is
broadcast over all frames. Faces are ``wp.vec3i`` triangles, edges ``wp.vec2i``. Results are
``(F, N)`` arrays over N items (faces, edges, vertices); the grid is one thread per (frame, item),
flattened to rows ``i = f·N + n`` that :func:`dqskin.kernels.grid.launch_rows` splits across the
CPU cores. Undefined values (zero-length references, vertices outside any region) are NaN.
"""

import warp as wp

from .._warp import Device
from .grid import launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.func
def frame_item(row: int, items: int):
    """``(frame, item)`` of a flattened row ``frame·items + item``."""
    return row // items, row % items


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
    row_offset: int,
    # output
    volumes: wp.array2d(dtype=float),
):
    """Signed volume of the tetrahedron (origin, a, b, c): ``(a−o)·((b−o)×(c−o)) / 6``."""
    f, t = frame_item(wp.tid() + row_offset, volumes.shape[1])
    tri = faces[t]
    o = origins[f]
    a = points[f, tri[0]] - o
    b = points[f, tri[1]] - o
    c = points[f, tri[2]] - o
    volumes[f, t] = wp.dot(a, wp.cross(b, c)) / 6.0


@wp.kernel
def edge_strain_kernel(
    points: wp.array2d(dtype=wp.vec3),
    rest_points: wp.array2d(dtype=wp.vec3),
    edges: wp.array(dtype=wp.vec2i),
    row_offset: int,
    # output
    strain: wp.array2d(dtype=float),
):
    """Engineering strain ``|p_a − p_b| / |r_a − r_b| − 1``; NaN for zero-length rest edges."""
    f, e = frame_item(wp.tid() + row_offset, strain.shape[1])
    ab = edges[e]
    rf = ref_frame(f, rest_points.shape[0])
    rest = wp.length(rest_points[rf, ab[0]] - rest_points[rf, ab[1]])
    if rest == 0.0:
        strain[f, e] = nan()
    else:
        strain[f, e] = wp.length(points[f, ab[0]] - points[f, ab[1]]) / rest - 1.0


@wp.kernel
def distance_kernel(
    points: wp.array2d(dtype=wp.vec3),
    reference: wp.array2d(dtype=wp.vec3),
    row_offset: int,
    # output
    distances: wp.array2d(dtype=float),
):
    """Euclidean distance between corresponding points."""
    f, v = frame_item(wp.tid() + row_offset, distances.shape[1])
    distances[f, v] = wp.length(points[f, v] - reference[ref_frame(f, reference.shape[0]), v])


# ---------------------------------------------------------------------------------------------
# launchers: keyword arguments, chunked over the CPU cores by dqskin.kernels.grid


def _launch_items(kernel, inputs, outputs, device):
    """``kernel`` over every (frame, item) of ``outputs[0]`` (F, N)."""
    frames, items = outputs[0].shape
    launch_rows(kernel, frames * items, inputs, outputs, device)


def volumes(*, points: wp.array, faces: wp.array, origins: wp.array, out: wp.array,
            device: Device) -> None:
    """Signed tetrahedron volumes (see :func:`face_volume_kernel`) of ``points`` (F, V) over
    ``faces`` (T,) ``wp.vec3i`` with one ``origins`` (F,) point per frame, into ``out`` (F, T)."""
    _launch_items(face_volume_kernel, [points, faces, origins], [out], device)


def edge_strain(*, points: wp.array, rest_points: wp.array, edges: wp.array, out: wp.array,
                device: Device) -> None:
    """Strain of ``edges`` (E,) ``wp.vec2i`` between ``points`` (F, V) and ``rest_points``
    (F or 1, V), into ``out`` (F, E)."""
    _launch_items(edge_strain_kernel, [points, rest_points, edges], [out], device)


def distances(*, points: wp.array, reference: wp.array, out: wp.array,
              device: Device) -> None:
    """``|points − reference|`` per vertex, ``points`` (F, V), ``reference`` (F or 1, V), into
    ``out`` (F, V)."""
    _launch_items(distance_kernel, [points, reference], [out], device)

