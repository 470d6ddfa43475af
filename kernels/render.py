"""Ray-casting kernels of the offscreen renderer: vertex normals, shading, box downsampling.

One ray per (super-sampled) pixel is cast against a ``wp.Mesh`` BVH with
``wp.mesh_query_ray``. Surfaces are two-sided: the normal is flipped to face the viewer. Shading is
Lambert with one directional light plus an ambient term and a white rim light,
``c = albedo·(ambient + diffuse·max(n·l, 0)) + rim·(1 − max(n·v, 0))^rim_power`` where ``v`` points
from the surface to the eye. The albedo is either a constant colour or a colour-map lookup of a
per-vertex scalar interpolated barycentrically. Pixel rows run top to bottom; row-major pixel
index ``i = y·width + x``.
"""

import warp as wp

from .grid import launch, launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.struct
class CameraParams:
    """A camera on the device. ``half_w``/``half_h``: tangents of the half field of view
    (perspective) or half extents in world units (orthographic)."""

    eye: wp.vec3
    forward: wp.vec3
    right: wp.vec3
    up: wp.vec3
    half_w: float
    half_h: float
    orthographic: int


@wp.struct
class ShadingParams:
    """Light and colours; ``light`` is the unit world direction from the surface to the light."""

    light: wp.vec3
    base_color: wp.vec3
    background: wp.vec3
    ambient: float
    diffuse: float
    rim: float
    rim_power: float
    lit: int
    smooth: int


@wp.kernel
def vertex_normals_kernel(
    points: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.int32),
    vf_offsets: wp.array(dtype=wp.int32),
    vf_faces: wp.array(dtype=wp.int32),
    row_offset: int,
    # output
    normals: wp.array(dtype=wp.vec3),
):
    """Unit area-weighted vertex normals, gathered over each vertex's faces (CSR ``vf_*``)."""
    v = wp.tid() + row_offset
    n = wp.vec3(0.0)
    for k in range(vf_offsets[v], vf_offsets[v + 1]):
        f = vf_faces[k]
        a = points[faces[3 * f]]
        n += wp.cross(points[faces[3 * f + 1]] - a, points[faces[3 * f + 2]] - a)
    normals[v] = wp.normalize(n)


@wp.func
def colormap(lut: wp.array(dtype=wp.vec3), t: float):
    """Linear interpolation in a colour lookup table at ``t`` in [0, 1] (clamped)."""
    n = lut.shape[0]
    x = wp.clamp(t, 0.0, 1.0) * float(n - 1)
    i0 = wp.min(int(wp.floor(x)), n - 1)
    i1 = wp.min(i0 + 1, n - 1)
    return wp.lerp(lut[i0], lut[i1], x - float(i0))


@wp.func
def camera_ray_origin(cam: CameraParams, x: float, y: float):
    if cam.orthographic != 0:
        return cam.eye + (x * cam.half_w) * cam.right + (y * cam.half_h) * cam.up
    return cam.eye


@wp.func
def camera_ray_direction(cam: CameraParams, x: float, y: float):
    if cam.orthographic != 0:
        return cam.forward
    return wp.normalize(cam.forward + (x * cam.half_w) * cam.right + (y * cam.half_h) * cam.up)


@wp.kernel
def render_kernel(
    mesh: wp.uint64,
    faces: wp.array(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    scalars: wp.array(dtype=float),
    lut: wp.array(dtype=wp.vec3),
    scalar_min: float,
    scalar_scale: float,
    nan_color: wp.vec3,
    cam: CameraParams,
    shading: ShadingParams,
    width: int,
    height: int,
    row_offset: int,
    # output: straight RGB and coverage per super-sampled pixel
    image: wp.array(dtype=wp.vec4),
):
    """Shade one super-sampled pixel (row-major index ``row_offset + tid``).

    ``scalars`` empty → constant ``base_color``; else the albedo is
    ``lut((s − scalar_min)·scalar_scale)`` with ``s`` interpolated barycentrically, or
    ``nan_color`` where ``s`` is not finite.
    """
    i = wp.tid() + row_offset
    px = i % width
    py = i // width
    x = 2.0 * (float(px) + 0.5) / float(width) - 1.0
    y = 1.0 - 2.0 * (float(py) + 0.5) / float(height)
    origin = camera_ray_origin(cam, x, y)
    d = camera_ray_direction(cam, x, y)
    q = wp.mesh_query_ray(mesh, origin, d, 1.0e30)
    if not q.result:
        image[i] = wp.vec4(shading.background[0], shading.background[1], shading.background[2],
                           0.0)
        return
    f = q.face
    ia = faces[3 * f]
    ib = faces[3 * f + 1]
    ic = faces[3 * f + 2]
    w = 1.0 - q.u - q.v
    geometric = wp.normalize(q.normal)
    n = geometric
    if shading.smooth != 0:
        s = q.u * normals[ia] + q.v * normals[ib] + w * normals[ic]
        if wp.length(s) > 0.0:
            n = wp.normalize(s)
    if wp.dot(geometric, d) > 0.0:
        n = -n
    albedo = shading.base_color
    if scalars.shape[0] > 0:
        value = q.u * scalars[ia] + q.v * scalars[ib] + w * scalars[ic]
        if wp.isfinite(value):
            albedo = colormap(lut, (value - scalar_min) * scalar_scale)
        else:
            albedo = nan_color
    c = albedo
    if shading.lit != 0:
        lambert = wp.max(wp.dot(n, shading.light), 0.0)
        facing = wp.max(-wp.dot(n, d), 0.0)
        rim = shading.rim * wp.pow(1.0 - facing, shading.rim_power)
        c = albedo * (shading.ambient + shading.diffuse * lambert) + wp.vec3(rim)
    image[i] = wp.vec4(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0),
                       wp.clamp(c[2], 0.0, 1.0), 1.0)


@wp.func
def to_byte(c: float):
    return wp.uint8(int(wp.clamp(c, 0.0, 1.0) * 255.0 + 0.5))


@wp.kernel
def downsample_kernel(
    image: wp.array(dtype=wp.vec4),
    factor: int,
    transparent: int,
    # output (height, width, 4), row 0 at the top
    out: wp.array3d(dtype=wp.uint8),
):
    """Box-filter ``factor × factor`` super-samples into one 8-bit RGBA pixel.

    Opaque: the plain mean of the samples (misses hold the background colour). Transparent: RGB is
    the coverage-weighted mean (straight alpha) and alpha the mean coverage.
    """
    y, x = wp.tid()
    width = out.shape[1] * factor
    total = wp.vec3(0.0)
    weighted = wp.vec3(0.0)
    coverage = float(0.0)
    for dy in range(factor):
        row = (y * factor + dy) * width + x * factor
        for dx in range(factor):
            s = image[row + dx]
            rgb = wp.vec3(s[0], s[1], s[2])
            total += rgb
            weighted += s[3] * rgb
            coverage += s[3]
    count = float(factor * factor)
    rgb = total / count
    alpha = float(1.0)
    if transparent != 0:
        alpha = coverage / count
        if coverage > 0.0:
            rgb = weighted / coverage
    out[y, x, 0] = to_byte(rgb[0])
    out[y, x, 1] = to_byte(rgb[1])
    out[y, x, 2] = to_byte(rgb[2])
    out[y, x, 3] = to_byte(alpha)


# ---------------------------------------------------------------------------------------------
# launchers: keyword arguments, chunked over the CPU cores by dqskin.kernels.grid


def vertex_normals(*, points, faces, vf_offsets, vf_faces, out, device):
    """Unit area-weighted normals of ``points`` (V,) into ``out`` (V,); ``faces`` (3T,) int32
    flat triangles, ``vf_offsets`` (V+1,) and ``vf_faces`` the vertex → face CSR lists."""
    launch_rows(vertex_normals_kernel, out.shape[0], [points, faces, vf_offsets, vf_faces], [out],
                device)


def render(*, mesh, faces, normals, scalars, lut, scalar_min, scalar_scale, nan_color, camera,
           shading, width, height, out, device):
    """Ray cast every super-sampled pixel of a ``width × height`` image into ``out``
    (width·height,) ``wp.vec4``; ``mesh`` is a ``wp.Mesh`` id (see :func:`render_kernel` for the
    other arguments)."""
    launch_rows(render_kernel, width * height,
                [mesh, faces, normals, scalars, lut, float(scalar_min), float(scalar_scale),
                 nan_color, camera, shading, int(width), int(height)], [out], device)


def downsample(*, samples, factor, transparent, out, device):
    """Box-filter ``samples`` (H·factor · W·factor,) ``wp.vec4`` into the 8-bit RGBA ``out``
    (H, W, 4)."""
    launch(downsample_kernel, out.shape[:2], [samples, int(factor), int(transparent)], [out],
           device)
