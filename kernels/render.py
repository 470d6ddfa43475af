"""Ray-casting kernels of the offscreen renderer: vertex normals, shading, box downsampling,
adaptive anti-aliasing.

One ray per (super-sampled) pixel is cast against a ``wp.Mesh`` BVH with
``wp.mesh_query_ray``; with adaptive anti-aliasing, one per pixel and the super-sampled grid only
for pixels on an edge (:func:`refine_kernel`). Each ray can shade two :class:`Layer` s (a plain
and a heat-map image of one pose). Surfaces are two-sided: the normal is flipped to face the
viewer. Shading is Lambert with one directional light plus an ambient term and a white rim light,
``c = albedo·(ambient + diffuse·max(n·l, 0)) + rim·(1 − max(n·v, 0))^rim_power`` where ``v`` points
from the surface to the eye. The albedo is either a constant colour or a colour-map lookup of a
per-vertex scalar interpolated barycentrically. Pixel rows run top to bottom; row-major pixel
index ``i = y·width + x``.
"""

import warp as wp

from .._warp import Device
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


@wp.func
def to_byte(c: float):
    return wp.uint8(int(wp.clamp(c, 0.0, 1.0) * 255.0 + 0.5))


@wp.struct
class Layer:
    """What one image shows of the surface a ray hits: a constant colour (``scalars`` empty) or
    a heat map ``lut((s − scalar_min)·scalar_scale)`` of per-vertex scalars interpolated
    barycentrically (``nan_color`` where ``s`` is not finite), lit by ``shading``. Two layers
    share every ray (e.g. the plain and the heat-map image of one mesh)."""

    scalars: wp.array(dtype=float)
    lut: wp.array(dtype=wp.vec3)
    scalar_min: float
    scalar_scale: float
    nan_color: wp.vec3
    shading: ShadingParams


@wp.func
def background(layer: Layer):
    bg = layer.shading.background
    return wp.vec4(bg[0], bg[1], bg[2], 0.0)


@wp.func
def shade_hit(faces: wp.array(dtype=wp.int32), normals: wp.array(dtype=wp.vec3), layer: Layer,
              face: int, u: float, v: float, geometric: wp.vec3, d: wp.vec3):
    """Straight RGB and coverage 1 of a hit on ``face`` at barycentrics ``(u, v)`` seen along
    ``d``, and the viewer-facing shading normal."""
    shading = layer.shading
    ia = faces[3 * face]
    ib = faces[3 * face + 1]
    ic = faces[3 * face + 2]
    w = 1.0 - u - v
    g = wp.normalize(geometric)
    n = g
    if shading.smooth != 0:
        s = u * normals[ia] + v * normals[ib] + w * normals[ic]
        if wp.length(s) > 0.0:
            n = wp.normalize(s)
    if wp.dot(g, d) > 0.0:
        n = -n
    albedo = shading.base_color
    if layer.scalars.shape[0] > 0:
        value = u * layer.scalars[ia] + v * layer.scalars[ib] + w * layer.scalars[ic]
        if wp.isfinite(value):
            albedo = colormap(layer.lut, (value - layer.scalar_min) * layer.scalar_scale)
        else:
            albedo = layer.nan_color
    c = albedo
    if shading.lit != 0:
        lambert = wp.max(wp.dot(n, shading.light), 0.0)
        facing = wp.max(-wp.dot(n, d), 0.0)
        rim = shading.rim * wp.pow(1.0 - facing, shading.rim_power)
        c = albedo * (shading.ambient + shading.diffuse * lambert) + wp.vec3(rim)
    color = wp.vec4(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0),
                    wp.clamp(c[2], 0.0, 1.0), 1.0)
    return color, n


@wp.func
def trace(mesh: wp.uint64, faces: wp.array(dtype=wp.int32), normals: wp.array(dtype=wp.vec3),
          cam: CameraParams, a: Layer, b: Layer, layers: int, x: float, y: float):
    """Cast the ray through normalized device coordinates ``(x, y)`` and shade what it hits in
    layer ``a`` (and ``b`` when ``layers`` is 2).

    Returns ``(colour a, colour b, depth, normal)``: straight RGB and coverage
    (``(background, 0)`` on a miss), the hit distance along the ray (-1 on a miss) and the
    viewer-facing shading normal of layer ``a``.
    """
    d = camera_ray_direction(cam, x, y)
    q = wp.mesh_query_ray(mesh, camera_ray_origin(cam, x, y), d, 1.0e30)
    if not q.result:
        return background(a), background(b), -1.0, wp.vec3(0.0)
    ca, n = shade_hit(faces, normals, a, q.face, q.u, q.v, q.normal, d)
    cb = background(b)
    if layers > 1:
        cb, nb = shade_hit(faces, normals, b, q.face, q.u, q.v, q.normal, d)
    return ca, cb, q.t, n


@wp.kernel
def render_centres_kernel(
    mesh: wp.uint64,
    faces: wp.array(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    cam: CameraParams,
    a: Layer,
    b: Layer,
    layers: int,
    width: int,
    height: int,
    row_offset: int,
    # outputs: per pixel, the centre sample's colours, hit distance (-1: miss) and normal
    centres_a: wp.array(dtype=wp.vec4),
    centres_b: wp.array(dtype=wp.vec4),
    depth: wp.array(dtype=float),
    facing: wp.array(dtype=wp.vec3),
):
    """One ray through the centre of each pixel (row-major index ``row_offset + tid``), shaded
    by :func:`trace`: every sample of full super-sampling (on the super-sampled grid), or the
    first pass of adaptive anti-aliasing. ``centres_b`` is written when ``layers`` is 2."""
    i = wp.tid() + row_offset
    x = 2.0 * (float(i % width) + 0.5) / float(width) - 1.0
    y = 1.0 - 2.0 * (float(i // width) + 0.5) / float(height)
    ca, cb, t, n = trace(mesh, faces, normals, cam, a, b, layers, x, y)
    centres_a[i] = ca
    if layers > 1:
        centres_b[i] = cb
    depth[i] = t
    facing[i] = n


@wp.func
def discontinuous(depth: wp.array(dtype=float), facing: wp.array(dtype=wp.vec3), i: int, j: int,
                  depth_jump: float, normal_cos: float):
    """Whether the centre samples of pixels ``i`` and ``j`` straddle an edge: one hits and the
    other misses, their depths differ by more than ``depth_jump`` of the nearer one, or their
    normals by more than ``acos(normal_cos)``."""
    da = depth[i]
    db = depth[j]
    if (da < 0.0) != (db < 0.0):
        return True
    if da < 0.0:
        return False
    if wp.abs(da - db) > depth_jump * wp.min(da, db):
        return True
    return wp.dot(facing[i], facing[j]) < normal_cos


@wp.func
def write_pixel(out: wp.array3d(dtype=wp.uint8), py: int, px: int, rgb: wp.vec3, alpha: float):
    out[py, px, 0] = to_byte(rgb[0])
    out[py, px, 1] = to_byte(rgb[1])
    out[py, px, 2] = to_byte(rgb[2])
    out[py, px, 3] = to_byte(alpha)


@wp.func
def resolve(total: wp.vec3, weighted: wp.vec3, coverage: float, count: float, transparent: int):
    """Box filter of ``count`` samples: the plain mean (opaque, misses hold the background) or
    the coverage-weighted mean with the mean coverage as alpha (transparent)."""
    rgb = total / count
    alpha = float(1.0)
    if transparent != 0:
        alpha = coverage / count
        if coverage > 0.0:
            rgb = weighted / coverage
    return rgb, alpha


@wp.kernel
def refine_kernel(
    mesh: wp.uint64,
    faces: wp.array(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    cam: CameraParams,
    a: Layer,
    b: Layer,
    layers: int,
    centres_a: wp.array(dtype=wp.vec4),
    centres_b: wp.array(dtype=wp.vec4),
    depth: wp.array(dtype=float),
    facing: wp.array(dtype=wp.vec3),
    factor: int,
    transparent: int,
    depth_jump: float,
    normal_cos: float,
    row_offset: int,
    # outputs (height, width, 4) per layer, row 0 at the top
    out_a: wp.array3d(dtype=wp.uint8),
    out_b: wp.array3d(dtype=wp.uint8),
):
    """Second pass: a pixel whose centre sample differs from a 4-neighbour's
    (:func:`discontinuous`) is resampled on the ``factor × factor`` grid of full super-sampling
    and box-filtered (as :func:`downsample_kernel`); any other pixel keeps its centre sample."""
    i = wp.tid() + row_offset
    height = out_a.shape[0]
    width = out_a.shape[1]
    px = i % width
    py = i // width
    edge = bool(False)
    if px > 0:
        edge = edge or discontinuous(depth, facing, i, i - 1, depth_jump, normal_cos)
    if px + 1 < width:
        edge = edge or discontinuous(depth, facing, i, i + 1, depth_jump, normal_cos)
    if py > 0:
        edge = edge or discontinuous(depth, facing, i, i - width, depth_jump, normal_cos)
    if py + 1 < height:
        edge = edge or discontinuous(depth, facing, i, i + width, depth_jump, normal_cos)
    total_a = wp.vec3(0.0)
    weighted_a = wp.vec3(0.0)
    total_b = wp.vec3(0.0)
    weighted_b = wp.vec3(0.0)
    coverage = float(0.0)
    count = float(1.0)
    if not edge or factor == 1:
        ca = centres_a[i]
        cb = centres_b[i * (layers - 1)]  # (index 0 of an unused array: never read below)
        total_a = wp.vec3(ca[0], ca[1], ca[2])
        weighted_a = ca[3] * total_a
        total_b = wp.vec3(cb[0], cb[1], cb[2])
        weighted_b = ca[3] * total_b
        coverage = ca[3]
    else:
        sw = width * factor
        sh = height * factor
        for dy in range(factor):
            for dx in range(factor):
                x = 2.0 * (float(px * factor + dx) + 0.5) / float(sw) - 1.0
                y = 1.0 - 2.0 * (float(py * factor + dy) + 0.5) / float(sh)
                ca, cb, t, n = trace(mesh, faces, normals, cam, a, b, layers, x, y)
                sa = wp.vec3(ca[0], ca[1], ca[2])
                sb = wp.vec3(cb[0], cb[1], cb[2])
                total_a += sa
                weighted_a += ca[3] * sa
                total_b += sb
                weighted_b += ca[3] * sb
                coverage += ca[3]
        count = float(factor * factor)
    rgb, alpha = resolve(total_a, weighted_a, coverage, count, transparent)
    write_pixel(out_a, py, px, rgb, alpha)
    if layers > 1:
        rgb_b, alpha_b = resolve(total_b, weighted_b, coverage, count, transparent)
        write_pixel(out_b, py, px, rgb_b, alpha_b)


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


def vertex_normals(*, points: wp.array, faces: wp.array, vf_offsets: wp.array,
                   vf_faces: wp.array, out: wp.array, device: Device) -> None:
    """Unit area-weighted normals of ``points`` (V,) into ``out`` (V,); ``faces`` (3T,) int32
    flat triangles, ``vf_offsets`` (V+1,) and ``vf_faces`` the vertex → face CSR lists."""
    launch_rows(vertex_normals_kernel, out.shape[0], [points, faces, vf_offsets, vf_faces], [out],
                device)


def render(*, mesh: wp.uint64, faces: wp.array, normals: wp.array, camera: CameraParams,
           layer_a: Layer, layer_b: Layer, layers: int, width: int, height: int,
           out_a: wp.array, out_b: wp.array, depth: wp.array, facing: wp.array,
           device: Device) -> None:
    """Ray cast every pixel of a ``width × height`` (super-sampled) image into ``out_a`` (and
    ``out_b`` for ``layers`` = 2) (width·height,) ``wp.vec4``, hit distances into ``depth`` and
    normals into ``facing``; ``mesh`` is a ``wp.Mesh`` id, the layers :class:`Layer` (see
    :func:`render_centres_kernel`)."""
    launch_rows(render_centres_kernel, width * height,
                [mesh, faces, normals, camera, layer_a, layer_b, int(layers), int(width),
                 int(height)], [out_a, out_b, depth, facing], device)


def render_adaptive(*, mesh: wp.uint64, faces: wp.array, normals: wp.array,
                    camera: CameraParams, layer_a: Layer, layer_b: Layer, layers: int,
                    factor: int, transparent: bool, depth_jump: float, normal_cos: float,
                    centres_a: wp.array, centres_b: wp.array, depth: wp.array,
                    facing: wp.array, out_a: wp.array, out_b: wp.array,
                    device: Device) -> None:
    """Adaptive anti-aliasing into the 8-bit RGBA ``out_a`` (and ``out_b``) (H, W, 4): one ray
    per pixel (:func:`render_centres_kernel`, into the scratch arrays ``centres_*``, ``depth``,
    ``facing`` of H·W), then ``factor × factor`` rays for the pixels on an edge
    (:func:`refine_kernel`)."""
    height, width = out_a.shape[:2]
    common = [mesh, faces, normals, camera, layer_a, layer_b, int(layers)]
    render(mesh=mesh, faces=faces, normals=normals, camera=camera, layer_a=layer_a,
           layer_b=layer_b, layers=layers, width=width, height=height, out_a=centres_a,
           out_b=centres_b, depth=depth, facing=facing, device=device)
    launch_rows(refine_kernel, width * height,
                common + [centres_a, centres_b, depth, facing, int(factor), int(transparent),
                          float(depth_jump), float(normal_cos)], [out_a, out_b], device)


def downsample(*, samples: wp.array, factor: int, transparent: bool, out: wp.array,
               device: Device) -> None:
    """Box-filter ``samples`` (H·factor · W·factor,) ``wp.vec4`` into the 8-bit RGBA ``out``
    (H, W, 4)."""
    launch(downsample_kernel, out.shape[:2], [samples, int(factor), int(transparent)], [out],
           device)
