"""Differentiable kernels: forward kinematics and LBS / DQS / blend / COR skinning whose adjoints
Warp generates (``wp.launch(..., adjoint=True)``), for :mod:`dqskin.autograd` (the DQS point
kernel's adjoint is written out in :mod:`.grad_dqs`).

They compute what :mod:`.skin` and :mod:`.fk` compute, from the same :mod:`.dqmath` functions,
written so that every step has a derivative: no packets, no native snippets, no data-dependent
loops (influence loops unrolled for a fixed ``K``), and two substitutions:

* The polar rotation ``R`` of ``A = R·S`` comes from scaled Newton iterations
  ``X ← ½(γ·X + X⁻ᵀ/γ)``, ``γ = |det X|^(−1/3)`` (Higham), a fixed number of steps
  (:data:`POLAR_STEPS`), instead of an SVD: the SVD's derivative divides by differences of
  singular values, which are all equal at a rigid transform. At a rotation one step returns it and
  its derivative is the exact polar derivative ``R·skew(Rᵀ·dA)``.
* The normal split's Gram-Schmidt-like iteration (:func:`~.dqmath.orthonormalize_columns`) runs
  its 20 steps without the early exit (:func:`orthonormalize_fixed`), the same value to float32.

DQS always blends the scale/shear residuals, ``p_s = Σ wᵢ·Sᵢ·p``: the value of :mod:`.skin`
wherever the weights sum to 1 or a joint of the frame has a residual, and the one form whose
derivative is right at rigid transforms (a shear of ``A`` makes ``S ≠ I``).

Layouts: per-(frame, joint) data flat ``(F·J,)``, frame-major; per-vertex data flat
``(Fp·V,)`` with a frame stride (``V``, or 0 for one set shared by every frame); influences
``(V, K)`` int32 joint indices and float32 weights as given (no sort, no padding). A point or
normal thread handles one (frame, vertex) of a chunk of vertices ``first .. first + rows`` and all
frames, so per-vertex adjoints (points, weights, centers, blend) are written by one CPU thread
only; per-joint adjoints go to a buffer of the chunk's own (:func:`launch_vertices`), summed in
chunk order (:func:`sum_chunks_kernel`).
"""

import functools
import itertools
from collections.abc import Callable, Sequence
from typing import Any

import warp as wp

from .._warp import Device
from .dqmath import (
    FACTOR_EPSILON,
    dq_blend_add,
    dq_from_rt,
    mat44_linear,
    orthonormalize_step,
    quat_from_rotation,
    vec8,
)
from .grid import PIECES_PER_THREAD, cpu_threads, is_cpu, launch, run_tasks
from .skin import dqs_apply, rotation_only

__all__ = ["LBS", "DQS", "BLEND", "COR", "POLAR_STEPS", "launch_joints", "launch_vertices",
           "local_kernel", "fk_kernel", "prepare_kernel", "prepare_normals_kernel",
           "points_kernel", "normals_kernel", "sum_chunks_kernel", "vertex_chunks",
           "fused_cpu_flags"]

wp.set_module_options({"enable_backward": True, "max_unroll": 32})  # unrolled: differentiable

LBS, DQS, BLEND, COR = 0, 1, 2, 3

POLAR_STEPS = 10
"""Scaled Newton steps of :func:`polar_newton`: float32-converged for condition numbers up to
about 10⁴ (one step at a rotation)."""

_MIN_CHUNK = 8192
"""Vertex-frames below which a point launch runs on one CPU thread."""


@wp.func
def polar_newton(a: wp.mat33):
    """Rotation factor ``R`` (det +1) of ``A = R·S`` by :data:`POLAR_STEPS` scaled Newton steps,
    negated when ``det A < 0`` (as :func:`~.dqmath.polar_rotation`); ``A`` invertible."""
    x = a
    for _k in range(POLAR_STEPS):
        g = wp.pow(wp.abs(wp.determinant(x)), -1.0 / 3.0)
        x = (x * g + wp.transpose(wp.inverse(x)) * (1.0 / g)) * 0.5
    if wp.determinant(a) < 0.0:
        x = -x
    return x


@wp.func
def orthonormalize_fixed(m: wp.mat33):
    """:func:`~.dqmath.orthonormalize_columns` with all 20 steps (no early exit: a derivative)."""
    tx = wp.normalize(wp.vec3(m[0, 0], m[1, 0], m[2, 0]))
    ty = wp.normalize(wp.vec3(m[0, 1], m[1, 1], m[2, 1]))
    tz = wp.normalize(wp.vec3(m[0, 2], m[1, 2], m[2, 2]))
    for _k in range(20):
        tx, ty, tz = orthonormalize_step(tx, ty, tz)
    return wp.matrix_from_cols(tx, ty, tz)


@wp.func
def axis_angle_quat(v: wp.vec3):
    """Warp quaternion ``(x, y, z, w)`` of rotation vector ``v`` (angle ``|v|`` about
    ``v/|v|``); a series near 0, so the derivative is finite there."""
    t2 = wp.dot(v, v)
    k = 0.5 - t2 / 48.0
    w = 1.0 - t2 / 8.0
    if t2 > 1.0e-6:
        t = wp.sqrt(t2)
        k = wp.sin(0.5 * t) / t
        w = wp.cos(0.5 * t)
    return wp.quat(v[0] * k, v[1] * k, v[2] * k, w)


def _local_kernel(axis_angle: bool):
    rot_type = wp.vec3 if axis_angle else wp.vec4

    def kernel(
        rotations: wp.array(dtype=rot_type),
        translations: wp.array(dtype=wp.vec3),
        translation_stride: int,
        scales: wp.array(dtype=wp.vec3),
        scale_stride: int,
        root: wp.array(dtype=wp.vec3),
        parents: wp.array(dtype=wp.int32),
        # outputs
        local: wp.array(dtype=wp.mat44),
    ):
        i = wp.tid()  # (frame, joint), frame-major
        joint_count = parents.shape[0]
        f = i // joint_count
        j = i - f * joint_count
        r = rotations[i]
        if wp.static(axis_angle):
            q = axis_angle_quat(r)
        else:
            q = wp.normalize(wp.quat(r[1], r[2], r[3], r[0]))
        t = translations[f * translation_stride + j]
        if root.shape[0] > 0 and parents[j] < 0:
            t = t + root[f]
        s = wp.vec3(1.0, 1.0, 1.0)
        if scales.shape[0] > 0:
            s = scales[f * scale_stride + j]
        m = wp.quat_to_matrix(q) * wp.diag(s)
        local[i] = wp.mat44(m[0, 0], m[0, 1], m[0, 2], t[0],
                            m[1, 0], m[1, 1], m[1, 2], t[1],
                            m[2, 0], m[2, 1], m[2, 2], t[2],
                            0.0, 0.0, 0.0, 1.0)

    kernel.__doc__ = ("Local joint matrix ``T·R·S`` per (frame, joint) from "
                      + ("rotation vectors" if axis_angle else "quaternions (w, x, y, z), "
                         "normalized") + "; translations and scales (optional: empty) with a "
                      "frame stride (J or 0); ``root`` (F,) (optional) added to the roots' "
                      "translations.")
    name = f"local_{'axis_angle' if axis_angle else 'quat'}_kernel"
    return wp.kernel(kernel, name=name)


_LOCAL_KERNELS = {False: _local_kernel(False), True: _local_kernel(True)}


def local_kernel(axis_angle: bool) -> wp.Kernel:
    """The local-matrix kernel for quaternions (False) or rotation vectors (True)."""
    return _LOCAL_KERNELS[axis_angle]


@wp.kernel
def fk_kernel(
    local: wp.array(dtype=wp.mat44),
    parents: wp.array(dtype=wp.int32),
    inverse_bind: wp.array(dtype=wp.mat44),
    # outputs
    world: wp.array(dtype=wp.mat44),
    skinning: wp.array(dtype=wp.mat44),
):
    """One frame: ``world[j] = world[parents[j]] · local[j]`` parents first, and
    ``skinning[j] = world[j] · inverse_bind[j]`` when ``inverse_bind`` (J,) is given (else
    ``skinning`` is ``world``)."""
    f = wp.tid()
    joint_count = parents.shape[0]
    o = f * joint_count
    for j in range(joint_count):
        p = parents[j]
        m = local[o + j]
        if p >= 0:
            m = world[o + p] * m
        world[o + j] = m
        if inverse_bind.shape[0] > 0:
            skinning[o + j] = m * inverse_bind[j]


@wp.kernel
def prepare_kernel(
    xforms: wp.array(dtype=wp.mat44),
    # outputs
    dqs: wp.array(dtype=vec8),
    residuals: wp.array(dtype=wp.mat33),
):
    """Per (frame, joint): the polar split ``A = R·S`` of the linear part into the unit dual
    quaternion of ``(R, t)`` and the residual ``S = Rᵀ·A``; ``|det A| <``
    :data:`~.dqmath.FACTOR_EPSILON`: a zero dual quaternion and ``S = I`` (as :mod:`.skin`)."""
    i = wp.tid()
    m = xforms[i]
    a = mat44_linear(m)
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:
        dqs[i] = vec8()
        residuals[i] = wp.identity(n=3, dtype=float)
    else:
        r = polar_newton(a)
        dqs[i] = dq_from_rt(quat_from_rotation(r), wp.vec3(m[0, 3], m[1, 3], m[2, 3]))
        residuals[i] = wp.transpose(r) * a


@wp.kernel
def prepare_normals_kernel(
    xforms: wp.array(dtype=wp.mat44),
    # outputs
    linears: wp.array(dtype=wp.mat33),
    rotations: wp.array(dtype=wp.quat),
    residuals: wp.array(dtype=wp.mat33),
):
    """Per (frame, joint), the normal matrix ``N = A⁻ᵀ`` (LBS), and its split ``N = Rn·(Rnᵀ·N)``
    as UsdSkel's DQS (``Rn`` orthonormalized columns, :func:`orthonormalize_fixed`); a singular
    ``A``: zero ``N`` and rotation, ``S = I`` (adds nothing)."""
    i = wp.tid()
    a = mat44_linear(xforms[i])
    if wp.abs(wp.determinant(a)) < FACTOR_EPSILON:
        linears[i] = wp.mat33()
        rotations[i] = wp.quat(0.0, 0.0, 0.0, 0.0)
        residuals[i] = wp.identity(n=3, dtype=float)
    else:
        n = wp.transpose(wp.inverse(a))
        rn = orthonormalize_fixed(n)
        linears[i] = n
        rotations[i] = quat_from_rotation(rn)
        residuals[i] = wp.transpose(rn) * n


@wp.kernel
def sum_chunks_kernel(
    parts: wp.array2d(dtype=float),
    # outputs
    total: wp.array(dtype=float),
):
    """``total[i] = Σ_c parts[c, i]`` in chunk order: the per-chunk per-joint adjoints of a
    vertex launch (:func:`launch_vertices`), summed."""
    i = wp.tid()
    s = float(0.0)
    for c in range(parts.shape[0]):
        s = s + parts[c, i]
    total[i] = s


def _index_kernel(dtype: Any, name: str) -> wp.Kernel:
    """Count in ``bad[0]`` the joint indices (``dtype``) outside ``0 .. joints - 1``; int64 ones
    are also written to ``narrow`` as int32 (0 where out of range); int32 ones are read only
    (``narrow`` is then the caller's indices themselves, unwritten)."""
    wide = dtype == wp.int64

    def kernel(
        indices: wp.array(dtype=dtype),
        joints: int,
        # outputs
        narrow: wp.array(dtype=wp.int32),
        bad: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        v = indices[i]
        out = v < dtype(0) or v >= dtype(joints)
        if out:
            wp.atomic_add(bad, 0, 1)
        if wp.static(wide):
            narrow[i] = wp.where(out, 0, wp.int32(v))

    kernel.__doc__ = _index_kernel.__doc__
    return wp.kernel(kernel, name=name)


index_check_kernel = _index_kernel(wp.int32, "index_check_kernel")
index_narrow_kernel = _index_kernel(wp.int64, "index_narrow_kernel")


def _pivot_slot(influences: int):
    """``@wp.func`` ``(weights, v) → slot`` of the vertex's largest weight, first on ties."""

    @wp.func
    def pivot_slot(weights: wp.array2d(dtype=float), v: int):
        slot = int(0)
        best = weights[v, 0]
        for k in range(1, wp.static(influences)):
            if weights[v, k] > best:
                best = weights[v, k]
                slot = k
        return slot

    return pivot_slot


@wp.func
def frame_vertex(t: int, first: int, rows: int, joint_count: int):
    """``(frame, vertex, frame's first joint)`` of thread ``t`` of a chunk: frame ``t div rows``,
    vertex ``first + t mod rows``."""
    f = t // rows
    return f, first + t - f * rows, f * joint_count


def _vertex_kernel(kernel: Callable[..., None], kind: str, method: int, influences: int,
                   running_sum: bool) -> wp.Kernel:
    """A point or normal kernel in a Warp module of its own (compiled on first use, alone)."""
    label = ["lbs", "dqs", "blend", "cor"][method]
    name = f"grad_{kind}_{label}_k{influences}{'_running_sum' if running_sum else ''}"
    kernel.__doc__ = (f"Skin {kind} with {label.upper()}, {influences} influences, per (frame, "
                      "vertex) of a chunk (:func:`frame_vertex`); ``out`` (F·V).")
    module = f"{__name__}.{name}"
    options = {"enable_backward": True, "max_unroll": max(32, influences)}
    if kind == "points" and method == DQS:  # measured faster; LBS's point kernel slower
        options["cpu_compiler_flags"] = fused_cpu_flags()
    wp.set_module_options(options, module=module)
    return wp.kernel(kernel, name=name, module=module)


def fused_cpu_flags() -> str:
    """CPU compiler flags of the DQS point kernels' modules (forward, :mod:`.grad_dqs`'s
    adjoint): Warp's configured ones (its default ``-march=native``) with fused multiply-adds
    (``-ffp-contract=fast``: fewer instructions; results within float32 rounding of the unfused
    ones)."""
    flags = wp.config.cpu_compiler_flags  # None: Warp's default; "" (generic) kept as set
    return f"{'-march=native' if flags is None else flags} -ffp-contract=fast"


@functools.cache
def points_kernel(method: int, influences: int, running_sum: bool) -> wp.Kernel:
    """The point kernel of ``method`` for ``influences`` (K) per vertex and a sign rule
    (``running_sum``: Blender's running sum in input order; else the largest weight's joint,
    UsdSkel's), compiled on first use in a Warp module of its own."""
    pivot_slot = _pivot_slot(influences)
    lbs_part = method in (LBS, BLEND, COR)
    dqs_part = method != LBS

    def kernel(
        points: wp.array(dtype=wp.vec3),
        point_stride: int,
        indices: wp.array2d(dtype=wp.int32),
        weights: wp.array2d(dtype=float),
        xforms: wp.array(dtype=wp.mat44),
        dqs: wp.array(dtype=vec8),
        residuals: wp.array(dtype=wp.mat33),
        blend: wp.array(dtype=float),
        centers: wp.array(dtype=wp.vec3),
        has_center: wp.array(dtype=wp.int32),
        joint_count: int,
        first: int,
        rows: int,
        # outputs
        out: wp.array(dtype=wp.vec3),
    ):
        f, v, o = frame_vertex(wp.tid(), first, rows, joint_count)
        vertex_count = weights.shape[0]
        p = points[f * point_stride + v]
        y = p  # what the residuals scale: the point, or (COR) its offset from the center
        c = wp.vec3()
        if wp.static(method == COR):
            if has_center[v] != 0:
                c = centers[v]
                y = p - c
        lbs = wp.mat44()
        b = vec8()
        ys = wp.vec3()  # Σ wᵢ·Sᵢ·y
        if wp.static(dqs_part):
            pv = dqs[o + indices[v, pivot_slot(weights, v)]]
        for k in range(wp.static(influences)):
            j = o + indices[v, k]
            w = weights[v, k]
            if wp.static(lbs_part):
                lbs = lbs + xforms[j] * w
            if wp.static(dqs_part):
                if wp.static(running_sum):
                    b = dq_blend_add(b, dqs[j], w, b)
                else:
                    b = dq_blend_add(b, dqs[j], w, pv)
                ys = ys + (residuals[j] * y) * w
        if wp.static(method == LBS):
            h = lbs * wp.vec4(p[0], p[1], p[2], 1.0)
            out[f * vertex_count + v] = wp.vec3(h[0], h[1], h[2])
        else:
            d = wp.vec3()
            if wp.static(method == COR):
                if has_center[v] != 0:
                    h = lbs * wp.vec4(c[0], c[1], c[2], 1.0)
                    d = dqs_apply(rotation_only(b), ys) + wp.vec3(h[0], h[1], h[2])
                else:
                    d = dqs_apply(b, ys)
            else:
                d = dqs_apply(b, ys)
            if wp.static(method == BLEND):
                h = lbs * wp.vec4(p[0], p[1], p[2], 1.0)
                d = wp.vec3(h[0], h[1], h[2]) * (1.0 - blend[v]) + d * blend[v]
            out[f * vertex_count + v] = d

    return _vertex_kernel(kernel, "points", method, influences, running_sum and dqs_part)


@functools.cache
def normals_kernel(method: int, influences: int, running_sum: bool) -> wp.Kernel:
    """The normal kernel matching :func:`points_kernel`: LBS ``normalize(Σ wᵢ·Nᵢ·n)``; DQS
    (and COR) the sign-aligned blend of the normal rotations applied to ``Σ wᵢ·Sᵢ·n``,
    normalized; blend the normalized mix of the two."""
    pivot_slot = _pivot_slot(influences)
    lbs_part = method in (LBS, BLEND)
    dqs_part = method != LBS

    def kernel(
        normals: wp.array(dtype=wp.vec3),
        normal_stride: int,
        indices: wp.array2d(dtype=wp.int32),
        weights: wp.array2d(dtype=float),
        linears: wp.array(dtype=wp.mat33),
        rotations: wp.array(dtype=wp.quat),
        residuals: wp.array(dtype=wp.mat33),
        blend: wp.array(dtype=float),
        joint_count: int,
        first: int,
        rows: int,
        # outputs
        out: wp.array(dtype=wp.vec3),
    ):
        f, v, o = frame_vertex(wp.tid(), first, rows, joint_count)
        vertex_count = weights.shape[0]
        n = normals[f * normal_stride + v]
        lin = wp.mat33()
        r = wp.quat(0.0, 0.0, 0.0, 0.0)
        x = wp.vec3()  # Σ wᵢ·Sᵢ·n
        if wp.static(dqs_part):
            ref = rotations[o + indices[v, pivot_slot(weights, v)]]
        for k in range(wp.static(influences)):
            j = o + indices[v, k]
            w = weights[v, k]
            if wp.static(lbs_part):
                lin = lin + linears[j] * w
            if wp.static(dqs_part):
                q = rotations[j]
                if wp.static(running_sum):
                    r = r + q * (w * wp.sign(wp.dot(q, r)))
                else:
                    r = r + q * (w * wp.sign(wp.dot(q, ref)))
                x = x + (residuals[j] * n) * w
        y = wp.vec3()
        if wp.static(lbs_part):
            y = wp.normalize(lin * n)
        if wp.static(dqs_part):
            s = x
            d = wp.normalize(s)
            if wp.length(r) >= 1.0e-10:
                d = wp.normalize(wp.quat_rotate(wp.normalize(r), s))
            if wp.static(method == BLEND):
                y = wp.normalize(y * (1.0 - blend[v]) + d * blend[v])
            else:
                y = d
        out[f * vertex_count + v] = y

    return _vertex_kernel(kernel, "normals", method, influences, running_sum and dqs_part)


# ---------------------------------------------------------------------------------------------
# launchers


def _launch(kernel: wp.Kernel, dim: int, inputs: Sequence[Any], outputs: Sequence[Any],
            device: Device, adj_inputs: Sequence[Any] | None,
            adj_outputs: Sequence[Any] | None) -> None:
    if dim <= 0:
        return
    if adj_inputs is None:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=device)
    else:
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, adj_inputs=adj_inputs,
                  adj_outputs=adj_outputs, adjoint=True, device=device)


def launch_joints(kernel: wp.Kernel, dim: int, inputs: Sequence[Any], outputs: Sequence[Any],
                  device: Device, adj_inputs: Sequence[Any] | None = None,
                  adj_outputs: Sequence[Any] | None = None) -> None:
    """Launch a per-(frame, joint) or per-frame kernel (one launch), or with ``adj_inputs`` and
    ``adj_outputs`` its adjoint (input adjoints accumulated, ``None`` for non-arrays)."""
    _launch(kernel, dim, inputs, outputs, device, adj_inputs, adj_outputs)


CHUNK_ADJOINT_BYTES = 1 << 28
"""Most bytes of per-chunk per-joint adjoint buffers a backward pass allocates (each chunk
holds ``frames × joints`` of them, :data:`_ADJOINT_BYTES_PER_JOINT` each): fewer chunks where
more would pass it."""

_ADJOINT_BYTES_PER_JOINT = 4 * (16 + 8 + 9 + 9 + 4 + 9)  # points' and normals' buffers, float32


def vertex_chunks(vertex_count: int, frames: int, device: Device, joint_frames: int = 0
                  ) -> list[tuple[int, int]]:
    """``(first, rows)`` vertex ranges of a point launch: on the CPU, for large launches,
    :data:`~.grid.PIECES_PER_THREAD` per thread, which the threads take in turn
    (:func:`launch_vertices`), at most as many as keep ``joint_frames`` (frames × joints) per
    chunk of adjoint buffers within :data:`CHUNK_ADJOINT_BYTES`; one on CUDA; none without
    vertices or frames."""
    if vertex_count <= 0 or frames <= 0:
        return []
    chunks = 1
    if is_cpu(device):
        work = vertex_count * frames // _MIN_CHUNK
        threads = max(1, min(cpu_threads(), work, vertex_count))
        chunks = min(vertex_count, threads * max(1, min(PIECES_PER_THREAD, work // threads)))
        most = CHUNK_ADJOINT_BYTES // max(1, joint_frames * _ADJOINT_BYTES_PER_JOINT)
        chunks = max(1, min(chunks, most))
    bounds = [vertex_count * c // chunks for c in range(chunks + 1)]
    return [(bounds[c], bounds[c + 1] - bounds[c]) for c in range(chunks)]


def launch_vertices(kernel: wp.Kernel, chunks: Sequence[tuple[int, int]], frames: int,
                    inputs: Callable[[int], Sequence[Any]],
                    outputs: Callable[[int], Sequence[Any]], device: Device,
                    adj_inputs: Callable[[int], Sequence[Any]] | None = None,
                    adj_outputs: Sequence[Any] | None = None, frame_loop: bool = False) -> None:
    """Launch a point or normal kernel over ``chunks`` (:func:`vertex_chunks`) × ``frames``,
    the CPU threads taking the chunks in turn (a thread slowed by another process leaves its
    later chunks to the others); ``inputs(c)``, ``outputs(c)`` and ``adj_inputs(c)`` give
    chunk ``c``'s lists (its own per-joint adjoint buffers: chunks run at once, and a
    buffer per chunk keeps the sums' order fixed), without ``first`` and ``rows``, which are
    appended to the inputs. ``frame_loop``: a kernel whose thread loops over the frames itself
    (grid ``rows``, only ``first`` appended)."""
    count = len(chunks)
    taken = itertools.count()  # the next chunk: next() is atomic under the GIL

    def run() -> None:
        while (c := next(taken)) < count:
            first, rows = chunks[c]
            tail = [first] if frame_loop else [first, rows]
            dim = rows if frame_loop else rows * frames
            if adj_inputs is None:
                launch(kernel, dim, [*inputs(c), *tail], outputs(c), device)
            else:
                _launch(kernel, dim, [*inputs(c), *tail], outputs(c), device,
                        [*adj_inputs(c), *([0] * len(tail))], adj_outputs)

    run_tasks([run] * min(count, cpu_threads() if is_cpu(device) else 1))
