"""The rigid FK step as native snippets: local matrix → quaternion (Shepperd), composed onto the
parent's dual quaternion, normalized (:func:`rigid_step`); a unit dual quaternion → its 4×4
matrix (:func:`rigid_matrix`).

Warp compiles ``@wp.func`` quaternion arithmetic to scalar code on the CPU. On the CPU these
snippets hold quaternions in clang vectors (``ext_vector_type(4)``): a Hamilton product is four
multiply-adds of whole vectors against sign-flipped shuffles of the other factor
(``tools/bench.py``'s FK table measures the kernel).

:func:`rigid_packet` takes one joint of eight frames at once, each quantity in the lanes of an
``ext_vector_type(8)`` (the transposes of :mod:`.packets`), for :mod:`.fk`'s packet kernel; on
CUDA it takes no lane and leaves every frame to the one-frame path.

On CUDA (``__CUDA_ARCH__``) they are the same arithmetic written out in scalars. That branch is
also compiled for the CPU by :func:`scalar_step_source`'s twin in the tests, so its arithmetic is
checked on every machine, not only where a GPU is.

Quaternions are ``(w, x, y, z)`` here, in the vector's lanes ``.x .y .z .w`` in that order; the
dual quaternion of a pose is ``r + ε·½·t·r`` (:mod:`.dqmath`).
"""

import warp as wp

from .dqmath import vec8
from .packets import VECTOR_END, VECTOR_PRELUDE

wp.set_module_options({"enable_backward": False})  # forward-only kernels

# Shepperd's quaternion (w, x, y, z) of m's linear part, times a positive factor, by selects
_SHEPPERD = """
    const float m00 = m.data[0][0], m11 = m.data[1][1], m22 = m.data[2][2];
    const float d0 = m.data[2][1] - m.data[1][2], d1 = m.data[0][2] - m.data[2][0],
                d2 = m.data[1][0] - m.data[0][1];
    const float s0 = m.data[0][1] + m.data[1][0], s1 = m.data[0][2] + m.data[2][0],
                s2 = m.data[1][2] + m.data[2][1];
    const float tr = m00 + m11 + m22;
    const float b1 = m11 > m22 ? m11 : m22;
    const float big = m00 > b1 ? m00 : b1;
    const bool cw = tr >= big;
    const bool cx = !cw && m00 == big;
    const bool cy = !cw && !cx && m11 == big;
    // scaled by 1/4 (exact): 1/2 t q cannot overflow for any float32 t
    const float qw = 0.25f * (cw ? 1.0f + tr : cx ? d0 : cy ? d1 : d2);
    const float qx = 0.25f * (cw ? d0 : cx ? 1.0f + m00 - m11 - m22 : cy ? s0 : s1);
    const float qy = 0.25f * (cw ? d1 : cx ? s0 : cy ? 1.0f - m00 + m11 - m22 : s2);
    const float qz = 0.25f * (cw ? d2 : cx ? s1 : cy ? s2 : 1.0f - m00 - m11 + m22);
    const float n = 1.0f / sqrtf(qw * qw + qx * qx + qy * qy + qz * qz);
    const float t0 = m.data[0][3], t1 = m.data[1][3], t2 = m.data[2][3];
"""

# parent (rw..dz) or the identity; u = d + 1/2 r (0, t); result (r q, u q) * n
_SCALAR_STEP = """
    float rw = 1.0f, rx = 0.0f, ry = 0.0f, rz = 0.0f, dw = 0.0f, dx = 0.0f, dy = 0.0f, dz = 0.0f;
    if (has_parent) {
        rw = parent.c[0]; rx = parent.c[1]; ry = parent.c[2]; rz = parent.c[3];
        dw = parent.c[4]; dx = parent.c[5]; dy = parent.c[6]; dz = parent.c[7];
    }
    const float uw = dw - 0.5f * (rx * t0 + ry * t1 + rz * t2);
    const float ux = dx + 0.5f * (rw * t0 + ry * t2 - rz * t1);
    const float uy = dy + 0.5f * (rw * t1 - rx * t2 + rz * t0);
    const float uz = dz + 0.5f * (rw * t2 + rx * t1 - ry * t0);
    wp::vec_t<8, float> out;
    out.c[0] = n * (rw * qw - rx * qx - ry * qy - rz * qz);
    out.c[1] = n * (rw * qx + rx * qw + ry * qz - rz * qy);
    out.c[2] = n * (rw * qy - rx * qz + ry * qw + rz * qx);
    out.c[3] = n * (rw * qz + rx * qy - ry * qx + rz * qw);
    out.c[4] = n * (uw * qw - ux * qx - uy * qy - uz * qz);
    out.c[5] = n * (uw * qx + ux * qw + uy * qz - uz * qy);
    out.c[6] = n * (uw * qy - ux * qz + uy * qw + uz * qx);
    out.c[7] = n * (uw * qz + ux * qy - uy * qx + uz * qw);
    return out;
"""

# a (w, x, y, z) times B as a sum of B's signed shuffles: i·B, j·B, k·B
_VECTOR_TYPES = """
    typedef float f4 __attribute__((ext_vector_type(4)));
"""
_LEFT = """
    const f4 NAME1 = NAME.yxwz * (f4){-1.0f, 1.0f, -1.0f, 1.0f};
    const f4 NAME2 = NAME.zwxy * (f4){-1.0f, 1.0f, 1.0f, -1.0f};
    const f4 NAME3 = NAME.wzyx * (f4){-1.0f, -1.0f, 1.0f, 1.0f};
"""
_VECTOR_STEP = _VECTOR_TYPES + """
    const f4 B = (f4){qw, qx, qy, qz};""" + _LEFT.replace("NAME", "B") + """
    f4 ra = (f4){1.0f, 0.0f, 0.0f, 0.0f}, da = (f4){0.0f, 0.0f, 0.0f, 0.0f};
    if (has_parent) {
        __builtin_memcpy(&ra, &parent, 16);
        __builtin_memcpy(&da, (const char*)&parent + 16, 16);
    }
    const f4 T = (f4){0.0f, t0, t1, t2} * 0.5f;""" + _LEFT.replace("NAME", "T") + """
    const f4 u = da + ra.x * T + ra.y * T1 + ra.z * T2 + ra.w * T3;
    const f4 r = (ra.x * B + ra.y * B1 + ra.z * B2 + ra.w * B3) * n;
    const f4 d = (u.x * B + u.y * B1 + u.z * B2 + u.w * B3) * n;
    wp::vec_t<8, float> out;
    __builtin_memcpy(&out, &r, 16);
    __builtin_memcpy((char*)&out + 16, &d, 16);
    return out;
"""


def step_source(scalar_on_cpu: bool = False) -> str:
    """C++ of :func:`rigid_step`: vectors on the CPU, scalars on CUDA (and on the CPU too with
    ``scalar_on_cpu``, for the tests)."""
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    return (_SHEPPERD + f"#if {cond}\n" + _SCALAR_STEP + "#else\n" + _VECTOR_STEP
            + "#endif\n")


# rotation from r; translation 2·d·r*
_SCALAR_MATRIX = """
    const float w = a.c[0], x = a.c[1], y = a.c[2], z = a.c[3];
    const float ew = a.c[4], ex = a.c[5], ey = a.c[6], ez = a.c[7];
    const float tx = 2.0f * (-ew * x + ex * w - ey * z + ez * y);
    const float ty = 2.0f * (-ew * y + ex * z + ey * w - ez * x);
    const float tz = 2.0f * (-ew * z - ex * y + ey * x + ez * w);
"""
_VECTOR_MATRIX = _VECTOR_TYPES + """
    f4 r, d;
    __builtin_memcpy(&r, &a, 16);
    __builtin_memcpy(&d, (const char*)&a + 16, 16);
    const f4 C = r * (f4){1.0f, -1.0f, -1.0f, -1.0f};""" + _LEFT.replace("NAME", "C") + """
    const f4 t = (d.x * C + d.y * C1 + d.z * C2 + d.w * C3) * 2.0f;
    const float w = r.x, x = r.y, y = r.z, z = r.w;
    const float tx = t.y, ty = t.z, tz = t.w;
"""
_MATRIX_TAIL = """
    const float x2 = x + x, y2 = y + y, z2 = z + z;
    const float xx = x * x2, yy = y * y2, zz = z * z2, xy = x * y2, xz = x * z2, yz = y * z2;
    const float wx = w * x2, wy = w * y2, wz = w * z2;
    wp::mat_t<4, 4, float> o;
    o.data[0][0] = 1.0f - yy - zz; o.data[0][1] = xy - wz; o.data[0][2] = xz + wy;
    o.data[0][3] = tx;
    o.data[1][0] = xy + wz; o.data[1][1] = 1.0f - xx - zz; o.data[1][2] = yz - wx;
    o.data[1][3] = ty;
    o.data[2][0] = xz - wy; o.data[2][1] = yz + wx; o.data[2][2] = 1.0f - xx - yy;
    o.data[2][3] = tz;
    o.data[3][0] = 0.0f; o.data[3][1] = 0.0f; o.data[3][2] = 0.0f; o.data[3][3] = 1.0f;
    return o;
"""


def matrix_source(scalar_on_cpu: bool = False) -> str:
    """C++ of :func:`rigid_matrix` (see :func:`step_source`)."""
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    return (f"#if {cond}\n" + _SCALAR_MATRIX + "#else\n" + _VECTOR_MATRIX + "#endif\n"
            + _MATRIX_TAIL)


@wp.func_native(step_source())
def rigid_step(m: wp.mat44, parent: vec8, has_parent: int) -> vec8:
    """Unit DQ ``parent · η(R, t)`` (``parent`` ignored unless ``has_parent``) of a local matrix
    ``m = [R | t]`` whose linear part is a rotation."""
    ...


@wp.func_native(matrix_source())
def rigid_matrix(a: vec8) -> wp.mat44:
    """4×4 rigid matrix (column-vector convention) of unit dual quaternion ``a``."""
    ...


# finiteness (0·m summed: 0, or NaN at a NaN/inf entry) and the rotation error of m's linear part
# from its rows R0..R2: column norms Σ R∘R, column dots Σ R∘R.yzx, determinant R0·(R1×R2)
_SCALAR_CHECK = """
    float z = 0.0f;
    for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c)
            z += 0.0f * m.data[r][c];
    float n[3], o[3];
    for (int c = 0; c < 3; ++c) {
        const int c1 = c == 2 ? 0 : c + 1;
        n[c] = m.data[0][c] * m.data[0][c] + m.data[1][c] * m.data[1][c]
               + m.data[2][c] * m.data[2][c];
        o[c] = m.data[0][c] * m.data[0][c1] + m.data[1][c] * m.data[1][c1]
               + m.data[2][c] * m.data[2][c1];
    }
    const float det = m.data[0][0] * (m.data[1][1] * m.data[2][2] - m.data[1][2] * m.data[2][1])
                    + m.data[0][1] * (m.data[1][2] * m.data[2][0] - m.data[1][0] * m.data[2][2])
                    + m.data[0][2] * (m.data[1][0] * m.data[2][1] - m.data[1][1] * m.data[2][0]);
    const float err = fabsf(n[0] - 1.0f) + fabsf(n[1] - 1.0f) + fabsf(n[2] - 1.0f)
                    + fabsf(o[0]) + fabsf(o[1]) + fabsf(o[2]) + fabsf(det - 1.0f);
    return wp::vec_t<2, float>(z, err);
"""
_VECTOR_CHECK = _VECTOR_TYPES + """
    f4 R0, R1, R2, R3;
    __builtin_memcpy(&R0, &m.data[0][0], 16);
    __builtin_memcpy(&R1, &m.data[1][0], 16);
    __builtin_memcpy(&R2, &m.data[2][0], 16);
    __builtin_memcpy(&R3, &m.data[3][0], 16);
    const f4 Z = R0 * 0.0f + R1 * 0.0f + R2 * 0.0f + R3 * 0.0f;  // no sum can overflow first
    const f4 n = R0 * R0 + R1 * R1 + R2 * R2;
    const f4 o = R0 * R0.yzxw + R1 * R1.yzxw + R2 * R2.yzxw;
    const f4 x = R1.yzxw * R2.zxyw - R1.zxyw * R2.yzxw;
    const f4 dd = R0 * x;
    const float det = dd.x + dd.y + dd.z;
    const f4 e = __builtin_elementwise_abs(n - 1.0f) + __builtin_elementwise_abs(o);
    const float err = e.x + e.y + e.z + fabsf(det - 1.0f);
    return wp::vec_t<2, float>(Z.x + Z.y + Z.z + Z.w, err);
"""


def check_source(scalar_on_cpu: bool = False) -> str:
    """C++ of :func:`local_check` (see :func:`step_source`)."""
    cond = "1" if scalar_on_cpu else "defined(__CUDA_ARCH__)"
    return f"#if {cond}\n" + _SCALAR_CHECK + "#else\n" + _VECTOR_CHECK + "#endif\n"


@wp.func_native(check_source())
def local_check(m: wp.mat44) -> wp.vec2:
    """``(z, err)`` of a local matrix: ``z`` is 0 when every entry is finite, NaN otherwise;
    ``err`` the rotation error of its linear part ``A`` (``Σ|‖cᵢ‖² − 1| + Σ|cᵢ·cⱼ| +
    |det A − 1|`` over its columns; below ~1e-6 for a float32 rotation, NaN with ``z``)."""
    ...


# ---------------------------------------------------------------------------------------------
# eight frames of one joint at a time (CPU): the rigid step of :func:`rigid_step` in the lanes of
# clang vectors, for :mod:`.fk`'s packet kernel

_PACKET_VECTOR = """
    long long row[8], up[8];
    for (int l = 0; l < 8; ++l) {  // lanes past the last frame repeat lane 0 (not stored)
        const long long base = (long long)(f0 + (l < n ? l : 0)) * stride;
        row[l] = base + j;
        up[l] = base + (pj < 0 ? 0 : pj);
    }
    const float* MS = (const float*)matrices.data;
    f8 ra[8], rb[8], M[16];
    for (int l = 0; l < 8; ++l) {
        __builtin_memcpy(&ra[l], MS + 16 * row[l], 32);
        __builtin_memcpy(&rb[l], MS + 16 * row[l] + 8, 32);
    }
    transpose8(ra, M);  // M[4 r + c] = m[r][c]
    transpose8(rb, M + 8);
    // local_check's rotation error, its vector branch's expressions one for one (the same
    // roundings and contractions, so both paths take the same joints)
    const f8 n0 = M[0] * M[0] + M[4] * M[4] + M[8] * M[8];
    const f8 n1 = M[1] * M[1] + M[5] * M[5] + M[9] * M[9];
    const f8 n2 = M[2] * M[2] + M[6] * M[6] + M[10] * M[10];
    const f8 o0 = M[0] * M[1] + M[4] * M[5] + M[8] * M[9];
    const f8 o1 = M[1] * M[2] + M[5] * M[6] + M[9] * M[10];
    const f8 o2 = M[2] * M[0] + M[6] * M[4] + M[10] * M[8];
    const f8 k0 = M[5] * M[10] - M[6] * M[9];  // row 1 × row 2
    const f8 k1 = M[6] * M[8] - M[4] * M[10];
    const f8 k2 = M[4] * M[9] - M[5] * M[8];
    const f8 dd0 = M[0] * k0, dd1 = M[1] * k1, dd2 = M[2] * k2;
    const f8 det = dd0 + dd1 + dd2;
    const f8 e0 = __builtin_elementwise_abs(n0 - 1.0f) + __builtin_elementwise_abs(o0);
    const f8 e1 = __builtin_elementwise_abs(n1 - 1.0f) + __builtin_elementwise_abs(o1);
    const f8 e2 = __builtin_elementwise_abs(n2 - 1.0f) + __builtin_elementwise_abs(o2);
    const f8 err = e0 + e1 + e2 + __builtin_elementwise_abs(det - 1.0f);
    // and local_check's finiteness: 0 times every entry, summed (NaN at a NaN or inf entry,
    // then the frame goes back to the one-frame code, which names it)
    f8 zero = M[0] * 0.0f;
    for (int c = 1; c < 16; ++c) zero += M[c] * 0.0f;
    i8 take = (err < 1.0e-6f) & (zero == 0.0f);
    f8 P[8];
    if (pj >= 0) {  // the parents' unit dual quaternions, where rigid
        f8 pr[8];
        i8 rigid;
        for (int l = 0; l < 8; ++l) {
            rigid[l] = ((const unsigned char*)world_rigid.data)[up[l]] ? -1 : 0;
            __builtin_memcpy(&pr[l], (const float*)world_dqs.data + 8 * up[l], 32);
        }
        transpose8(pr, P);
        take = take & rigid;
    } else {
        P[0] = 1.0f;
        for (int c = 1; c < 8; ++c) P[c] = 0.0f;
    }
    int mask = 0;
    for (int l = 0; l < n; ++l) mask |= take[l] ? 1 << l : 0;
    const int all = (1 << n) - 1;
    if (mask == 0) return all;
    // Shepperd's quaternion by selects, scaled by 1/4, as rigid_step
    const f8 m00 = M[0], m11 = M[5], m22 = M[10];
    const f8 d0 = M[9] - M[6], d1 = M[2] - M[8], d2 = M[4] - M[1];
    const f8 s0 = M[1] + M[4], s1 = M[2] + M[8], s2 = M[6] + M[9];
    const f8 tr = m00 + m11 + m22;
    const f8 b1 = m11 > m22 ? m11 : m22;
    const f8 big = m00 > b1 ? m00 : b1;
    const i8 cw = tr >= big;
    const i8 cx = ~cw & (m00 == big);
    const i8 cy = ~cw & ~cx & (m11 == big);
    const f8 qw = 0.25f * (cw ? 1.0f + tr : cx ? d0 : cy ? d1 : d2);
    const f8 qx = 0.25f * (cw ? d0 : cx ? 1.0f + m00 - m11 - m22 : cy ? s0 : s1);
    const f8 qy = 0.25f * (cw ? d1 : cx ? s0 : cy ? 1.0f - m00 + m11 - m22 : s2);
    const f8 qz = 0.25f * (cw ? d2 : cx ? s1 : cy ? s2 : 1.0f - m00 - m11 + m22);
    const f8 nn = 1.0f / __builtin_elementwise_sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    // rigid_step's vector branch, one lane per frame: B·(w, x, y, z) as the sum of B's signed
    // shuffles B1..B3 (and T's), the same expressions one for one
    const f8 Z = 0.0f;
    const f8 h0 = M[3] * 0.5f, h1 = M[7] * 0.5f, h2 = M[11] * 0.5f;
    const f8 Zh = Z * 0.5f;
    const f8 B[4] = {qw, qx, qy, qz}, B1[4] = {-qx, qw, -qz, qy};
    const f8 B2[4] = {-qy, qz, qw, -qx}, B3[4] = {-qz, -qy, qx, qw};
    const f8 T[4] = {Zh, h0, h1, h2}, T1[4] = {-h0, Zh, -h2, h1};
    const f8 T2[4] = {-h1, h2, Zh, -h0}, T3[4] = {-h2, -h1, h0, Zh};
    const f8 rw = P[0], rx = P[1], ry = P[2], rz = P[3];
    f8 u[4], E[8];
    for (int c = 0; c < 4; ++c)
        u[c] = P[4 + c] + rw * T[c] + rx * T1[c] + ry * T2[c] + rz * T3[c];
    for (int c = 0; c < 4; ++c) {
        E[c] = (rw * B[c] + rx * B1[c] + ry * B2[c] + rz * B3[c]) * nn;
        E[4 + c] = (u[0] * B[c] + u[1] * B1[c] + u[2] * B2[c] + u[3] * B3[c]) * nn;
    }
    // rigid_matrix's: translation from the conjugate's signed shuffles, rotation as its tail
    const f8 w = E[0], x = E[1], y = E[2], z = E[3];
    const f8 ew = E[4], ex = E[5], ey = E[6], ez = E[7];
    const f8 x2 = x + x, y2 = y + y, z2 = z + z;
    const f8 xx = x * x2, yy = y * y2, zz = z * z2, xy = x * y2, xz = x * z2, yz = y * z2;
    const f8 wx = w * x2, wy = w * y2, wz = w * z2;
    f8 O[16];
    O[0] = 1.0f - yy - zz; O[1] = xy - wz; O[2] = xz + wy;
    O[3] = (ew * -x + ex * w + ey * -z + ez * y) * 2.0f;
    O[4] = xy + wz; O[5] = 1.0f - xx - zz; O[6] = yz - wx;
    O[7] = (ew * -y + ex * z + ey * w + ez * -x) * 2.0f;
    O[8] = xz - wy; O[9] = yz + wx; O[10] = 1.0f - xx - yy;
    O[11] = (ew * -z + ex * -y + ey * x + ez * w) * 2.0f;
    O[12] = 0.0f; O[13] = 0.0f; O[14] = 0.0f; O[15] = 1.0f;
    f8 er[8], oa[8], ob[8];
    transpose8(E, er);
    transpose8(O, oa);
    transpose8(O + 8, ob);
    for (int l = 0; l < n; ++l) {
        if (!take[l]) continue;
        __builtin_memcpy((float*)world_dqs.data + 8 * row[l], &er[l], 32);
        __builtin_memcpy((float*)world.data + 16 * row[l], &oa[l], 32);
        __builtin_memcpy((float*)world.data + 16 * row[l] + 8, &ob[l], 32);
        ((unsigned char*)world_rigid.data)[row[l]] = 1;
    }
    return all & ~mask;
"""


def packet_source(all_fallback: bool = False) -> str:
    """C++ of :func:`rigid_packet`: vectors on the CPU; on CUDA (and with ``all_fallback``, the
    tests' twin) it takes no lane, so the kernel's one-frame path does every joint."""
    cond = "1" if all_fallback else "defined(__CUDA_ARCH__)"
    return (f"#if {cond}\n    return (1 << n) - 1;\n#else\n" + VECTOR_PRELUDE + _PACKET_VECTOR
            + VECTOR_END + "#endif\n")


@wp.func_native(packet_source())
def rigid_packet(matrices: wp.array(dtype=wp.mat44), world: wp.array(dtype=wp.mat44),
                 world_dqs: wp.array(dtype=vec8), world_rigid: wp.array(dtype=wp.uint8),
                 f0: int, n: int, stride: int, j: int, pj: int) -> int:
    """Joint ``j`` (parent ``pj``, −1 for a root) of frames ``f0 .. f0 + n − 1`` (``n ≤ 8``; a
    frame's joints start at ``f·stride`` in the flat arrays): each lane whose local matrix is
    finite and a rotation (as :func:`local_check`) under a rigid parent (or none) gets its world
    dual quaternion, matrix and rigid flag stored, as :func:`rigid_step` and
    :func:`rigid_matrix` would give; returns the bit mask of the other lanes (bit ``l``: frame
    ``f0 + l``), for the one-frame path."""
    ...
