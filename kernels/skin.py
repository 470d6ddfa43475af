"""Per-vertex skinning kernels: LBS, DQS and the per-vertex LBS↔DQS blend, batched over frames.

Launch grids are ``(frames, vertices)``; any number of influences per vertex (``K`` columns,
zero-weight padding allowed). Semantics follow UsdSkel (``UsdSkelSkinPointsLBS/DQS``):

* LBS: ``p' = Σ wᵢ·Mᵢ·p`` -- weights used as given, never renormalized.
* DQS: each skinning matrix is split by the polar decomposition ``A = R·S`` into a unit dual
  quaternion ``η`` (``R``, ``t``) and a residual ``S``. If any joint of the frame has ``S ≠ I``, the
  point is first blended linearly through the residuals, ``p_s = Σ wᵢ·Sᵢ·p``; then
  ``p' = normalize(Σ ±wᵢ·ηᵢ)(p_s)``, each ``ηᵢ`` sign-flipped onto the hemisphere of the vertex's
  largest-weight joint (antipodality) and normalized per Montgomery-Smith eq. 14 (Plücker).
* blend: ``p' = (1 − b)·LBS + b·DQS`` with a per-vertex ``b`` (Maya's "weight blended").

Normals use the inverse transpose of each linear part; tangents use the linear part itself; both
are normalized after blending.
"""

import warp as wp

from .dqmath import (dq_blend_add, dq_from_rt, dq_normalize_blend, dq_real, dq_transform_point,
                     is_identity33, mat44_linear, orthonormalize_columns, polar_rotation, vec8)

LBS = wp.constant(0)
DQS = wp.constant(1)
BLEND = wp.constant(2)

RESIDUAL_TOLERANCE = wp.constant(1.0e-6)


@wp.kernel
def prepare_joints_kernel(
    xforms: wp.array2d(dtype=wp.mat44),
    # outputs
    dqs: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    normal_linears: wp.array2d(dtype=wp.mat33),
    normal_residuals: wp.array2d(dtype=wp.mat33),
    normal_rotations: wp.array2d(dtype=wp.quat),
    has_residual: wp.array(dtype=wp.int32),
):
    """Per (frame, joint): split the skinning matrix into DQ + residual and the normal matrices.

    Points and tangents: polar split ``A = R·S``. Normals: ``N = A⁻ᵀ`` split as UsdSkel does,
    ``N = Rn·(Rnᵀ·N)`` with ``Rn`` from :func:`orthonormalize_columns`.
    """
    f, j = wp.tid()
    m = xforms[f, j]
    a = mat44_linear(m)
    r = polar_rotation(a)
    s = wp.transpose(r) * a
    q = wp.normalize(wp.quat_from_matrix(r))
    dqs[f, j] = dq_from_rt(q, wp.vec3(m[0, 3], m[1, 3], m[2, 3]))
    residuals[f, j] = s
    linears[f, j] = a
    rotations[f, j] = q
    n = wp.transpose(wp.inverse(a))
    rn = orthonormalize_columns(n)
    normal_linears[f, j] = n
    normal_residuals[f, j] = wp.transpose(rn) * n
    normal_rotations[f, j] = wp.normalize(wp.quat_from_matrix(rn))
    if not is_identity33(s, RESIDUAL_TOLERANCE):
        wp.atomic_max(has_residual, f, 1)


@wp.func
def largest_weight_slot(weights: wp.array2d(dtype=float), v: int):
    """Column of the vertex's largest weight (first one on ties)."""
    best = int(0)
    for k in range(1, weights.shape[1]):
        if weights[v, k] > weights[v, best]:
            best = k
    return best


@wp.func
def dqs_fraction(method: int, blend: wp.array(dtype=float), v: int):
    if method == LBS:
        return 0.0
    if method == DQS:
        return 1.0
    return blend[v]


@wp.kernel
def skin_points_kernel(
    points: wp.array2d(dtype=wp.vec3),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=float),
    blend: wp.array(dtype=float),
    xforms: wp.array2d(dtype=wp.mat44),
    dqs: wp.array2d(dtype=vec8),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    method: int,
    vertex_offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """``points`` (Fp, V) with Fp 1 or F, bind space; ``out`` (F, V) skinned points."""
    f, i = wp.tid()
    v = i + vertex_offset
    p = points[wp.min(f, points.shape[0] - 1), v]
    b = dqs_fraction(method, blend, v)
    result = wp.vec3()
    if b < 1.0:
        acc = wp.vec3()
        for k in range(indices.shape[1]):
            w = weights[v, k]
            if w != 0.0:
                acc += wp.transform_point(xforms[f, indices[v, k]], p) * w
        result = acc * (1.0 - b)
    if b > 0.0:
        pivot = dq_real(dqs[f, indices[v, largest_weight_slot(weights, v)]])
        scaled = p
        use_residual = has_residual[f] != 0
        if use_residual:
            scaled = wp.vec3()
        acc8 = vec8()
        for k in range(indices.shape[1]):
            w = weights[v, k]
            if w != 0.0:
                j = indices[v, k]
                acc8 = dq_blend_add(acc8, dqs[f, j], w, pivot)
                if use_residual:
                    scaled += (residuals[f, j] * p) * w
        result += dq_transform_point(dq_normalize_blend(acc8), scaled) * b
    out[f, v] = result


@wp.kernel
def skin_vectors_kernel(
    vectors: wp.array2d(dtype=wp.vec3),
    vector_vertex: wp.array(dtype=wp.int32),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=float),
    blend: wp.array(dtype=float),
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    method: int,
    offset: int,
    # outputs
    out: wp.array2d(dtype=wp.vec3),
):
    """Skin directions (normals or tangents), normalized.

    ``vectors`` (Fp, N); ``vector_vertex`` (N,) maps each vector to the vertex whose influences it
    uses (identity for per-vertex data, the face-vertex map for faceVarying). For normals pass the
    inverse-transpose matrices as ``linears``/``residuals``; for tangents the matrices themselves.
    """
    f, i = wp.tid()
    n = i + offset
    v = vector_vertex[n]
    x = vectors[wp.min(f, vectors.shape[0] - 1), n]
    b = dqs_fraction(method, blend, v)
    result = wp.vec3()
    if b < 1.0:
        acc = wp.vec3()
        for k in range(indices.shape[1]):
            w = weights[v, k]
            if w != 0.0:
                acc += (linears[f, indices[v, k]] * x) * w
        result = wp.normalize(acc) * (1.0 - b)
    if b > 0.0:
        pivot = rotations[f, indices[v, largest_weight_slot(weights, v)]]
        scaled = x
        use_residual = has_residual[f] != 0
        if use_residual:
            scaled = wp.vec3()
        qsum = wp.quat(0.0, 0.0, 0.0, 0.0)
        for k in range(indices.shape[1]):
            w = weights[v, k]
            if w != 0.0:
                j = indices[v, k]
                qj = rotations[f, j]
                if wp.dot(qj, pivot) < 0.0:
                    qsum = qsum - qj * w
                else:
                    qsum = qsum + qj * w
                if use_residual:
                    scaled += (residuals[f, j] * x) * w
        if wp.length(qsum) < 1.0e-10:
            qsum = wp.quat_identity()
        result += wp.normalize(wp.quat_rotate(wp.normalize(qsum), scaled)) * b
    out[f, n] = wp.normalize(result)
