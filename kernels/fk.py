"""Forward kinematics: local joint transforms → world transforms, concatenated as dual quaternions.

A joint transform is carried as a pair ``(η, S)``: a unit dual quaternion ``η`` (rotation ``R`` and
translation ``t``) and a 3×3 residual ``S`` applied first, so ``M = [R·S | t]``. Rigid joints have
``S = I`` and FK is pure dual-quaternion concatenation. With scale or shear the pair still composes
exactly::

    (η_p, S_p) ∘ (η_l, S_l) = (η_p · η(R_l, S_p·t_l),  R_lᵀ · S_p · R_l · S_l)

which reduces to ``η_p · η_l`` when ``S_p = I``. Local matrices are split by the polar decomposition
``A = R·S`` (the same split UsdSkel uses for its DQS); local TRS poses (what animations store) need
no split: ``η = η(q, t)`` and ``S = diag(s)``.

Kernels run one thread per (frame, skeleton), walking that skeleton's joints parents-first;
``parents`` holds global joint indices (−1 for roots) and skeleton ``s`` owns joints
``skeleton_start[s] .. skeleton_start[s+1]-1`` of the concatenated joint axis. Poses are flat
(F·J,) arrays, frame-major.

The rigid case is the fast path: a cheap rotation check, the local quaternion by branch-free
selects, one DQ product (without forming the child's own DQ), normalization after it, the matrix
written straight from the result. Each joint keeps a rigid flag; residuals are stored only for
non-rigid joints, and only their descendants take the residual composition.

On the CPU, from :data:`PACKET_MIN_FRAMES` frames of local matrices, a thread carries one
skeleton through eight frames at once (:func:`packet_kernel`): each joint's fast path runs in
the lanes of clang vectors (:func:`~.fk_native.rigid_packet`), and the frames it leaves take the
one-frame path, with the same expressions, so both give the same bits.
"""

import warp as wp

from .._warp import Device
from . import fk_native as native
from .buffers import empty
from .dqmath import dq_from_rt, dq_mul, mat44_linear, polar_rotation, vec8
from .grid import is_cpu, launch, launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.struct
class LocalPoses:
    """Parent-relative joint poses, flat (F·J,) (frame-major): 4×4 ``matrices``, or
    ``translations``, ``rotations`` ``(w, x, y, z)`` of any positive length and ``scales``
    (``M = T·R·S``); the other kind stays unset."""

    matrices: wp.array(dtype=wp.mat44)
    translations: wp.array(dtype=wp.vec3)
    rotations: wp.array(dtype=wp.vec4)
    scales: wp.array(dtype=wp.vec3)


@wp.func
def rotation_quat(m: wp.mat33):
    """Warp quaternion ``(x, y, z, w)`` of rotation matrix ``m``, times a positive factor (not
    normalized). Shepperd's method: the row of ``4·q·qᵀ`` with the largest diagonal term, picked
    by scalar selects (no branches: random rotations mispredict them)."""
    m00 = m[0, 0]
    m11 = m[1, 1]
    m22 = m[2, 2]
    d0 = m[2, 1] - m[1, 2]  # 4wx
    d1 = m[0, 2] - m[2, 0]  # 4wy
    d2 = m[1, 0] - m[0, 1]  # 4wz
    s0 = m[0, 1] + m[1, 0]  # 4xy
    s1 = m[0, 2] + m[2, 0]  # 4xz
    s2 = m[1, 2] + m[2, 1]  # 4yz
    tr = m00 + m11 + m22
    big = wp.max(m00, wp.max(m11, m22))
    cw = tr >= big
    cx = not cw and m00 == big
    cy = not cw and not cx and m11 == big
    x = wp.where(cw, d0, wp.where(cx, 1.0 + m00 - m11 - m22, wp.where(cy, s0, s1)))
    y = wp.where(cw, d1, wp.where(cx, s0, wp.where(cy, 1.0 - m00 + m11 - m22, s2)))
    z = wp.where(cw, d2, wp.where(cx, s1, wp.where(cy, s2, 1.0 - m00 - m11 + m22)))
    w = wp.where(cw, 1.0 + tr, wp.where(cx, d0, wp.where(cy, d1, d2)))
    return wp.quat(x, y, z, w)


@wp.func
def hamilton(a: wp.vec4, b: wp.vec4):
    """Quaternion product ``a·b``, both ``(w, x, y, z)``."""
    return wp.vec4(a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
                   a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
                   a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
                   a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0])


@wp.func
def compose(a: vec8, q: wp.quat, t: wp.vec3):
    """``a·η(q, t)`` without forming ``η(q, t) = q + ε·½·t·q``: real ``r_a·q``, dual
    ``(d_a + ½·r_a·t)·q`` (16 products fewer than :func:`dq_mul` of :func:`dq_from_rt`). Linear
    in ``q``: a scaled ``q`` scales the result."""
    u = wp.vec4(a[4] - 0.5 * (a[1] * t[0] + a[2] * t[1] + a[3] * t[2]),
                a[5] + 0.5 * (a[0] * t[0] + a[2] * t[2] - a[3] * t[1]),
                a[6] + 0.5 * (a[0] * t[1] - a[1] * t[2] + a[3] * t[0]),
                a[7] + 0.5 * (a[0] * t[2] + a[1] * t[1] - a[2] * t[0]))
    b = wp.vec4(q[3], q[0], q[1], q[2])
    r = hamilton(wp.vec4(a[0], a[1], a[2], a[3]), b)
    d = hamilton(u, b)
    return vec8(r[0], r[1], r[2], r[3], d[0], d[1], d[2], d[3])


@wp.func
def is_rigid(m: wp.mat44):
    """True when the linear part of ``m`` is a rotation (to ~1e-6): columns ``c0``, ``c1``
    orthonormal and ``c2 = c0 × c1`` (which makes it unit, orthogonal to both and det = +1; a
    reflection has ``c2 = −c0 × c1``)."""
    c0 = wp.vec3(m[0, 0], m[1, 0], m[2, 0])
    c1 = wp.vec3(m[0, 1], m[1, 1], m[2, 1])
    e = wp.vec3(m[0, 2], m[1, 2], m[2, 2]) - wp.cross(c0, c1)
    err = (wp.abs(wp.dot(c0, c0) - 1.0) + wp.abs(wp.dot(c1, c1) - 1.0) + wp.abs(wp.dot(c0, c1))
           + wp.abs(e[0]) + wp.abs(e[1]) + wp.abs(e[2]))
    return err < 1.0e-6


@wp.func
def split_matrix(m: wp.mat44):
    """``(rotation, translation, rigid)`` of a local 4×4 matrix: its linear part when that is a
    rotation, else the rotation of its polar split ``A = R·S``; the rotation is a quaternion
    times a positive factor."""
    a = mat44_linear(m)
    rigid = is_rigid(m)
    r = a
    if not rigid:
        r = polar_rotation(a)
    return rotation_quat(r), wp.vec3(m[0, 3], m[1, 3], m[2, 3]), rigid


@wp.func
def local_residual(m: wp.mat44, q: wp.quat):
    """Residual ``S = Rᵀ·A`` of a local matrix whose rotation is ``q``."""
    return wp.transpose(wp.quat_to_matrix(q)) * mat44_linear(m)


@wp.func
def split_trs(r: wp.vec4, sc: wp.vec3):
    """``(rotation, rigid)`` of a TRS pose (``r`` is ``(w, x, y, z)``, any positive length)."""
    rigid = sc[0] == 1.0 and sc[1] == 1.0 and sc[2] == 1.0
    return wp.quat(r[1], r[2], r[3], r[0]), rigid


@wp.func
def store_general(i: int, k: int, q: wp.quat, t: wp.vec3, res: wp.mat33, eta: vec8,
                  world: wp.array(dtype=wp.mat44), world_dqs: wp.array(dtype=vec8),
                  world_residuals: wp.array(dtype=wp.mat33),
                  world_rigid: wp.array(dtype=wp.uint8)):
    """Store joint ``i`` with local residual ``res`` (``eta``: its DQ, already composed onto a
    rigid parent). ``k >= 0`` is a non-rigid parent: ``(η_p·η(R_l, S_p·t_l), R_lᵀ·S_p·R_l·S_l)``."""
    e = eta
    s = res
    if k >= 0:
        sp = world_residuals[k]
        r = wp.quat_to_matrix(q)
        e = dq_mul(world_dqs[k], dq_from_rt(q, sp * t))
        s = wp.transpose(r) * sp * r * res
    world_dqs[i] = e
    world_residuals[i] = s
    world_rigid[i] = wp.uint8(0)
    x = native.rigid_matrix(e)
    lin = mat44_linear(x) * s
    world[i] = wp.mat44(lin[0, 0], lin[0, 1], lin[0, 2], x[0, 3],
                        lin[1, 0], lin[1, 1], lin[1, 2], x[1, 3],
                        lin[2, 0], lin[2, 1], lin[2, 2], x[2, 3],
                        0.0, 0.0, 0.0, 1.0)


@wp.func
def general_joint(i: int, j: int, base: int, q: wp.quat, t: wp.vec3, rigid: bool,
                  poses: LocalPoses, trs: int, parents: wp.array(dtype=wp.int32),
                  world: wp.array(dtype=wp.mat44), world_dqs: wp.array(dtype=vec8),
                  world_residuals: wp.array(dtype=wp.mat33),
                  world_rigid: wp.array(dtype=wp.uint8)):
    """Joint ``i`` (``j`` in its skeleton, its frame's joints from ``base``) off the rigid fast
    path, from its local rotation ``q`` (times a positive factor), translation ``t`` and whether
    its local transform is rigid; the residual from ``poses`` (scales when ``trs``)."""
    # q is the rotation times a positive factor (up to 4 from a matrix): scaled by ¼
    # (exact) so ½·t·q cannot overflow for any float32 t, and normalized after the
    # product, so the square root and division run beside it rather than before it
    q = q * 0.25
    n = 1.0 / wp.sqrt(wp.dot(q, q))
    eta = vec8()
    p = parents[j]
    k = -1
    if p >= 0:
        k = base + p
        if world_rigid[k] != wp.uint8(0):
            eta = compose(world_dqs[k], q, t)
            k = -1
        else:
            eta = dq_from_rt(q, t)
    else:
        eta = dq_from_rt(q, t)
    eta = eta * n
    if rigid and k < 0:
        world_dqs[i] = eta
        world_rigid[i] = wp.uint8(1)
        world[i] = native.rigid_matrix(eta)
    else:
        res = wp.identity(n=3, dtype=float)
        if not rigid:
            if trs != 0:
                res = wp.diag(poses.scales[i])
            else:
                res = local_residual(poses.matrices[i], q * n)
        store_general(i, k, q * n, t, res, eta, world, world_dqs, world_residuals,
                      world_rigid)


PACKET_FRAMES = 8
"""Frames of one skeleton a packet-kernel thread carries (:func:`~.fk_native.rigid_packet`)."""

PACKET_MIN_FRAMES = 3
"""Frames from which the CPU runs the packet kernel (fewer fill too few of its eight lanes: one
thread, 500 skeletons of 19 random rigid joints, packet ÷ one-frame kernel time 1.02 at 2 frames,
0.68 at 3, 0.57 at 4, 0.47 at 6, 0.62 at 8, 0.82 at 16)."""


def _forward_kinematics_kernel(trs, name, rigid_packet=None):
    """FK from :class:`LocalPoses` of one kind, resolved at compile time: one thread per (frame,
    skeleton) row, or with ``rigid_packet`` (local matrices; :func:`~.fk_native.rigid_packet`,
    or in the tests its CUDA branch, which leaves every frame to the one-frame code) per (block
    of eight frames, skeleton) row, block-major: each joint of the eight frames at once, the
    frames the snippet leaves (not a rotation, a non-rigid parent, not finite) one by one as in
    the one-frame kernel. The outputs (a :class:`WorldPoses`) are top-level arrays: Warp gives
    contiguous top-level arrays constant strides, arrays in a struct not (a stride loaded at
    every access)."""

    def kernel(
        parents: wp.array(dtype=wp.int32),
        skeleton_start: wp.array(dtype=wp.int32),
        poses: LocalPoses,
        frames: int,
        row_offset: int,
        # outputs
        world: wp.array(dtype=wp.mat44),
        world_dqs: wp.array(dtype=vec8),
        world_residuals: wp.array(dtype=wp.mat33),
        world_rigid: wp.array(dtype=wp.uint8),
        invalid: wp.array(dtype=wp.int32),
    ):
        r = wp.tid() + row_offset  # one row per (frame, skeleton), frame-major
        skeletons = skeleton_start.shape[0] - 1
        if wp.static(rigid_packet is not None):  # one row per (block of 8 frames, skeleton)
            block = r // skeletons
            s = r - block * skeletons
            f0 = block * PACKET_FRAMES
            n = wp.min(PACKET_FRAMES, frames - f0)
            stride = skeleton_start[skeletons]
            bad = float(0.0)  # stays 0 unless a local matrix has a NaN or inf
            for j in range(skeleton_start[s], skeleton_start[s + 1]):
                rest = rigid_packet(poses.matrices, world, world_dqs, world_rigid, f0, n, stride,
                                    j, parents[j])
                if rest != 0:
                    for lane in range(n):
                        if (rest >> lane) & 1 != 0:
                            base = (f0 + lane) * stride
                            i = base + j
                            m = poses.matrices[i]
                            bad += native.local_check(m)[0]
                            q, t, rigid = split_matrix(m)
                            general_joint(i, j, base, q, t, rigid, poses, 0, parents, world,
                                          world_dqs, world_residuals, world_rigid)
            if bad != 0.0:
                invalid[0] = 1
            return
        f = r // skeletons
        s = r - f * skeletons
        base = f * skeleton_start[skeletons]
        bad = float(0.0)  # stays 0 unless a local matrix has a NaN or inf
        for j in range(skeleton_start[s], skeleton_start[s + 1]):
            i = base + j
            t = wp.vec3()
            if wp.static(trs):
                t = poses.translations[i]
                q, rigid = split_trs(poses.rotations[i], poses.scales[i])
            else:
                m = poses.matrices[i]
                ck = native.local_check(m)
                bad += ck[0]  # 0 where finite, NaN at NaN/inf (also float64 beyond float32)
                if ck[1] < 1.0e-6:
                    # the common case, a rotation under a rigid parent (or none), as native
                    # snippets (SIMD on the CPU: kernels/fk_native.py)
                    pj = parents[j]
                    above = vec8()
                    has = int(0)
                    if pj >= 0:
                        has = int(world_rigid[base + pj])
                        if has != 0:
                            above = world_dqs[base + pj]
                    if pj < 0 or has != 0:
                        e = native.rigid_step(m, above, has)
                        world_dqs[i] = e
                        world_rigid[i] = wp.uint8(1)
                        world[i] = native.rigid_matrix(e)
                        continue
                q, t, rigid = split_matrix(m)
            general_joint(i, j, base, q, t, rigid, poses, wp.static(int(trs)), parents, world,
                          world_dqs, world_residuals, world_rigid)
        if bad != 0.0:  # one store per row, none in the joint loop
            invalid[0] = 1

    kernel.__doc__ = (f"FK over (frame, skeleton) rows from local {'TRS' if trs else 'matrices'}.")
    return wp.kernel(kernel, name=name)


forward_kinematics_kernel = _forward_kinematics_kernel(False, "forward_kinematics_kernel")
forward_kinematics_trs_kernel = _forward_kinematics_kernel(True, "forward_kinematics_trs_kernel")
forward_kinematics_packet_kernel = _forward_kinematics_kernel(
    False, "forward_kinematics_packet_kernel", native.rigid_packet)


@wp.kernel
def bind_relative_kernel(
    world: wp.array2d(dtype=wp.mat44),
    inverse_bind: wp.array(dtype=wp.mat44),
    # outputs
    skinning: wp.array2d(dtype=wp.mat44),
):
    """Skinning transforms ``world ∘ inverse(bind)`` per (frame, joint)."""
    f, j = wp.tid()
    skinning[f, j] = world[f, j] * inverse_bind[j]


class WorldPoses:
    """FK outputs, flat (F·J,) (frame-major) device arrays: world ``matrices`` (``wp.mat44``),
    the rigid part ``dqs`` (``vec8``), and the scale/shear ``residuals`` (``wp.mat33``,
    ``matrix = [R·S | t]``), written only where ``rigid`` (``uint8``) is 0 (1: the residual is the
    identity); ``invalid`` (1,) ``int32`` flags a non-finite local matrix."""

    __slots__ = ("matrices", "dqs", "residuals", "rigid", "invalid")

    def __init__(self, count: int, device: Device) -> None:
        self.matrices = empty(count, wp.mat44, device)
        self.dqs = empty(count, vec8, device)
        self.residuals = empty(count, wp.mat33, device)
        self.rigid = wp.empty(count, dtype=wp.uint8, device=device)
        self.invalid = wp.zeros(1, dtype=wp.int32, device=device)
        """(1,) set to 1 when a local matrix is not finite (NaN, inf): the caller's host check
        can then run only when needed, to name the frame and joint."""


def world_poses(count: int, device: Device) -> WorldPoses:
    """A :class:`WorldPoses` of ``count`` (F·J) uninitialized joints on ``device``."""
    return WorldPoses(count, device)


def forward_kinematics(*, parents: wp.array, skeleton_start: wp.array,
                       local: wp.array | tuple[wp.array, wp.array, wp.array], out: WorldPoses,
                       device: Device) -> None:
    """FK of every skeleton for every frame: ``local`` is a flat (F·J,) ``wp.mat44`` array or a
    ``(translations, rotations, scales)`` tuple of (F·J,) arrays; fills ``out``
    (:func:`world_poses`). One thread per (frame, skeleton); on the CPU those rows are split
    across the cores (one frame of a crowd's many skeletons too), and from
    :data:`PACKET_MIN_FRAMES` frames of local matrices a thread carries eight frames of one
    skeleton (:func:`forward_kinematics_packet_kernel`)."""
    trs = isinstance(local, tuple)
    poses = LocalPoses()
    if trs:
        poses.translations, poses.rotations, poses.scales = local
    else:
        poses.matrices = local
    skeletons = skeleton_start.shape[0] - 1
    frames = (local[0] if trs else local).shape[0] // max(parents.shape[0], 1)
    outputs = [out.matrices, out.dqs, out.residuals, out.rigid, out.invalid]
    inputs = [parents, skeleton_start, poses, frames]
    if not trs and frames >= PACKET_MIN_FRAMES and is_cpu(device):
        launch_rows(forward_kinematics_packet_kernel, -(-frames // PACKET_FRAMES) * skeletons,
                    inputs, outputs, device, min_chunk=8)
        return
    kernel = forward_kinematics_trs_kernel if trs else forward_kinematics_kernel
    launch_rows(kernel, frames * skeletons, inputs, outputs, device, min_chunk=64)


def bind_relative(*, world: wp.array, inverse_bind: wp.array, skinning: wp.array,
                  device: Device) -> None:
    """``skinning[f, j] = world[f, j] @ inverse_bind[j]``."""
    launch(bind_relative_kernel, world.shape, [world, inverse_bind], [skinning], device)
