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
``skeleton_start[s] .. skeleton_start[s+1]-1`` of the concatenated joint axis.
"""

import warp as wp

from .dqmath import (
    dq_from_rt,
    dq_mul,
    dq_to_matrix,
    is_identity33,
    is_rotation,
    mat44_linear,
    polar_rotation,
    quat_from_rotation,
    vec8,
)
from .grid import launch, launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.func
def fk_joint(f: int, j: int, p: int, q: wp.quat, t: wp.vec3, res: wp.mat33, rigid: bool,
             world_dq: wp.array2d(dtype=vec8), world_residual: wp.array2d(dtype=wp.mat33),
             world: wp.array2d(dtype=wp.mat44)):
    """Compose joint ``j`` (local rotation ``q``, translation ``t``, residual ``res``) onto its
    parent ``p`` and store the world pair and matrix. Rigid parents take a plain DQ product."""
    eta = dq_from_rt(q, t)
    if p >= 0:
        sp = world_residual[f, p]
        if is_identity33(sp, 0.0):
            eta = dq_mul(world_dq[f, p], eta)
        else:
            rigid = False
            r = wp.quat_to_matrix(q)
            eta = dq_mul(world_dq[f, p], dq_from_rt(q, sp * t))
            res = wp.transpose(r) * sp * r * res
    world_dq[f, j] = eta
    world_residual[f, j] = res
    x = dq_to_matrix(eta)
    if not rigid:
        lin = mat44_linear(x) * res
        x = wp.mat44(lin[0, 0], lin[0, 1], lin[0, 2], x[0, 3],
                     lin[1, 0], lin[1, 1], lin[1, 2], x[1, 3],
                     lin[2, 0], lin[2, 1], lin[2, 2], x[2, 3],
                     0.0, 0.0, 0.0, 1.0)
    world[f, j] = x


@wp.struct
class LocalPoses:
    """Parent-relative joint poses (F, J): 4×4 ``matrices``, or ``translations``, unit
    ``rotations`` ``(w, x, y, z)`` and ``scales`` (``M = T·R·S``); the other kind stays unset."""

    matrices: wp.array2d(dtype=wp.mat44)
    translations: wp.array2d(dtype=wp.vec3)
    rotations: wp.array2d(dtype=wp.vec4)
    scales: wp.array2d(dtype=wp.vec3)


@wp.func
def split_matrix(m: wp.mat44):
    """``(rotation, translation, residual, rigid)`` of a local 4×4 matrix (polar split)."""
    a = mat44_linear(m)
    r = a
    res = wp.identity(n=3, dtype=float)
    rigid = is_rotation(a)
    if not rigid:
        r = polar_rotation(a)
        res = wp.transpose(r) * a
    return quat_from_rotation(r), wp.vec3(m[0, 3], m[1, 3], m[2, 3]), res, rigid


@wp.func
def split_trs(t: wp.vec3, r: wp.vec4, sc: wp.vec3):
    """``(rotation, translation, residual, rigid)`` of a TRS pose (``r`` is ``(w, x, y, z)``)."""
    rigid = sc[0] == 1.0 and sc[1] == 1.0 and sc[2] == 1.0
    return wp.normalize(wp.quat(r[1], r[2], r[3], r[0])), t, wp.diag(sc), rigid


def _forward_kinematics_kernel(trs, name):
    """FK from :class:`LocalPoses` of one kind, resolved at compile time."""

    def kernel(
        parents: wp.array(dtype=wp.int32),
        skeleton_start: wp.array(dtype=wp.int32),
        poses: LocalPoses,
        row_offset: int,
        # outputs
        world_dq: wp.array2d(dtype=vec8),
        world_residual: wp.array2d(dtype=wp.mat33),
        world: wp.array2d(dtype=wp.mat44),
    ):
        r = wp.tid() + row_offset  # one row per (frame, skeleton), frame-major
        skeletons = skeleton_start.shape[0] - 1
        f = r // skeletons
        s = r - f * skeletons
        for j in range(skeleton_start[s], skeleton_start[s + 1]):
            if wp.static(trs):
                q, t, res, rigid = split_trs(poses.translations[f, j], poses.rotations[f, j],
                                             poses.scales[f, j])
            else:
                q, t, res, rigid = split_matrix(poses.matrices[f, j])
            fk_joint(f, j, parents[j], q, t, res, rigid, world_dq, world_residual, world)

    kernel.__doc__ = (f"FK over (frame, skeleton) rows from local {'TRS' if trs else 'matrices'}.")
    return wp.kernel(kernel, name=name)


forward_kinematics_kernel = _forward_kinematics_kernel(False, "forward_kinematics_kernel")
forward_kinematics_trs_kernel = _forward_kinematics_kernel(True, "forward_kinematics_trs_kernel")


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


def forward_kinematics(*, parents, skeleton_start, local, world_dq, world_residual, world,
                       device):
    """FK of every skeleton for every frame: ``local`` is a (F, J) ``wp.mat44`` array or a
    ``(translations, rotations, scales)`` tuple of (F, J) arrays; fills the three (F, J) outputs.
    One thread per (frame, skeleton); on the CPU those rows are split across the cores (one frame
    of a crowd's many skeletons too)."""
    trs = isinstance(local, tuple)
    poses = LocalPoses()
    if trs:
        poses.translations, poses.rotations, poses.scales = local
    else:
        poses.matrices = local
    kernel = forward_kinematics_trs_kernel if trs else forward_kinematics_kernel
    frames, skeletons = (local[0] if trs else local).shape[0], skeleton_start.shape[0] - 1
    launch_rows(kernel, frames * skeletons, [parents, skeleton_start, poses],
                [world_dq, world_residual, world], device, min_chunk=64)


def bind_relative(*, world, inverse_bind, skinning, device):
    """``skinning[f, j] = world[f, j] @ inverse_bind[j]``."""
    launch(bind_relative_kernel, world.shape, [world, inverse_bind], [skinning], device)
