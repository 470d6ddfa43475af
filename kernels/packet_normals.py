"""LBS of directions (normals, tangents) eight at a time on the CPU, for :func:`.skin.skin_vectors`:
the native snippet :func:`lbs_vector_packet` and its kernel :data:`skin_vectors_lbs_packet_kernel`.

The arithmetic is :func:`.skin.skin_vectors_kernel`'s for LBS, term for term and in the same
order, so the results are bit for bit the same: ``y = (Σ wₖ·Mₖ)·x`` over one group of four
influences (``Mₖ`` the 3×3 matrices of the vertex's joints: the inverse transposes for normals,
the linear parts for tangents), then ``y`` normalized twice, as the one-vertex kernel does
(``wp.normalize``: ``y / |y|``, zero for a zero ``y``). One thread handles rows ``n0 .. n0 + 7``
of a frame in the lanes of clang vectors (:data:`.packets.VECTOR_PRELUDE`); each row's
influences are those of its vertex ``vector_vertex[n]`` (face-varying normals share a vertex's).
A last packet of fewer than eight rows reads its first row's vertex in the missing lanes with
zero weights and stores only its own rows. CUDA (``__CUDA_ARCH__``) compiles a scalar loop over
the eight rows; the launcher uses the kernel only on the CPU.
"""

import warp as wp

from .grid import FRAME_BLOCK
from .layout import InfluenceLayout, contiguous_vec4, contiguous_vec4i
from .packets import VECTOR_END, VECTOR_PRELUDE

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
    for (int i = 0; i < n; ++i) {
        const int v = ((const int*)vector_vertex.data)[n0 + i];
        const float* X = (const float*)vectors.data + 3 * (vector_base + n0 + i);
        const int* I = (const int*)indices.data + 4 * v;
        const float* W = (const float*)weights.data + 4 * v;
        const float* J = (const float*)linears.data + 9 * (long long)o;
        const V x = X[0], y = X[1], z = X[2];
        const V w0 = W[0], w1 = W[1], w2 = W[2], w3 = W[3];
#define LOAD(K, OUT) for (int c = 0; c < 9; ++c) OUT[c] = J[9 * I[K] + c]
#define SQRT(S) sqrtf(S)
        MATH
#undef LOAD
#undef SQRT
        float* O = (float*)out.data + 3 * (out_base + n0 + i);
        O[0] = ox; O[1] = oy; O[2] = oz;
    }
    return 0;"""

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
    const f8 o0 = SHUF(SHUF(ox, oy, 0, 8, -1, 1, 9, -1, 2, 10),
                       oz, 0, 1, 8, 3, 4, 9, 6, 7);
    const f8 o1 = SHUF(SHUF(ox, oy, -1, 3, 11, -1, 4, 12, -1, 5),
                       oz, 10, 1, 2, 11, 4, 5, 12, 7);
    const f8 o2 = SHUF(SHUF(ox, oy, 13, -1, 6, 14, -1, 7, 15, -1),
                       oz, 0, 13, 2, 3, 14, 5, 6, 15);
    float* O = (float*)out.data + 3 * (out_base + n0);
    if (n == 8) {
        __builtin_memcpy(O, &o0, 32);
        __builtin_memcpy(O + 8, &o1, 32);
        __builtin_memcpy(O + 16, &o2, 32);
    } else {
        float ob[24];
        __builtin_memcpy(ob, &o0, 32);
        __builtin_memcpy(ob + 8, &o1, 32);
        __builtin_memcpy(ob + 16, &o2, 32);
        for (int e = 0; e < 3 * n; ++e) O[e] = ob[e];
    }
    return 0;"""


def vector_packet_source(scalar_on_cpu: bool = False) -> str:
    """C++ of :func:`lbs_vector_packet`; ``scalar_on_cpu`` compiles the scalar (CUDA) branch
    for the CPU too (the tests' twin)."""
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    return f"""
    const int n = count - n0 < 8 ? count - n0 : 8;
#if {cond}
{_SCALAR.replace("MATH", _MATH)}
#else
{VECTOR_PRELUDE}{_VECTOR.replace("    MATH", _MATH)}{VECTOR_END}
#endif
"""


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
    t = wp.tid() + row_offset
    indices = contiguous_vec4i(inf.indices)
    weights = contiguous_vec4(inf.weights)
    rows = out.shape[0] // frame_count
    packets = (rows + 7) // 8
    block = t // packets
    first = block * _FRAME_BLOCK
    end = wp.min(first + _FRAME_BLOCK, frame_count)
    n0 = (t - block * packets) * 8
    for f in range(first, end):
        lbs_vector_packet(vectors, wp.int64(f) * wp.int64(vector_stride), vector_vertex, indices,
                          weights, linears, f * joint_count, n0, rows, out,
                          wp.int64(f) * wp.int64(rows))
