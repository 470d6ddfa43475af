"""Point skinning eight vertices at a time on the CPU: LBS and DQS (each of the three sign
rules) of one group of four influences as native snippets that hold each quantity of eight
vertices in one clang vector (structure of arrays), for :mod:`.skin`'s packet kernels.

Warp's CPU back end compiles a kernel to one scalar loop over its threads. A DQS vertex is a chain
of ~100 dependent scalar operations (gather, sign tests, blend, normalization, transform); the
core's out-of-order window holds about two such chains, so the loop runs at the chain's latency,
not at the machine's width. Here one thread skins vertices ``v0 .. v0 + 7``: it loads each
influence's joint data as rows (one 32-byte ``vec8`` or 48-byte affine per vertex; the
input-order DQS rules its two 16-byte halves, real part then dual part, which keeps fewer
quantities live), transposes them with shuffles so that lane ``i`` of vector ``c`` is component
``c`` of vertex ``i``, and runs the arithmetic once for all eight (AVX2, NEON or SSE, as the
CPU has; ``tools/bench.py``'s "Kernels alone" table compares it with minimal scalar kernels).

The arithmetic is the scalar kernels' (:func:`.skin.dqs_apply`, :func:`.blend.affine_gather`),
term for term and in the same order; it is written once, over a type ``V``: ``f8`` (eight lanes)
on the CPU, ``float`` on CUDA (``__CUDA_ARCH__``), where the snippet loops over the eight vertices
one by one (the launcher uses packet kernels only on the CPU; a GPU runs one vertex per thread).
The scalar branch is also compiled for the CPU by the tests (``scalar_on_cpu``), so it is checked
on every machine.

Semantics (as :mod:`.skin`): LBS ``p' = Σ wₖ·Aₖ·[p, 1]``; DQS ``p' = normalize(Σ ±wₖ·ηₖ)(p)``
with each sign taken against the pivot: slot 0 of the sorted layout (rule ``"sorted"``: its own
sign is +1) or the first largest weight of the input-order slots (``"searched"``: every slot,
slot 0 included, is signed against it); or (``"running"``, Blender's rule) against the sum of the
blend so far, input order, slot 0's sign +1: each lane carries its own running sum. A dot product
of exactly ``-0.0`` or NaN flips nothing, as ``wp.sign``. A zero blend leaves the point
unchanged. The last packet of a frame may hold fewer than eight vertices: its missing lanes read
lane 0's joints with zero weights and are not stored.
With ``check`` the snippets also check their inputs (a one-shot call's, unchecked on the host:
one pass over the caller's arrays fewer) and flag what the host checks would refuse (one test of
all the packet's indices, coordinates and weights); an index out of range never reads outside
the joints.

Arrays are the flat 1-D views of :mod:`.skin` (contiguous): ``points`` / ``out`` element
``base + v``, ``indices`` / ``weights`` one ``vec4i`` / ``vec4`` per vertex (one group), joint data
from element ``o`` (the frame's first joint).
"""

import warp as wp

from .dqmath import mat34, vec8

wp.set_module_options({"enable_backward": False})  # forward-only kernels

# ---------------------------------------------------------------------------------------------
# the arithmetic, over V (f8 or float). LOAD(k, T) fills T[] with influence k's joint data
# (DQS: LOADR / LOADD its real / dual part only, LOADS its residual);
# x, y, z, w0..w3 are loaded before.

# frames with scale/shear: p_s = Σ wₖ·Sₖ·p first (Sₖ the 3×3 residuals, from element o)
_DQS_RESIDUAL = """
        if (scaled) {
            V S[9], U[9];
            LOADS(0, S);
            for (int c = 0; c < 9; ++c) S[c] = S[c] * w0;
            const V ws[3] = {w1, w2, w3};
            for (int k = 1; k < 4; ++k) {
                LOADS(k, U);
                for (int c = 0; c < 9; ++c) S[c] += U[c] * ws[k - 1];
            }
            const V sx = S[0] * x + S[1] * y + S[2] * z;
            const V sy = S[3] * x + S[4] * y + S[5] * z;
            z = S[6] * x + S[7] * y + S[8] * z;
            x = sx;
            y = sy;
        }"""

_DQS_SORTED = """
        V D0[8], T[8], B[8];
        LOAD(0, D0);
        for (int c = 0; c < 8; ++c) B[c] = D0[c] * w0;
        const V wk[3] = {w1, w2, w3};
        for (int k = 1; k < 4; ++k) {
            LOAD(k, T);
            const V dot = D0[0] * T[0] + D0[1] * T[1] + D0[2] * T[2] + D0[3] * T[3];
            const V s = dot < 0.0f ? -wk[k - 1] : wk[k - 1];
            for (int c = 0; c < 8; ++c) B[c] += T[c] * s;
        }"""

# the dual parts of a blend whose real parts and signed weights ``sk`` are done: one joint at a
# time, each component's terms in input order
_DUAL_PARTS = """
        for (int k = 0; k < 4; ++k) {
            V D[4];
            LOADD(k, D);
            if (k == 0)
                for (int c = 0; c < 4; ++c) B[4 + c] = D[c] * sk[k];
            else
                for (int c = 0; c < 4; ++c) B[4 + c] += D[c] * sk[k];
        }"""

# the four real parts first (eight rows of four floats, one transpose each), the pivot's real
# part selected among them while the first largest weight is searched (no loads of its own:
# faster than loading the pivot lane by lane), the four signs; then the dual parts
# (_DUAL_PARTS): fewer quantities live at once than with the four joints loaded whole (which
# spill registers), the same terms in the same order
_DQS_SEARCHED = """
        V R[4][4], B[8], p[4], sk[4];
        for (int k = 0; k < 4; ++k) LOADR(k, R[k]);
        const V wk[4] = {w0, w1, w2, w3};
        V best = w0;  // the first largest weight's real part
        for (int c = 0; c < 4; ++c) p[c] = R[0][c];
        for (int k = 1; k < 4; ++k) {
            const auto more = wk[k] > best;
            best = more ? wk[k] : best;
            for (int c = 0; c < 4; ++c) p[c] = more ? R[k][c] : p[c];
        }
        for (int k = 0; k < 4; ++k) {
            const V dot = p[0] * R[k][0] + p[1] * R[k][1] + p[2] * R[k][2] + p[3] * R[k][3];
            sk[k] = dot < 0.0f ? -wk[k] : wk[k];
        }
        for (int c = 0; c < 4; ++c) B[c] = R[0][c] * sk[0];
        for (int k = 1; k < 4; ++k)
            for (int c = 0; c < 4; ++c) B[c] += R[k][c] * sk[k];
        DUAL_PARTS"""

# the running sum (Blender): each sign against the blend so far, in input order, from the pairwise
# dots of the four real parts (as :func:`.skin.dq_gather`: b_k · d_k = Σ_{m<k} s_m·w_m·(d_m · d_k),
# the first term's sign +1), the lanes carrying their own sums; the four real parts loaded first,
# then the dual parts one joint at a time (as the searched rule)
_DQS_RUNNING = """
        V R[4][4], B[8];
        for (int k = 0; k < 4; ++k) LOADR(k, R[k]);
#define RDOT(A, C) (R[A][0] * R[C][0] + R[A][1] * R[C][1] + R[A][2] * R[C][2] + R[A][3] * R[C][3])
        const V a1 = w0 * RDOT(0, 1);
        const V s1 = a1 < 0.0f ? -w1 : w1;
        const V a2 = w0 * RDOT(0, 2) + s1 * RDOT(1, 2);
        const V s2 = a2 < 0.0f ? -w2 : w2;
        const V a3 = w0 * RDOT(0, 3) + s1 * RDOT(1, 3) + s2 * RDOT(2, 3);
        const V s3 = a3 < 0.0f ? -w3 : w3;
#undef RDOT
        const V sk[4] = {w0, s1, s2, s3};
        for (int c = 0; c < 4; ++c) B[c] = R[0][c] * w0;
        for (int k = 1; k < 4; ++k)
            for (int c = 0; c < 4; ++c) B[c] += R[k][c] * sk[k];
        DUAL_PARTS"""

_DQS_RULES = {"sorted": _DQS_SORTED,
              "searched": _DQS_SEARCHED.replace("        DUAL_PARTS", _DUAL_PARTS),
              "running": _DQS_RUNNING.replace("        DUAL_PARTS", _DUAL_PARTS)}

# dqs_apply: x + 2·(r⃗×(r⃗×x + r_w·x) + r_w·d⃗ − d_w·r⃗ + r⃗×d⃗)/|r|²
_DQS_APPLY = """
        const V rw = B[0], rx = B[1], ry = B[2], rz = B[3];
        const V dw = B[4], dx = B[5], dy = B[6], dz = B[7];
        V nn = rw * rw + (rx * rx + ry * ry + rz * rz);
        nn = nn > 1.0e-30f ? nn : 1.0e-30f;
        const V s = 2.0f / nn;
        const V ux = (ry * z - rz * y) + rw * x;
        const V uy = (rz * x - rx * z) + rw * y;
        const V uz = (rx * y - ry * x) + rw * z;
        const V ox = x + s * ((((ry * uz - rz * uy) + rw * dx) - dw * rx) + (ry * dz - rz * dy));
        const V oy = y + s * ((((rz * ux - rx * uz) + rw * dy) - dw * ry) + (rz * dx - rx * dz));
        const V oz = z + s * ((((rx * uy - ry * ux) + rw * dz) - dw * rz) + (rx * dy - ry * dx));"""

_LBS = """
        V A[12], T[12];
        LOAD(0, A);
        for (int c = 0; c < 12; ++c) A[c] = A[c] * w0;
        const V wk[3] = {w1, w2, w3};
        for (int k = 1; k < 4; ++k) {
            LOAD(k, T);
            for (int c = 0; c < 12; ++c) A[c] += T[c] * wk[k - 1];
        }
        const V ox = A[0] * x + A[1] * y + A[2] * z + A[3];
        const V oy = A[4] * x + A[5] * y + A[6] * z + A[7];
        const V oz = A[8] * x + A[9] * y + A[10] * z + A[11];"""

# ---------------------------------------------------------------------------------------------
# scalar branch: vertex by vertex (CUDA; the CPU twin of the tests)

_SCALAR = """
    typedef float V;
    for (int i = 0; i < n; ++i) {
        const float* P = (const float*)points.data + 3 * (point_base + v0 + i);
        const int* I = (const int*)indices.data + 4 * (v0 + i);
        const float* W = (const float*)weights.data + 4 * (v0 + i);
        float pv[3], wv[4];
        int iv[4], bad = 0;  // copies, indices out of range read as joint 0
        for (int e = 0; e < 3; ++e) {
            pv[e] = P[e];
            bad |= !(pv[e] - pv[e] == 0.0f);
        }
        for (int e = 0; e < 4; ++e) {
            const bool outside = (unsigned)I[e] >= (unsigned)joint_count;
            iv[e] = outside ? 0 : I[e];
            wv[e] = W[e];
            bad |= outside | !(wv[e] >= 0.0f && wv[e] <= 3.40282347e38f);
        }
        if (check && bad) *(volatile int*)flags.data = 1;
        P = pv;
        I = iv;
        W = wv;
        const float* J = (const float*)joints.data + WIDTH * (long long)o;
        RESIDUAL_BASE
        V x = P[0], y = P[1], z = P[2];
        const V w0 = W[0], w1 = W[1], w2 = W[2], w3 = W[3];
#define LOAD(K, OUT) for (int c = 0; c < WIDTH; ++c) OUT[c] = J[WIDTH * I[K] + c]
#define LOADS(K, OUT) for (int c = 0; c < 9; ++c) OUT[c] = RS[9 * I[K] + c]
#define LOADR(K, OUT) for (int c = 0; c < 4; ++c) OUT[c] = J[WIDTH * I[K] + c]
#define LOADD(K, OUT) for (int c = 0; c < 4; ++c) OUT[c] = J[WIDTH * I[K] + 4 + c]
        MATH
#undef LOAD
#undef LOADS
#undef LOADR
#undef LOADD
        float* O = (float*)out.data + 3 * (out_base + v0 + i);
        O[0] = ox; O[1] = oy; O[2] = oz;
    }
    return 0;"""

# ---------------------------------------------------------------------------------------------
# vector branch: eight vertices in the lanes of f8

VECTOR_PRELUDE = """
    typedef float f8 __attribute__((ext_vector_type(8)));
    typedef float f4 __attribute__((ext_vector_type(4)));
    typedef int i8 __attribute__((ext_vector_type(8)));
#define SHUF __builtin_shufflevector
    // lane i of column c = component c of row i, eight rows of eight floats (AVX's 8x8 transpose)
    auto transpose8 = [](const f8* r, f8* c) {
        f8 t[8], s[8];
        for (int i = 0; i < 4; ++i) {
            t[2 * i] = SHUF(r[2 * i], r[2 * i + 1], 0, 8, 1, 9, 4, 12, 5, 13);
            t[2 * i + 1] = SHUF(r[2 * i], r[2 * i + 1], 2, 10, 3, 11, 6, 14, 7, 15);
        }
        for (int i = 0; i < 2; ++i)
            for (int h = 0; h < 2; ++h) {
                s[4 * i + 2 * h] = SHUF(t[4 * i + h], t[4 * i + h + 2], 0, 1, 8, 9, 4, 5, 12, 13);
                s[4 * i + 2 * h + 1] = SHUF(t[4 * i + h], t[4 * i + h + 2],
                                            2, 3, 10, 11, 6, 7, 14, 15);
            }
        for (int i = 0; i < 4; ++i) {
            c[i] = SHUF(s[i], s[i + 4], 0, 1, 2, 3, 8, 9, 10, 11);
            c[i + 4] = SHUF(s[i], s[i + 4], 4, 5, 6, 7, 12, 13, 14, 15);
        }
    };
    // four floats of eight rows: rows i and i + 4 side by side, then the 4x4 transpose per half
    auto transpose4 = [](const f4* q, f8* c) {
        f8 u[4], t[4];
        for (int i = 0; i < 4; ++i) u[i] = SHUF(q[i], q[i + 4], 0, 1, 2, 3, 4, 5, 6, 7);
        t[0] = SHUF(u[0], u[1], 0, 8, 1, 9, 4, 12, 5, 13);
        t[1] = SHUF(u[0], u[1], 2, 10, 3, 11, 6, 14, 7, 15);
        t[2] = SHUF(u[2], u[3], 0, 8, 1, 9, 4, 12, 5, 13);
        t[3] = SHUF(u[2], u[3], 2, 10, 3, 11, 6, 14, 7, 15);
        c[0] = SHUF(t[0], t[2], 0, 1, 8, 9, 4, 5, 12, 13);
        c[1] = SHUF(t[0], t[2], 2, 3, 10, 11, 6, 7, 14, 15);
        c[2] = SHUF(t[1], t[3], 0, 1, 8, 9, 4, 5, 12, 13);
        c[3] = SHUF(t[1], t[3], 2, 3, 10, 11, 6, 7, 14, 15);
    };
"""
"""C++ opening a vector branch: the clang vector types ``f8``, ``f4``, ``i8``, ``SHUF`` and the
lambdas ``transpose8(rows, columns)`` (eight rows of eight floats) and ``transpose4(rows,
columns)`` (eight rows of four floats into four ``f8``); close it with :data:`VECTOR_END`."""

VECTOR_END = "\n#undef SHUF\n"

STORE_VECTOR = """    // interleave x, y, z back into 24 floats
    const f8 o0 = SHUF(SHUF(ox, oy, 0, 8, -1, 1, 9, -1, 2, 10),
                       oz, 0, 1, 8, 3, 4, 9, 6, 7);
    const f8 o1 = SHUF(SHUF(ox, oy, -1, 3, 11, -1, 4, 12, -1, 5),
                       oz, 10, 1, 2, 11, 4, 5, 12, 7);
    const f8 o2 = SHUF(SHUF(ox, oy, 13, -1, 6, 14, -1, 7, 15, -1),
                       oz, 0, 13, 2, 3, 14, 5, 6, 15);
    float* O = (float*)out.data + 3 * (out_base + FIRST);
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
"""The end of a packet body (at ``    STORE_OUTPUT``): ``ox, oy, oz`` (a quantity of eight rows
each) interleaved and stored from row ``FIRST`` of ``out``, all eight or the ``n`` of a partial
last packet."""

_VECTOR = """
    typedef f8 V;
    const float* P = (const float*)points.data + 3 * (point_base + v0);
    const int* I = (const int*)indices.data + 4 * v0;
    const float* W = (const float*)weights.data + 4 * v0;
    const char* J = (const char*)joints.data + 4 * WIDTH * (long long)o;
    RESIDUAL_BASE
    float pbuf[24], wbuf[32];
    int ibuf[32];
    if (n < 8) {  // the last packet: copies, the missing lanes read lane 0's joints with zero
        for (int e = 0; e < 24; ++e) pbuf[e] = e < 3 * n ? P[e] : 0.0f;  // weights
        for (int e = 0; e < 32; ++e) ibuf[e] = e < 4 * n ? I[e] : I[e & 3];
        for (int e = 0; e < 32; ++e) wbuf[e] = e < 4 * n ? W[e] : 0.0f;
        P = pbuf;
        I = ibuf;
        W = wbuf;
    }
    f8 pa, pb, pc;
    __builtin_memcpy(&pa, P, 32);
    __builtin_memcpy(&pb, P + 8, 32);
    __builtin_memcpy(&pc, P + 16, 32);
    V x = SHUF(SHUF(pa, pb, 0, 3, 6, 9, 12, 15, -1, -1),
               pc, 0, 1, 2, 3, 4, 5, 10, 13);
    V y = SHUF(SHUF(pa, pb, 1, 4, 7, 10, 13, -1, -1, -1),
               pc, 0, 1, 2, 3, 4, 8, 11, 14);
    V z = SHUF(SHUF(pa, pb, 2, 5, 8, 11, 14, -1, -1, -1),
               pc, 0, 1, 2, 3, 4, 9, 12, 15);
    f4 wq[8];
    for (int i = 0; i < 8; ++i) __builtin_memcpy(&wq[i], W + 4 * i, 16);
    f8 wc[4];
    transpose4(wq, wc);
    const V w0 = wc[0], w1 = wc[1], w2 = wc[2], w3 = wc[3];
    if (check) {  // one test of every input of the eight vertices, as unsigned integers:
        // an index at or above joint_count (a negative one is large); a point coordinate whose
        // magnitude's bits exceed the largest finite float's (inf, NaN); a weight whose bits do,
        // -0.0 made +0.0 first (negative, inf, NaN)
        typedef unsigned int u8 __attribute__((ext_vector_type(8)));
        u8 iv[4];
        for (int q = 0; q < 4; ++q) __builtin_memcpy(&iv[q], I + 8 * q, 32);
        auto umax = [](u8 a, u8 b) { return a > b ? a : b; };
        const u8 largest = umax(umax(iv[0], iv[1]), umax(iv[2], iv[3]));
        const u8 magnitude = 0x7fffffffu;
        const u8 values = umax(
            umax(umax(__builtin_bit_cast(u8, x) & magnitude, __builtin_bit_cast(u8, y) & magnitude),
                 umax(__builtin_bit_cast(u8, z) & magnitude, __builtin_bit_cast(u8, w0 + 0.0f))),
            umax(__builtin_bit_cast(u8, w1 + 0.0f),
                 umax(__builtin_bit_cast(u8, w2 + 0.0f), __builtin_bit_cast(u8, w3 + 0.0f))));
        const u8 joints_u = (unsigned)joint_count, finite_max = 0x7f7fffffu;
        if (__builtin_reduce_or((largest >= joints_u) | (values > finite_max))) {
            *(volatile int*)flags.data = 1;
            for (int q = 0; q < 4; ++q) {  // indices outside the joints read joint 0
                const u8 zero = 0;
                iv[q] = iv[q] >= joints_u ? zero : iv[q];
                __builtin_memcpy(ibuf + 8 * q, &iv[q], 32);
            }
            I = ibuf;
        }
    }
    MATH
    STORE_OUTPUT""".replace("    STORE_OUTPUT", STORE_VECTOR.replace("FIRST", "v0"))

_VECTOR_LOAD_DQ = """
#define LOAD(K, OUT) do { f8 r_[8]; \\
        for (int i = 0; i < 8; ++i) __builtin_memcpy(&r_[i], J + 32 * I[4 * i + (K)], 32); \\
        transpose8(r_, OUT); } while (0)"""

_VECTOR_LOAD_HALVES = """
#define LOADR(K, OUT) do { f4 q_[8]; \\
        for (int i = 0; i < 8; ++i) __builtin_memcpy(&q_[i], J + 32 * I[4 * i + (K)], 16); \\
        transpose4(q_, OUT); } while (0)
#define LOADD(K, OUT) do { f4 q_[8]; \\
        for (int i = 0; i < 8; ++i) __builtin_memcpy(&q_[i], J + 32 * I[4 * i + (K)] + 16, 16); \\
        transpose4(q_, OUT); } while (0)"""

_VECTOR_LOAD_RESIDUAL = """
#define LOADS(K, OUT) do { f8 r_[8]; \\
        for (int i = 0; i < 8; ++i) __builtin_memcpy(&r_[i], RS + 36 * I[4 * i + (K)], 32); \\
        transpose8(r_, OUT); \\
        for (int i = 0; i < 8; ++i) OUT[8][i] = ((const float*)(RS + 36 * I[4 * i + (K)]))[8]; \\
        } while (0)"""

_VECTOR_LOAD_AFFINE = """
#define LOAD(K, OUT) do { f8 r_[8]; f4 q_[8]; \\
        for (int i = 0; i < 8; ++i) { \\
            __builtin_memcpy(&r_[i], J + 48 * I[4 * i + (K)], 32); \\
            __builtin_memcpy(&q_[i], J + 48 * I[4 * i + (K)] + 32, 16); } \\
        transpose8(r_, OUT); transpose4(q_, OUT + 8); } while (0)"""


def packet_source(method: str, rule: str = "sorted", scalar_on_cpu: bool = False) -> str:
    """C++ of a packet snippet: ``method`` ``"lbs"`` or ``"dqs"`` (rigid), ``rule`` the DQS
    sign rule, ``"sorted"``, ``"searched"`` or ``"running"`` (see the module docstring);
    ``scalar_on_cpu`` compiles the scalar (CUDA) branch for the CPU too (the tests' twin)."""
    if method == "lbs":
        math = _LBS
        width, load = 12, _VECTOR_LOAD_AFFINE
        scalar_base = vector_base = ""
        undef = "\n#undef LOAD"
    else:
        math = _DQS_RESIDUAL + _DQS_RULES[rule] + _DQS_APPLY
        width, load = 8, _VECTOR_LOAD_DQ + _VECTOR_LOAD_HALVES + _VECTOR_LOAD_RESIDUAL
        scalar_base = "const float* RS = (const float*)residuals.data + 9 * (long long)o;"
        vector_base = "const char* RS = (const char*)residuals.data + 36 * (long long)o;"
        undef = "\n#undef LOAD\n#undef LOADS\n#undef LOADR\n#undef LOADD"
    scalar = (_SCALAR.replace("MATH", math)
              .replace("RESIDUAL_BASE", scalar_base))
    vector = VECTOR_PRELUDE + (_VECTOR.replace("RESIDUAL_BASE", vector_base)
                               .replace("    MATH", load + math + undef)) + VECTOR_END
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    body = f"""
    const int n = count - v0 < 8 ? count - v0 : 8;
#if {cond}
{scalar}
#else
{vector}
#endif
"""
    return body.replace("WIDTH", str(width))


@wp.func_native(packet_source("lbs"))
def lbs_packet(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
               indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
               joints: wp.array(dtype=mat34), o: int, v0: int, count: int,
               out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
               check: int, flags: wp.array(dtype=wp.int32)) -> int:
    """LBS of vertices ``v0 .. min(v0 + 8, count) - 1`` (points ``point_base + v``, out
    ``out_base + v``) with the affines from element ``o``. With ``check``, an index outside
    ``0 .. joint_count - 1`` reads joint 0 and, as a non-finite point or a negative or non-finite
    weight, sets ``flags[0] = 1`` (the caller then names the problem)."""
    ...


@wp.func_native(packet_source("dqs"))
def dqs_sorted_packet(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
                      indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                      joints: wp.array(dtype=vec8), residuals: wp.array(dtype=wp.mat33),
                      scaled: int, o: int, v0: int, count: int,
                      out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                      check: int, flags: wp.array(dtype=wp.int32)) -> int:
    """DQS, pivot in slot 0 (sorted layout), of the vertices of :func:`lbs_packet`; ``scaled``:
    the frame has scale/shear, the points first blended through ``residuals`` (from ``o``)."""
    ...


@wp.func_native(packet_source("dqs", "searched"))
def dqs_searched_packet(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
                        indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                        joints: wp.array(dtype=vec8), residuals: wp.array(dtype=wp.mat33),
                        scaled: int, o: int, v0: int, count: int,
                        out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                        check: int, flags: wp.array(dtype=wp.int32)) -> int:
    """DQS, pivot searched (input order), otherwise as :func:`dqs_sorted_packet`."""
    ...


@wp.func_native(packet_source("dqs", "running"))
def dqs_running_packet(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
                       indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                       joints: wp.array(dtype=vec8), residuals: wp.array(dtype=wp.mat33),
                       scaled: int, o: int, v0: int, count: int,
                       out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                       check: int, flags: wp.array(dtype=wp.int32)) -> int:
    """DQS, signs against the running sum (input order), otherwise as
    :func:`dqs_sorted_packet`."""
    ...


VERTICES = 8
"""Vertices a packet kernel's thread skins."""

PACKETS = {(0, None): lbs_packet, (1, "sorted"): dqs_sorted_packet,
           (1, "searched"): dqs_searched_packet, (1, "running"): dqs_running_packet}
"""The packet snippet of ``(method, sign rule)`` (:data:`.skin.LBS` 0, :data:`.skin.DQS` 1)."""
