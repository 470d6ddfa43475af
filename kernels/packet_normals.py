"""Directions (normals, tangents) skinned eight at a time on the CPU, for
:func:`.skin.skin_vectors`: LBS (:func:`lbs_vector_packet`, :data:`skin_vectors_lbs_packet_kernel`)
and DQS / COR (:func:`dqs_vector_packet`, :data:`skin_vectors_dqs_packet_kernel`; each sign rule).

The arithmetic is :func:`.skin.skin_vectors_kernel`'s, term for term and in the same order, so
the results are bit for bit the same. LBS: ``y = (Σ wₖ·Mₖ)·x`` over one group of four
influences (``Mₖ`` the 3×3 matrices of the vertex's joints: the inverse transposes for normals,
the linear parts for tangents), then ``y`` normalized twice, as the one-vertex kernel does
(``wp.normalize``: ``y / |y|``, zero for a zero ``y``). DQS (and COR, whose directions turn as
DQS's): :func:`.skin.dqs_vector`, the quaternions' sign-aligned blend (pivot in slot 0, the first
largest weight, or the running sum) rotating the direction, first through the blended residuals
on a frame with scale/shear; normalized twice too. One thread handles rows ``n0 .. n0 + 7``
of a frame in the lanes of clang vectors (:data:`.packets.VECTOR_PRELUDE`); each row's
influences are those of its vertex ``vector_vertex[n]`` (face-varying normals share a vertex's).
A last packet of fewer than eight rows reads its first row's vertex in the missing lanes with
zero weights and stores only its own rows. CUDA (``__CUDA_ARCH__``) compiles a scalar loop over
the eight rows; the launcher uses the kernel only on the CPU.
"""

import warp as wp

from .grid import FRAME_BLOCK
from .layout import InfluenceLayout, contiguous_vec4, contiguous_vec4i
from .packets import STORE_VECTOR, VECTOR_END, VECTOR_PRELUDE

wp.set_module_options({"enable_backward": False})  # forward-only kernels

ROWS = 8
"""Rows (directions) a thread of :data:`skin_vectors_lbs_packet_kernel` skins."""

_FRAME_BLOCK = wp.constant(FRAME_BLOCK)

_NORMALIZE_TWICE = """
        for (int twice = 0; twice < 2; ++twice) {
            const V l = SQRT(ox * ox + oy * oy + oz * oz);
            const V zero = 0.0f;
            ox = l > 0.0f ? ox / l : zero;
            oy = l > 0.0f ? oy / l : zero;
            oz = l > 0.0f ? oz / l : zero;
        }"""

_MATH = """
        V A[9], T[9];
        LOAD(0, A);
        for (int c = 0; c < 9; ++c) A[c] = A[c] * w0;
        const V wk[3] = {w1, w2, w3};
        for (int k = 1; k < 4; ++k) {
            LOAD(k, T);
            for (int c = 0; c < 9; ++c) A[c] += T[c] * wk[k - 1];
        }
        V ox = A[0] * x + A[1] * y + A[2] * z;
        V oy = A[3] * x + A[4] * y + A[5] * z;
        V oz = A[6] * x + A[7] * y + A[8] * z;""" + _NORMALIZE_TWICE

_SCALAR = """
    typedef float V;
    typedef bool bool_v;
    for (int i = 0; i < n; ++i) {
        const int v = ((const int*)vector_vertex.data)[n0 + i];
        const float* X = (const float*)vectors.data + 3 * (vector_base + n0 + i);
        const int* I = (const int*)indices.data + 4 * v;
        const float* W = (const float*)weights.data + 4 * v;
        JOINT_DATA
        const V x = X[0], y = X[1], z = X[2];
        const V w0 = W[0], w1 = W[1], w2 = W[2], w3 = W[3];
#define LOAD(K, OUT) for (int c = 0; c < 9; ++c) OUT[c] = J[9 * I[K] + c]
#define LOADQ(K, OUT) for (int c = 0; c < 4; ++c) OUT[c] = R[4 * I[K] + c]
#define SQRT(S) sqrtf(S)
        MATH
#undef LOAD
#undef LOADQ
#undef SQRT
        float* O = (float*)out.data + 3 * (out_base + n0 + i);
        O[0] = ox; O[1] = oy; O[2] = oz;
    }
    return 0;"""
"""The scalar branch (CUDA's; the tests' CPU twin): row by row, ``JOINT_DATA`` setting ``J``
(3×3 matrices) and for DQS ``R`` (quaternions) to the frame's first joint."""

_LBS_JOINTS = "const float* J = (const float*)linears.data + 9 * (long long)o;"
_DQS_JOINTS = ("const float* R = (const float*)rotations.data + 4 * (long long)o;\n"
               "        const float* J = (const float*)residuals.data + 9 * (long long)o;")

_VECTOR = """
    typedef f8 V;
    const int* VV = (const int*)vector_vertex.data + n0;
    int lane_vertex[8];
    for (int i = 0; i < 8; ++i) lane_vertex[i] = VV[i < n ? i : 0];
    const float* X = (const float*)vectors.data + 3 * (vector_base + n0);
    float xbuf[24];
    if (n < 8) {  // the last packet: the missing lanes zero
        for (int e = 0; e < 24; ++e) xbuf[e] = e < 3 * n ? X[e] : 0.0f;
        X = xbuf;
    }
    int I[32];
    f4 wq[8];
    const f4 no_weight = 0.0f;
    for (int i = 0; i < 8; ++i) {
        __builtin_memcpy(I + 4 * i, (const int*)indices.data + 4 * lane_vertex[i], 16);
        __builtin_memcpy(&wq[i], (const float*)weights.data + 4 * lane_vertex[i], 16);
        if (i >= n) wq[i] = no_weight;
    }
    f8 wc[4];
    transpose4(wq, wc);
    const V w0 = wc[0], w1 = wc[1], w2 = wc[2], w3 = wc[3];
    f8 pa, pb, pc;
    __builtin_memcpy(&pa, X, 32);
    __builtin_memcpy(&pb, X + 8, 32);
    __builtin_memcpy(&pc, X + 16, 32);
    const V x = SHUF(SHUF(pa, pb, 0, 3, 6, 9, 12, 15, -1, -1),
                     pc, 0, 1, 2, 3, 4, 5, 10, 13);
    const V y = SHUF(SHUF(pa, pb, 1, 4, 7, 10, 13, -1, -1, -1),
                     pc, 0, 1, 2, 3, 4, 8, 11, 14);
    const V z = SHUF(SHUF(pa, pb, 2, 5, 8, 11, 14, -1, -1, -1),
                     pc, 0, 1, 2, 3, 4, 9, 12, 15);
    const char* J = (const char*)linears.data + 36 * (long long)o;
    // a joint's nine floats: the first eight as a row of transpose8, the ninth lane by lane
#define LOAD(K, OUT) do { f8 r_[8]; \\
        for (int i = 0; i < 8; ++i) __builtin_memcpy(&r_[i], J + 36 * I[4 * i + (K)], 32); \\
        transpose8(r_, OUT); \\
        for (int i = 0; i < 8; ++i) OUT[8][i] = ((const float*)(J + 36 * I[4 * i + (K)]))[8]; \\
        } while (0)
#define SQRT(S) ([](f8 s_) { f8 r_; for (int i = 0; i < 8; ++i) r_[i] = sqrtf(s_[i]); \\
        return r_; })(S)
    MATH
#undef LOAD
#undef SQRT
    STORE_OUTPUT""".replace("    STORE_OUTPUT", STORE_VECTOR.replace("FIRST", "n0"))


def vector_packet_source(scalar_on_cpu: bool = False) -> str:
    """C++ of :func:`lbs_vector_packet`; ``scalar_on_cpu`` compiles the scalar (CUDA) branch
    for the CPU too (the tests' twin)."""
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    return f"""
    const int n = count - n0 < 8 ? count - n0 : 8;
#if {cond}
{_SCALAR.replace("JOINT_DATA", _LBS_JOINTS).replace("MATH", _MATH)}
#else
{VECTOR_PRELUDE}{_VECTOR.replace("    MATH", _MATH)}{VECTOR_END}
#endif
"""


@wp.func
def packet_rows(t: int, rows: int, frame_count: int):
    """``(first row, first frame, end frame)`` of thread ``t``: packet ``t mod P`` (``P =
    ceil(rows / 8)``) of frame block ``t div P`` (:data:`~.grid.FRAME_BLOCK` frames)."""
    packets = (rows + 7) // 8
    block = t // packets
    first = block * _FRAME_BLOCK
    return (t - block * packets) * 8, first, wp.min(first + _FRAME_BLOCK, frame_count)


@wp.func_native(vector_packet_source())
def lbs_vector_packet(vectors: wp.array(dtype=wp.vec3), vector_base: wp.int64,
                      vector_vertex: wp.array(dtype=wp.int32),
                      indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                      linears: wp.array(dtype=wp.mat33), o: int, n0: int, count: int,
                      out: wp.array(dtype=wp.vec3), out_base: wp.int64) -> int:
    """LBS of directions ``n0 .. min(n0 + 8, count) - 1`` (``vectors[vector_base + n]``, out
    ``out_base + n``) with the 3×3 matrices from element ``o`` (the frame's first joint),
    normalized twice as :func:`.skin.skin_vectors_kernel`."""
    ...


@wp.kernel
def skin_vectors_lbs_packet_kernel(
    vectors: wp.array(dtype=wp.vec3),
    vector_stride: int,
    vector_vertex: wp.array(dtype=wp.int32),
    inf: InfluenceLayout,
    linears: wp.array(dtype=wp.mat33),
    joint_count: int,
    frame_count: int,
    row_offset: int,
    # outputs
    out: wp.array(dtype=wp.vec3),
):
    """:func:`.skin.skin_vectors_kernel` for LBS of one influence group, eight rows a thread:
    thread ``t`` skins packet ``t mod P`` (``P = ceil(N / 8)``) of the frames of block
    ``t div P`` (:data:`~.grid.FRAME_BLOCK` frames; the only frame when there is one)."""
    indices = contiguous_vec4i(inf.indices)
    weights = contiguous_vec4(inf.weights)
    rows = out.shape[0] // frame_count
    n0, first, end = packet_rows(wp.tid() + row_offset, rows, frame_count)
    for f in range(first, end):
        lbs_vector_packet(vectors, wp.int64(f) * wp.int64(vector_stride), vector_vertex, indices,
                          weights, linears, f * joint_count, n0, rows, out,
                          wp.int64(f) * wp.int64(rows))


# ---------------------------------------------------------------------------------------------
# DQS (and COR, whose directions turn as DQS's): the sign-aligned blend of the joints'
# quaternions rotates the direction, through the blended residuals on frames with scale/shear

_DQS_MATH = """
        V Q[4][4], B[4];
        for (int k = 0; k < 4; ++k) LOADQ(k, Q[k]);
        const V wk[4] = {w0, w1, w2, w3};
        V ref[4];
        for (int c = 0; c < 4; ++c) ref[c] = Q[0][c];  // sorted: the pivot in slot 0
        if (rule == 1) {  // searched: the first largest weight's slot
            PIVOT
            for (int c = 0; c < 4; ++c)
                ref[c] = slot == s1 ? Q[1][c] : slot == s2 ? Q[2][c] : slot == s3 ? Q[3][c]
                         : Q[0][c];
        }
        for (int c = 0; c < 4; ++c) B[c] = 0.0f;
        for (int k = 0; k < 4; ++k) {
            if (rule == 2)  // running: against the sum so far
                for (int c = 0; c < 4; ++c) ref[c] = B[c];
            const V dot = Q[k][0] * ref[0] + Q[k][1] * ref[1] + Q[k][2] * ref[2]
                          + Q[k][3] * ref[3];
            const V s = dot < 0.0f ? -wk[k] : wk[k];
            for (int c = 0; c < 4; ++c) B[c] = B[c] + Q[k][c] * s;
        }
        V sx = x, sy = y, sz = z;
        if (scaled) {
            V A[9], T[9];
            LOAD(0, A);
            for (int c = 0; c < 9; ++c) A[c] = A[c] * w0;
            for (int k = 1; k < 4; ++k) {
                LOAD(k, T);
                for (int c = 0; c < 9; ++c) A[c] += T[c] * wk[k];
            }
            sx = A[0] * x + A[1] * y + A[2] * z;
            sy = A[3] * x + A[4] * y + A[5] * z;
            sz = A[6] * x + A[7] * y + A[8] * z;
        }
        const V len = SQRT(B[0] * B[0] + B[1] * B[1] + B[2] * B[2] + B[3] * B[3]);
        const V inv = 1.0f / len;
        const V qx = B[0] * inv, qy = B[1] * inv, qz = B[2] * inv, qw = B[3] * inv;
        const V cc = 2.0f * qw * qw - 1.0f;
        const V d = 2.0f * (qx * sx + qy * sy + qz * sz);
        const V rx = sx * cc + qx * d + (qy * sz - qz * sy) * qw * 2.0f;
        const V ry = sy * cc + qy * d + (qz * sx - qx * sz) * qw * 2.0f;
        const V rz = sz * cc + qz * d + (qx * sy - qy * sx) * qw * 2.0f;
        const bool_v small = len < 1.0e-10f;  // no rotation: the scaled direction
        V ox = small ? sx : rx;
        V oy = small ? sy : ry;
        V oz = small ? sz : rz;""" + _NORMALIZE_TWICE

_SCALAR_PIVOT = """typedef int i8;
            const i8 s1 = 1, s2 = 2, s3 = 3;
            i8 slot = 0;  // the first largest weight's slot
            V best = w0;
            for (int k = 1; k < 4; ++k) {
                if (wk[k] > best) {
                    slot = k;
                    best = wk[k];
                }
            }"""

_VECTOR_PIVOT = """const i8 s1 = 1, s2 = 2, s3 = 3;
            i8 slot = 0;  // the first largest weight's slot, lane by lane
            V best = w0;
            for (int k = 1; k < 4; ++k) {
                const i8 more = wk[k] > best;
                const i8 kv = k;
                slot = more ? kv : slot;
                best = more ? wk[k] : best;
            }"""

_DQS_VECTOR_LOADS = """
    typedef i8 bool_v;
    const char* R = (const char*)rotations.data + 16 * (long long)o;
    const char* J = (const char*)residuals.data + 36 * (long long)o;
#define LOADQ(K, OUT) do { f4 q_[8]; \\
        for (int i = 0; i < 8; ++i) __builtin_memcpy(&q_[i], R + 16 * I[4 * i + (K)], 16); \\
        transpose4(q_, OUT); } while (0)
"""


def dqs_vector_packet_source(scalar_on_cpu: bool = False) -> str:
    """C++ of :func:`dqs_vector_packet`; ``scalar_on_cpu`` compiles the scalar (CUDA) branch
    for the CPU too (the tests' twin)."""
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    scalar = (_SCALAR.replace("JOINT_DATA", _DQS_JOINTS)
              .replace("MATH", _DQS_MATH.replace("PIVOT", _SCALAR_PIVOT)))
    vector = (_VECTOR.replace("linears.data + 36", "residuals.data + 36")
              .replace("    const char* J = (const char*)residuals.data + 36 * (long long)o;\n",
                       _DQS_VECTOR_LOADS)
              .replace("#undef LOAD\n", "#undef LOAD\n#undef LOADQ\n")
              .replace("    MATH", _DQS_MATH.replace("PIVOT", _VECTOR_PIVOT)))
    return f"""
    const int n = count - n0 < 8 ? count - n0 : 8;
#if {cond}
{scalar}
#else
{VECTOR_PRELUDE}{vector}{VECTOR_END}
#endif
"""


@wp.func_native(dqs_vector_packet_source())
def dqs_vector_packet(vectors: wp.array(dtype=wp.vec3), vector_base: wp.int64,
                      vector_vertex: wp.array(dtype=wp.int32),
                      indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                      rotations: wp.array(dtype=wp.quat), residuals: wp.array(dtype=wp.mat33),
                      scaled: int, rule: int, o: int, n0: int, count: int,
                      out: wp.array(dtype=wp.vec3), out_base: wp.int64) -> int:
    """DQS of directions ``n0 .. min(n0 + 8, count) - 1`` as :func:`.skin.dqs_vector`, then
    normalized again as :func:`.skin.skin_vectors_kernel`: the joints' quaternions (Warp's
    ``(x, y, z, w)``, from element ``o``) blended with signs against the pivot (``rule`` 0: slot
    0 of the sorted layout; 1: the first largest weight's slot) or the running sum (2); on a
    frame with scale/shear (``scaled``) the direction first goes through the blended
    ``residuals``."""
    ...


@wp.kernel
def skin_vectors_dqs_packet_kernel(
    vectors: wp.array(dtype=wp.vec3),
    vector_stride: int,
    vector_vertex: wp.array(dtype=wp.int32),
    inf: InfluenceLayout,
    rotations: wp.array(dtype=wp.quat),
    residuals: wp.array(dtype=wp.mat33),
    has_residual: wp.array(dtype=wp.int32),
    joint_count: int,
    frame_count: int,
    rule: int,
    row_offset: int,
    # outputs
    out: wp.array(dtype=wp.vec3),
):
    """:func:`.skin.skin_vectors_kernel` for DQS and COR of one influence group, eight rows a
    thread, as :data:`skin_vectors_lbs_packet_kernel`."""
    indices = contiguous_vec4i(inf.indices)
    weights = contiguous_vec4(inf.weights)
    rows = out.shape[0] // frame_count
    n0, first, end = packet_rows(wp.tid() + row_offset, rows, frame_count)
    for f in range(first, end):
        dqs_vector_packet(vectors, wp.int64(f) * wp.int64(vector_stride), vector_vertex, indices,
                          weights, rotations, residuals, has_residual[f], rule, f * joint_count,
                          n0, rows, out, wp.int64(f) * wp.int64(rows))
