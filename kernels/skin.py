"""Per-vertex skinning kernels: LBS, DQS and the per-vertex LBS↔DQS blend, batched over frames.

Semantics follow UsdSkel (``UsdSkelSkinPointsLBS/DQS``):

* LBS: ``p' = Σ wᵢ·Mᵢ·p`` -- weights used as given, never renormalized.
* DQS: each skinning matrix is split by the polar decomposition ``A = R·S`` into a unit dual
  quaternion ``η`` (``R``, ``t``) and a residual ``S``. If any joint of the frame has ``S ≠ I``, the
  point is first blended linearly through the residuals, ``p_s = Σ wᵢ·Sᵢ·p``; then
  ``p' = normalize(Σ ±wᵢ·ηᵢ)(p_s)``, each ``ηᵢ`` sign-flipped onto the hemisphere of the vertex's
  largest-weight joint (antipodality). Normalization (Montgomery-Smith eq. 14) is folded into the
  transform: for a blend ``b = r + ε·d``, ``p' = (r·p·r* + 2·(d·r*)_vec) / |r|²``; the Plücker
  correction of eq. 14 only changes the scalar part of ``d·r*`` and so drops out.
* blend: ``p' = (1 − b)·LBS + b·DQS`` with a per-vertex ``b`` (Maya's "weight blended").

Normals use the inverse transpose of each linear part; tangents the linear part itself; both are
normalized after blending.

Influence layout (:class:`dqskin.Skinner` builds it on upload): ``indices`` (V, C) ``wp.vec4i`` and
``weights`` (V, C) ``wp.vec4`` -- ``K`` influences in ``C = ceil(K/4)`` groups of four, sorted by
descending weight and zero-padded, so slot 0 is the antipodality pivot (the largest weight, first
on ties, as UsdSkel). Grids are (frame block, vertex): a thread skins one vertex for a block of
frames, so influences are read once per block and the block's joints stay in cache.
Dual quaternions are packed :data:`vec8` in the public order ``(rw, rx, ry, rz, dw, dx, dy, dz)``.
"""

import warp as wp


from .dqmath import (RESIDUAL_TOLERANCE, dq_blend_add, dq_from_rt, dq_sign, is_identity33,
                     mat44_linear, orthonormalize_columns, polar_rotation, quat_from_rotation,
                     vec8)
from .dqmath import mat34
from .grid import launch, launch_blocks

wp.set_module_options({"enable_backward": False})  # forward-only kernels


LBS = wp.constant(0)
DQS = wp.constant(1)
BLEND = wp.constant(2)


@wp.kernel
def prepare_points_kernel(
    xforms: wp.array2d(dtype=wp.mat44),
    # outputs
    affines: wp.array2d(dtype=mat34),
    dqs: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
):
    """Per (frame, joint): 3×4 affine for LBS; polar split ``A = R·S`` into a unit dual
    quaternion and the residual ``S`` for DQS. ``has_residual`` must be
    zeroed before the launch; it is set for frames where some ``S ≠ I`` (1e-6, as UsdSkel)."""
    f, j = wp.tid()
    m = xforms[f, j]
    a = mat44_linear(m)
    r = polar_rotation(a)
    s = wp.transpose(r) * a
    q = quat_from_rotation(r)
    dqs[f, j] = dq_from_rt(q, wp.vec3(m[0, 3], m[1, 3], m[2, 3]))
    affines[f, j] = mat34(m[0, 0], m[0, 1], m[0, 2], m[0, 3],
                          m[1, 0], m[1, 1], m[1, 2], m[1, 3],
                          m[2, 0], m[2, 1], m[2, 2], m[2, 3])
    residuals[f, j] = s
    if not is_identity33(s, RESIDUAL_TOLERANCE):
        wp.atomic_max(has_residual, f, 1)


@wp.kernel
def prepare_vectors_kernel(
    xforms: wp.array2d(dtype=wp.mat44),
    # outputs
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    normal_linears: wp.array2d(dtype=wp.mat33),
    normal_residuals: wp.array2d(dtype=wp.mat33),
    normal_rotations: wp.array2d(dtype=wp.quat),
):
    """Per (frame, joint) matrices for directions. Tangents: the linear part ``A`` and its polar
    rotation (Warp quaternion). Normals:
    ``N = A⁻ᵀ`` split as UsdSkel does, ``N = Rn·(Rnᵀ·N)`` with ``Rn`` from
    :func:`orthonormalize_columns`."""
    f, j = wp.tid()
    a = mat44_linear(xforms[f, j])
    linears[f, j] = a
    rotations[f, j] = quat_from_rotation(polar_rotation(a))
    n = wp.transpose(wp.inverse(a))
    rn = orthonormalize_columns(n)
    normal_linears[f, j] = n
    normal_residuals[f, j] = wp.transpose(rn) * n
    normal_rotations[f, j] = quat_from_rotation(rn)


@wp.func
def lbs_matrix(v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
               weights: wp.array2d(dtype=wp.vec4), affines: wp.array2d(dtype=mat34)):
    """``Σ wᵢ·Aᵢ``: the vertex's 3×4 matrices blended (also their derivatives, for velocities)."""
    acc = mat34()
    for c in range(indices.shape[1]):
        iv = indices[v, c]
        wv = weights[v, c]
        for k in range(4):
            acc += affines[f, iv[k]] * wv[k]
    return acc


@wp.func
def lbs_point(p: wp.vec3, v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
              weights: wp.array2d(dtype=wp.vec4), affines: wp.array2d(dtype=mat34)):
    """``Σ wᵢ·Aᵢ·[p, 1]``, blending the 3×4 matrices first."""
    return lbs_matrix(v, f, indices, weights, affines) * wp.vec4(p[0], p[1], p[2], 1.0)


@wp.func
def dqs_blend(v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
              weights: wp.array2d(dtype=wp.vec4), dqs: wp.array2d(dtype=vec8)):
    """Sign-aligned weighted sum of the vertex's dual quaternions (pivot: slot 0)."""
    pv = dqs[f, indices[v, 0][0]]
    b = vec8()
    for c in range(indices.shape[1]):
        iv = indices[v, c]
        wv = weights[v, c]
        for k in range(4):
            b = dq_blend_add(b, dqs[f, iv[k]], wv[k], pv)
    return b


@wp.func
def dqs_blend_derivative(v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
                         weights: wp.array2d(dtype=wp.vec4), dqs: wp.array2d(dtype=vec8),
                         dq_derivatives: wp.array2d(dtype=vec8)):
    """``Σ sᵢ·wᵢ·η̇ᵢ``: the derivative of :func:`dqs_blend`, whose signs ``sᵢ`` (against the
    pivot, slot 0) are locally constant."""
    pv = dqs[f, indices[v, 0][0]]
    acc = vec8()
    for c in range(indices.shape[1]):
        iv = indices[v, c]
        wv = weights[v, c]
        for k in range(4):
            j = iv[k]
            acc += dq_derivatives[f, j] * (wv[k] * dq_sign(dqs[f, j], pv))
    return acc


@wp.func
def residual_blend(p: wp.vec3, v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
                   weights: wp.array2d(dtype=wp.vec4), residuals: wp.array2d(dtype=wp.mat33)):
    """``Σ wᵢ·Sᵢ·p``: the point blended through the joints' scale/shear residuals."""
    x = wp.vec3()
    for c in range(indices.shape[1]):
        iv = indices[v, c]
        wv = weights[v, c]
        for k in range(4):
            x += (residuals[f, iv[k]] * p) * wv[k]
    return x


@wp.func
def dqs_apply(b: vec8, x: wp.vec3):
    """Apply a blended (unnormalized) dual quaternion ``b = r + ε·d`` to ``x``, normalization
    folded in: ``x + 2·(r⃗×(r⃗×x + r_w·x) + r_w·d⃗ − d_w·r⃗ + r⃗×d⃗)/|r|²``. A zero blend (all
    weights zero) leaves ``x`` unchanged, as Gf's normalize returns the identity."""
    rv = wp.vec3(b[1], b[2], b[3])
    rw = b[0]
    dv = wp.vec3(b[5], b[6], b[7])
    s = 2.0 / wp.max(rw * rw + wp.dot(rv, rv), 1.0e-30)
    return x + s * (wp.cross(rv, wp.cross(rv, x) + rw * x) + rw * dv - b[4] * rv + wp.cross(rv, dv))


@wp.func
def dqs_point(p: wp.vec3, v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
              weights: wp.array2d(dtype=wp.vec4), dqs: wp.array2d(dtype=vec8),
              residuals: wp.array2d(dtype=wp.mat33), use_residual: bool):
    """DQS of one point: the sign-aligned DQ blend applied to the point, or, on frames with
    scale/shear, to the point blended through the residuals first."""
    b = dqs_blend(v, f, indices, weights, dqs)
    if use_residual:
        return dqs_apply(b, residual_blend(p, v, f, indices, weights, residuals))
    return dqs_apply(b, p)


@wp.kernel
def skin_lbs_kernel(
    points: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.vec4i),
    weights: wp.array2d(dtype=wp.vec4),
    affines: wp.array2d(dtype=mat34),
    frame_block: int,
    block_offset: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """LBS over a (frame block, vertex) grid; each thread skins one vertex for ``frame_block``
    frames. ``points`` (Fp, V) bind space, Fp 1 or F; ``affines`` (F, J); ``out`` (F, V)."""
    b, i = wp.tid()
    v = i + vertex_offset
    last = points.shape[0] - 1
    f0 = (b + block_offset) * frame_block
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        out[f, v] = lbs_point(points[wp.min(f, last), v], v, f, indices, weights, affines)


@wp.kernel
def skin_dqs_kernel(
    points: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.vec4i),
    weights: wp.array2d(dtype=wp.vec4),
    dqs: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    frame_block: int,
    block_offset: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """DQS over a (frame block, vertex) grid (arrays as :func:`skin_lbs_kernel`)."""
    b, i = wp.tid()
    v = i + vertex_offset
    last = points.shape[0] - 1
    f0 = (b + block_offset) * frame_block
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        out[f, v] = dqs_point(points[wp.min(f, last), v], v, f, indices, weights, dqs, residuals,
                              has_residual[f] != 0)


@wp.kernel
def skin_dqs_rigid_kernel(
    points: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.vec4i),
    weights: wp.array2d(dtype=wp.vec4),
    dqs: wp.array2d(dtype=vec8),
    frame_block: int,
    block_offset: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """DQS for launches where no joint has scale or shear (no residual code: ~18% faster on the
    CPU than :func:`skin_dqs_kernel`, which the skinner uses otherwise)."""
    b, i = wp.tid()
    v = i + vertex_offset
    last = points.shape[0] - 1
    f0 = (b + block_offset) * frame_block
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        out[f, v] = dqs_apply(dqs_blend(v, f, indices, weights, dqs), points[wp.min(f, last), v])


@wp.kernel
def skin_blend_kernel(
    points: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.vec4i),
    weights: wp.array2d(dtype=wp.vec4),
    blend: wp.array(dtype=float),
    affines: wp.array2d(dtype=mat34),
    dqs: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    frame_block: int,
    block_offset: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """Per-vertex mix ``(1 − b)·LBS + b·DQS`` with ``b = blend[v]``, over a (frame block,
    vertex) grid."""
    blk, i = wp.tid()
    v = i + vertex_offset
    last = points.shape[0] - 1
    b = blend[v]
    f0 = (blk + block_offset) * frame_block
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        p = points[wp.min(f, last), v]
        out[f, v] = (lbs_point(p, v, f, indices, weights, affines) * (1.0 - b)
                     + dqs_point(p, v, f, indices, weights, dqs, residuals,
                                 has_residual[f] != 0) * b)


@wp.func
def dqs_vector(x: wp.vec3, v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
               weights: wp.array2d(dtype=wp.vec4), rotations: wp.array2d(dtype=wp.quat),
               residuals: wp.array2d(dtype=wp.mat33), use_residual: bool):
    """Rotation-only DQS of a direction (sign-aligned quaternion blend), unit length."""
    pivot = rotations[f, indices[v, 0][0]]
    r = wp.quat(0.0, 0.0, 0.0, 0.0)
    for c in range(indices.shape[1]):
        iv = indices[v, c]
        wv = weights[v, c]
        for k in range(4):
            q = rotations[f, iv[k]]
            r += q * (wv[k] * wp.sign(wp.dot(q, pivot)))
    scaled = x
    if use_residual:
        scaled = residual_blend(x, v, f, indices, weights, residuals)
    if wp.length(r) < 1.0e-10:
        return wp.normalize(scaled)
    return wp.normalize(wp.quat_rotate(wp.normalize(r), scaled))


@wp.func
def lbs_vector(x: wp.vec3, v: int, f: int, indices: wp.array2d(dtype=wp.vec4i),
               weights: wp.array2d(dtype=wp.vec4), linears: wp.array2d(dtype=wp.mat33)):
    acc = wp.mat33()
    for c in range(indices.shape[1]):
        iv = indices[v, c]
        wv = weights[v, c]
        for k in range(4):
            acc += linears[f, iv[k]] * wv[k]
    return wp.normalize(acc * x)


@wp.kernel
def skin_vectors_kernel(
    vectors: wp.array2d(dtype=wp.vec3),
    vector_vertex: wp.array(dtype=wp.int32),
    indices: wp.array2d(dtype=wp.vec4i),
    weights: wp.array2d(dtype=wp.vec4),
    blend: wp.array(dtype=float),
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    method: int,
    frame_block: int,
    block_offset: int,
    offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """Skin directions (normals or tangents), normalized, over a (frame block, vector) grid.

    ``vectors`` (Fp, N); ``vector_vertex`` (N,) maps each vector to the vertex whose influences it
    uses (identity for per-vertex data, the face-vertex map for faceVarying). For normals pass the
    inverse-transpose matrices and the rotations UsdSkel derives from them; for tangents the
    matrices themselves and their polar rotations.
    """
    blk, i = wp.tid()
    n = i + offset
    v = vector_vertex[n]
    last = vectors.shape[0] - 1
    f0 = (blk + block_offset) * frame_block
    for f in range(f0, wp.min(f0 + frame_block, out.shape[0])):
        x = vectors[wp.min(f, last), n]
        if method == LBS:
            out[f, n] = lbs_vector(x, v, f, indices, weights, linears)
        elif method == DQS:
            out[f, n] = dqs_vector(x, v, f, indices, weights, rotations, residuals,
                                   has_residual[f] != 0)
        else:
            b = blend[v]
            out[f, n] = wp.normalize(
                lbs_vector(x, v, f, indices, weights, linears) * (1.0 - b)
                + dqs_vector(x, v, f, indices, weights, rotations, residuals,
                             has_residual[f] != 0) * b)


@wp.kernel
def transform_frames_kernel(
    xforms: wp.array(dtype=wp.mat44),
    normalize: int,
    # outputs
    values: wp.array2d(dtype=wp.vec3),
):
    """In place ``values[f, i] = xforms[f] · [values[f, i], 1]`` (points). For directions pass the
    inverse transpose with a zero translation and ``normalize = 1``."""
    f, i = wp.tid()
    y = wp.transform_point(xforms[f], values[f, i])
    if normalize != 0:
        y = wp.normalize(y)
    values[f, i] = y


# ---------------------------------------------------------------------------------------------
# launchers: keyword arguments, chunked over the CPU cores by dqskin.kernels.grid


def prepare_points(*, xforms, affines, dqs, residuals, has_residual, device):
    """Per (frame, joint) data of :func:`skin_points` from ``xforms`` (F, J) ``wp.mat44``: zeroes
    ``has_residual`` (F,) and fills the (F, J) ``affines``, ``dqs`` and ``residuals``."""
    has_residual.zero_()
    launch(prepare_points_kernel, xforms.shape, [xforms], [affines, dqs, residuals, has_residual],
           device)


def prepare_vectors(*, xforms, linears, rotations, normal_linears, normal_residuals,
                    normal_rotations, device):
    """Per (frame, joint) data of :func:`skin_vectors` (see :func:`prepare_vectors_kernel`)."""
    launch(prepare_vectors_kernel, xforms.shape, [xforms],
           [linears, rotations, normal_linears, normal_residuals, normal_rotations], device)


def skin_points(*, method, points, indices, weights, blend, affines, dqs, residuals, has_residual,
                rigid, out, device):
    """Skin ``points`` (Fp, V) into ``out`` (F, V) with ``method`` (:data:`LBS`, :data:`DQS`,
    :data:`BLEND`). ``rigid`` (no frame has a residual) selects the DQS kernel without the
    residual code; the other arrays are :func:`prepare_points`' and the influence layout."""
    head = [points, indices, weights]
    if method == LBS:
        kernel, inputs = skin_lbs_kernel, head + [affines]
    elif method == DQS and rigid:
        kernel, inputs = skin_dqs_rigid_kernel, head + [dqs]
    elif method == DQS:
        kernel, inputs = skin_dqs_kernel, head + [dqs, residuals, has_residual]
    else:
        kernel, inputs = skin_blend_kernel, head + [blend, affines, dqs, residuals, has_residual]
    launch_blocks(kernel, out.shape[1], out.shape[0], inputs, [out], device)


def skin_vectors(*, method, vectors, vector_vertex, indices, weights, blend, linears, rotations,
                 residuals, has_residual, out, device):
    """Skin directions ``vectors`` (Fp, N) into ``out`` (F, N), normalized (see
    :func:`skin_vectors_kernel` for which per-joint arrays normals and tangents take)."""
    launch_blocks(skin_vectors_kernel, out.shape[1], out.shape[0],
                  [vectors, vector_vertex, indices, weights, blend, linears, rotations, residuals,
                   has_residual, int(method)], [out], device)


def transform_frames(*, xforms, normalize, values, device):
    """In place ``values[f, i] = xforms[f]·[values[f, i], 1]`` (normalized with ``normalize``)."""
    launch(transform_frames_kernel, values.shape, [xforms, int(normalize)], [values], device)
