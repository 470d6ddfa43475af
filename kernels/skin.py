"""Per-vertex skinning kernels: LBS, DQS, the per-vertex LBS↔DQS blend and optimized centers of
rotation (COR), batched over frames.

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
* COR (Le & Hodgins 2016): ``p' = R·(p − c) + Σ wᵢ·Aᵢ·[c, 1]`` with the vertex's precomputed
  center ``c`` (:mod:`dqskin.cor`), ``R`` the rotation of the DQS blend's real part (the same
  sign rule), ``Σ wᵢ·Sᵢ`` applied to ``p − c`` on frames with a residual; DQS where the vertex has
  no center.
* Sign rule (``Influences.running_sum``): 0, each joint's sign is taken against the pivot in slot 0
  (UsdSkel); otherwise against the running sum of the blend so far, the influences in their input
  order (Blender's Preserve Volume; the layout is then unsorted).

Normals use the inverse transpose of each linear part; tangents the linear part itself; both are
normalized after blending.

Influence layout (:class:`Influences`, built once per mesh by
:class:`dqskin.influences.Influences`): ``indices`` (V, C) ``wp.vec4i`` and ``weights`` (V, C)
``wp.vec4`` -- ``K`` influences in ``C = ceil(K/4)`` groups of four, sorted by descending weight
and zero-padded, so slot 0 is the antipodality pivot (the largest weight, first on ties, as
UsdSkel); or, ``unsorted``, in input order with the pivot searched per vertex (a one-shot call
whose ``(V, 4k)`` int32/float32 arrays are read in place: no layout pass). Per-(frame, joint)
data is a :class:`Joints` (from :func:`prepare_points`). Every kernel that blends influences --
here and in :mod:`dqskin.kernels.velocity` -- goes through the ``@wp.func`` blends below. Grids
are (frame block, row block): a thread skins its rows (one on CUDA, 64 on the CPU, where Warp's
per-thread call costs as much as a vertex) for a block of frames, so influences are read once per
block and the block's joints stay in cache. The point kernels are specialized at compile time for
the method, rigid frames and ``K <= 4``.
Dual quaternions are packed :data:`vec8` in the public order ``(rw, rx, ry, rz, dw, dx, dy, dz)``.
"""

from typing import Any

import warp as wp

from .dqmath import (
    FACTOR_EPSILON,
    RESIDUAL_TOLERANCE,
    dq_blend_add,
    dq_from_rt,
    dq_sign,
    is_identity33,
    mat34,
    mat44_linear,
    orthonormalize_columns,
    polar_rotation,
    quat_from_rotation,
    vec8,
)
from .grid import FrameBlocks, block_frames, block_rows, launch, launch_blocks

wp.set_module_options({"enable_backward": False})  # forward-only kernels


LBS = wp.constant(0)
DQS = wp.constant(1)
BLEND = wp.constant(2)
COR = wp.constant(3)


@wp.struct
class Influences:
    """A mesh's influences in the kernels' layout (see the module docstring)."""

    indices: wp.array2d(dtype=wp.vec4i)
    """(V, C) joint indices, four per group, largest weight first."""
    weights: wp.array2d(dtype=wp.vec4)
    """(V, C) weights, same layout."""
    blend: wp.array(dtype=float)
    """(V,) DQS fraction of ``method=BLEND``; empty otherwise."""
    centers: wp.array(dtype=wp.vec4)
    """(V,) centers of rotation of ``method=COR`` (bind space, ``w = 1``; ``w = 0``: none, the
    vertex falls back to DQS); empty otherwise."""
    running_sum: int
    """Sign reference of the rotation blends: 0 the pivot in slot 0 (largest weight, UsdSkel);
    nonzero the running sum of the blend so far, the slots in their input order (Blender)."""
    unsorted: int
    """Nonzero: the slots are in input order, not sorted by weight, and the pivot of
    ``running_sum = 0`` is searched per vertex (:func:`pivot_joint`)."""


@wp.struct
class Joints:
    """Per (frame, joint) data of the skinning transforms, from :func:`prepare_points_kernel`."""

    affines: wp.array2d(dtype=mat34)
    """(F, J) top rows of the 4×4 transforms (LBS)."""
    dqs: wp.array2d(dtype=vec8)
    """(F, J) unit dual quaternions of their polar rotation and translation (DQS)."""
    residuals: wp.array2d(dtype=wp.mat33)
    """(F, J) scale/shear residuals ``S = Rᵀ·A``."""
    has_residual: wp.array(dtype=wp.int32)
    """(F,) nonzero on frames where some ``S ≠ I``."""


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
    zeroed before the launch; it is set for frames where some ``S ≠ I`` (1e-6, as UsdSkel).
    A (near-)singular ``A`` (``|det A| <`` :data:`FACTOR_EPSILON`) gets a zero dual quaternion
    and ``S = I``, as UsdSkel's DQS; a non-finite one NaN, so it propagates in every method."""
    f, j = wp.tid()
    m = xforms[f, j]
    affines[f, j] = mat34(m[0, 0], m[0, 1], m[0, 2], m[0, 3],
                          m[1, 0], m[1, 1], m[1, 2], m[1, 3],
                          m[2, 0], m[2, 1], m[2, 2], m[2, 3])
    a = mat44_linear(m)
    if not wp.isfinite(m):  # device input is not checked on the host: NaN in every method
        dqs[f, j] = vec8(wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan, wp.nan)
        residuals[f, j] = a
        wp.atomic_max(has_residual, f, 1)
        return
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:
        dqs[f, j] = vec8()
        residuals[f, j] = wp.identity(n=3, dtype=float)
        return
    r = polar_rotation(a)
    s = wp.transpose(r) * a
    q = quat_from_rotation(r)
    dqs[f, j] = dq_from_rt(q, wp.vec3(m[0, 3], m[1, 3], m[2, 3]))
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
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:  # no inverse: adds nothing, as for points
        rotations[f, j] = wp.quat(0.0, 0.0, 0.0, 0.0)
        normal_linears[f, j] = wp.mat33()
        normal_residuals[f, j] = wp.identity(n=3, dtype=float)
        normal_rotations[f, j] = wp.quat(0.0, 0.0, 0.0, 0.0)
        return
    rotations[f, j] = quat_from_rotation(polar_rotation(a))
    n = wp.transpose(wp.inverse(a))
    rn = orthonormalize_columns(n)
    normal_linears[f, j] = n
    normal_residuals[f, j] = wp.transpose(rn) * n
    normal_rotations[f, j] = quat_from_rotation(rn)


@wp.func
def blend4(values: wp.array2d(dtype=Any), f: int, iv: wp.vec4i, wv: wp.vec4):
    """``Σ wᵢ·Xᵢ`` over one group of four influences of frame ``f``."""
    return (values[f, iv[0]] * wv[0] + values[f, iv[1]] * wv[1] + values[f, iv[2]] * wv[2]
            + values[f, iv[3]] * wv[3])


@wp.func
def blend_groups(inf: Influences, v: int, f: int, values: wp.array2d(dtype=Any), groups: int):
    """:func:`blend_joints` over the first ``groups`` groups (a compile-time 1 in the kernels
    specialized for ``K <= 4``: no loop)."""
    acc = blend4(values, f, inf.indices[v, 0], inf.weights[v, 0])
    for c in range(1, groups):
        acc += blend4(values, f, inf.indices[v, c], inf.weights[v, c])
    return acc


@wp.func
def blend_joints(inf: Influences, v: int, f: int, values: wp.array2d(dtype=Any)):
    """``Σ wᵢ·Xᵢ`` of the vertex's per-joint values (F, J): 3×4 affines (LBS) and their
    derivatives, 3×3 residuals ``S`` (DQS) and linear parts (directions)."""
    return blend_groups(inf, v, f, values, inf.indices.shape[1])


@wp.func
def pivot_joint(inf: Influences, v: int, groups: int):
    """The joint of the vertex's largest weight, first on ties: slot 0 of a sorted layout, else
    searched (``inf.unsorted``)."""
    iv = inf.indices[v, 0]
    j = iv[0]
    if inf.unsorted == 0:
        return j
    wv = inf.weights[v, 0]
    wm = wv[0]
    for k in range(1, 4):
        if wv[k] > wm:
            wm = wv[k]
            j = iv[k]
    for c in range(1, groups):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            if wv[k] > wm:
                wm = wv[k]
                j = iv[k]
    return j


@wp.func
def dqs_blend_groups(inf: Influences, v: int, f: int, dqs: wp.array2d(dtype=vec8), groups: int):
    """:func:`dqs_blend` over the first ``groups`` groups."""
    b = vec8()
    if inf.running_sum != 0:  # (one branch per vertex, not per influence)
        for c in range(groups):
            iv = inf.indices[v, c]
            wv = inf.weights[v, c]
            for k in range(4):
                b = dq_blend_add(b, dqs[f, iv[k]], wv[k], b)
        return b
    pv = dqs[f, pivot_joint(inf, v, groups)]
    for c in range(groups):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            b = dq_blend_add(b, dqs[f, iv[k]], wv[k], pv)
    return b


@wp.func
def dqs_blend(inf: Influences, v: int, f: int, dqs: wp.array2d(dtype=vec8)):
    """Sign-aligned weighted sum of the vertex's dual quaternions (pivot: slot 0, or the running
    sum with ``inf.running_sum``; a zero sum flips nothing)."""
    return dqs_blend_groups(inf, v, f, dqs, inf.indices.shape[1])


@wp.func
def dqs_blend_derivative(inf: Influences, v: int, f: int, dqs: wp.array2d(dtype=vec8),
                         dq_derivatives: wp.array2d(dtype=vec8)):
    """``Σ sᵢ·wᵢ·η̇ᵢ``: the derivative of :func:`dqs_blend`, whose signs ``sᵢ`` (the same rule)
    are locally constant."""
    pv = dqs[f, pivot_joint(inf, v, inf.indices.shape[1])]
    b = vec8()
    acc = vec8()
    for c in range(inf.indices.shape[1]):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            if inf.running_sum != 0:
                pv = b
            j = iv[k]
            sw = wv[k] * dq_sign(dqs[f, j], pv)
            b += dqs[f, j] * sw
            acc += dq_derivatives[f, j] * sw
    return acc


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
def rotation_only(b: vec8):
    """The real part of a blend, dual part zeroed: :func:`dqs_apply` then only rotates."""
    return vec8(b[0], b[1], b[2], b[3], 0.0, 0.0, 0.0, 0.0)


@wp.func
def by_method(inf: Influences, v: int, method: int, lbs: wp.vec3, dqs: wp.vec3):
    """The result of ``method``: ``lbs``, ``dqs`` (also for COR, whose directions rotate as DQS's)
    or their per-vertex blend ``(1 − b)·lbs + b·dqs``, ``b = inf.blend[v]``."""
    if method == LBS:
        return lbs
    if method == DQS or method == COR:
        return dqs
    b = inf.blend[v]
    return lbs * (1.0 - b) + dqs * b


@wp.func
def skin_point(p: wp.vec3, inf: Influences, v: int, f: int, joints: Joints, method: int,
               residual: bool, groups: int):
    """One point skinned with ``method`` (``residual``: the frame may have scale/shear) from the
    vertex's first ``groups`` influence groups."""
    if method == LBS:
        return blend_groups(inf, v, f, joints.affines, groups) * wp.vec4(p[0], p[1], p[2], 1.0)
    if method == COR:
        c4 = inf.centers[v]
        if c4[3] != 0.0:
            c = wp.vec3(c4[0], c4[1], c4[2])
            y = p - c
            if residual:
                if joints.has_residual[f] != 0:
                    y = blend_groups(inf, v, f, joints.residuals, groups) * y
            lc = blend_groups(inf, v, f, joints.affines, groups) * wp.vec4(c[0], c[1], c[2], 1.0)
            return dqs_apply(rotation_only(dqs_blend_groups(inf, v, f, joints.dqs, groups)), y) + lc
    x = p
    if residual:
        if joints.has_residual[f] != 0:
            x = blend_groups(inf, v, f, joints.residuals, groups) * p
    dqs = dqs_apply(dqs_blend_groups(inf, v, f, joints.dqs, groups), x)
    lbs = wp.vec3()
    if method == BLEND:
        lbs = blend_groups(inf, v, f, joints.affines, groups) * wp.vec4(p[0], p[1], p[2], 1.0)
    return by_method(inf, v, method, lbs, dqs)


def _skin_points_kernel(method, residual, four):
    """The (frame block, row block) kernel of one method, specialized at compile time:
    ``residual=False`` drops the scale/shear code (~18% faster on the CPU for rigid launches),
    ``four`` (``K <= 4``, one influence group) drops the loop over groups."""

    def kernel(
        points: wp.array2d(dtype=wp.vec3),
        inf: Influences,
        joints: Joints,
        blocks: FrameBlocks,
        # outputs
        out: wp.array2d(dtype=wp.vec3),
    ):
        b, i = wp.tid()
        first, end, _row = block_frames(blocks, b, out.shape[0])
        rows, rows_end = block_rows(blocks, i, out.shape[1])
        last = points.shape[0] - 1
        groups = inf.indices.shape[1]
        if wp.static(four):
            groups = 1
        for v in range(rows, rows_end):
            for f in range(first, end):
                out[f, v] = skin_point(points[wp.min(f, last), v], inf, v, f, joints,
                                       wp.static(method), wp.static(residual), groups)

    rigid = "_rigid" if method in (DQS, COR) and not residual else ""
    name = f"skin_{['lbs', 'dqs', 'blend', 'cor'][method]}{rigid}_kernel{'_k4' if four else ''}"
    kernel.__doc__ = (f"Skin ``points`` (Fp, V) bind space, Fp 1 or F, into ``out`` (F, V) with "
                      f"method {method} over a (frame block, row block) grid.")
    return wp.kernel(kernel, name=name)


SKIN_POINTS_KERNELS = {(m, r, four): _skin_points_kernel(m, r, four)
                       for m, r in ((LBS, False), (DQS, True), (DQS, False), (BLEND, True),
                                    (COR, True), (COR, False))
                       for four in (False, True)}
"""The point-skinning kernels by ``(method, residual code, K <= 4)``: LBS needs no residual code,
BLEND always has it."""
skin_dqs_kernel = SKIN_POINTS_KERNELS[(DQS, True, False)]
"""The general DQS kernel (any K, residual code compiled in), for tests comparing against it."""


@wp.func
def dqs_vector(x: wp.vec3, inf: Influences, v: int, f: int, rotations: wp.array2d(dtype=wp.quat),
               residuals: wp.array2d(dtype=wp.mat33), use_residual: bool):
    """Rotation-only DQS of a direction (sign-aligned quaternion blend, the sign rule of
    :func:`dqs_blend`), unit length."""
    pivot = rotations[f, pivot_joint(inf, v, inf.indices.shape[1])]
    r = wp.quat(0.0, 0.0, 0.0, 0.0)
    for c in range(inf.indices.shape[1]):
        iv = inf.indices[v, c]
        wv = inf.weights[v, c]
        for k in range(4):
            if inf.running_sum != 0:
                pivot = r
            q = rotations[f, iv[k]]
            r += q * (wv[k] * wp.sign(wp.dot(q, pivot)))
    scaled = x
    if use_residual:
        scaled = blend_joints(inf, v, f, residuals) * x
    if wp.length(r) < 1.0e-10:
        return wp.normalize(scaled)
    return wp.normalize(wp.quat_rotate(wp.normalize(r), scaled))


@wp.kernel
def skin_vectors_kernel(
    vectors: wp.array2d(dtype=wp.vec3),
    vector_vertex: wp.array(dtype=wp.int32),
    inf: Influences,
    linears: wp.array2d(dtype=wp.mat33),
    rotations: wp.array2d(dtype=wp.quat),
    residuals: wp.array2d(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    method: int,
    blocks: FrameBlocks,
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
    first, end, row = block_frames(blocks, blk, out.shape[0])
    n = i + row
    v = vector_vertex[n]
    last = vectors.shape[0] - 1
    for f in range(first, end):
        x = vectors[wp.min(f, last), n]
        lbs = wp.vec3()
        dqs = wp.vec3()
        if method == LBS or method == BLEND:
            lbs = wp.normalize(blend_joints(inf, v, f, linears) * x)
        if method != LBS:
            dqs = dqs_vector(x, inf, v, f, rotations, residuals, has_residual[f] != 0)
        out[f, n] = wp.normalize(by_method(inf, v, method, lbs, dqs))


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


def influences(*, indices, weights, blend, centers, running_sum=False, unsorted=False):
    """The :class:`Influences` struct of a mesh's device arrays."""
    s = Influences()
    s.indices, s.weights, s.blend, s.centers = indices, weights, blend, centers
    s.running_sum, s.unsorted = int(bool(running_sum)), int(bool(unsorted))
    return s


def joints(*, affines, dqs, residuals, has_residual):
    """The :class:`Joints` struct of (F, J) work arrays."""
    s = Joints()
    s.affines, s.dqs, s.residuals, s.has_residual = affines, dqs, residuals, has_residual
    return s


def prepare_points(*, xforms, joints, device):
    """Fill ``joints`` (a :class:`Joints` of (F, J) arrays) from ``xforms`` (F, J) ``wp.mat44``."""
    joints.has_residual.zero_()
    launch(prepare_points_kernel, xforms.shape, [xforms],
           [joints.affines, joints.dqs, joints.residuals, joints.has_residual], device)


def prepare_vectors(*, xforms, linears, rotations, normal_linears, normal_residuals,
                    normal_rotations, device):
    """Per (frame, joint) data of :func:`skin_vectors` (see :func:`prepare_vectors_kernel`)."""
    launch(prepare_vectors_kernel, xforms.shape, [xforms],
           [linears, rotations, normal_linears, normal_residuals, normal_rotations], device)


def skin_points(*, method, points, influences, joints, rigid, out, device):
    """Skin ``points`` (Fp, V) into ``out`` (F, V) with ``method`` (:data:`LBS`, :data:`DQS`,
    :data:`BLEND`, :data:`COR`). ``rigid`` (no frame has a residual) selects the DQS or COR
    kernel without the residual code."""
    residual = method == BLEND or (method != LBS and not rigid)
    four = influences.indices.shape[1] == 1
    kernel = SKIN_POINTS_KERNELS[(method, residual, four)]
    launch_blocks(kernel, out.shape[1], out.shape[0], [points, influences, joints], [out], device,
                  row_blocks=True)


def skin_vectors(*, method, vectors, vector_vertex, influences, linears, rotations, residuals,
                 has_residual, out, device):
    """Skin directions ``vectors`` (Fp, N) into ``out`` (F, N), normalized (see
    :func:`skin_vectors_kernel` for which per-joint arrays normals and tangents take)."""
    launch_blocks(skin_vectors_kernel, out.shape[1], out.shape[0],
                  [vectors, vector_vertex, influences, linears, rotations, residuals,
                   has_residual, int(method)], [out], device)


def transform_frames(*, xforms, normalize, values, device):
    """In place ``values[f, i] = xforms[f]·[values[f, i], 1]`` (normalized with ``normalize``)."""
    launch(transform_frames_kernel, values.shape, [xforms, int(normalize)], [values], device)
