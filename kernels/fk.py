"""Forward kinematics: local joint transforms → world transforms, concatenated as dual quaternions.

A joint transform is carried as a pair ``(η, S)``: a unit dual quaternion ``η`` (rotation ``R`` and
translation ``t``) and a 3×3 residual ``S`` applied first, so ``M = [R·S | t]``. Rigid joints have
``S = I`` and FK is pure dual-quaternion concatenation. With scale or shear the pair still composes
exactly::

    (η_p, S_p) ∘ (η_l, S_l) = (η_p · η(R_l, S_p·t_l),  R_lᵀ · S_p · R_l · S_l)

which reduces to ``η_p · η_l`` when ``S_p = I``. Local matrices are split by the polar decomposition
``A = R·S`` (the same split UsdSkel uses for its DQS).
"""

import warp as wp

from .dqmath import (dq_from_rt, dq_mul, dq_to_matrix, is_identity33, is_rotation, mat44_linear, polar_rotation,
                     vec8)


@wp.kernel
def forward_kinematics_kernel(
    parents: wp.array(dtype=wp.int32),
    skeleton_start: wp.array(dtype=wp.int32),
    local: wp.array2d(dtype=wp.mat44),
    frame_offset: int,
    # outputs
    world_dq: wp.array2d(dtype=vec8),
    world_residual: wp.array2d(dtype=wp.mat33),
    world: wp.array2d(dtype=wp.mat44),
):
    """One thread per (frame, skeleton), walking that skeleton's joints parents-first.

    ``parents`` holds global joint indices (−1 for roots); skeleton ``s`` owns joints
    ``skeleton_start[s] .. skeleton_start[s+1]-1`` of the concatenated joint axis. Where the
    parent's residual is the identity (rigid chains) the step is a plain DQ product.
    """
    i, s = wp.tid()
    f = i + frame_offset
    eye = wp.identity(n=3, dtype=float)
    for j in range(skeleton_start[s], skeleton_start[s + 1]):
        m = local[f, j]
        a = mat44_linear(m)
        r = a
        res = eye
        if not is_rotation(a):
            r = polar_rotation(a)
            res = wp.transpose(r) * a
        q = wp.normalize(wp.quat_from_matrix(r))
        t = wp.vec3(m[0, 3], m[1, 3], m[2, 3])
        p = parents[j]
        eta = dq_from_rt(q, t)
        if p >= 0:
            sp = world_residual[f, p]
            if is_identity33(sp, 0.0):
                eta = dq_mul(world_dq[f, p], eta)
            else:
                eta = dq_mul(world_dq[f, p], dq_from_rt(q, sp * t))
                res = wp.transpose(r) * sp * r * res
        world_dq[f, j] = eta
        world_residual[f, j] = res
        rigid = dq_to_matrix(eta)
        lin = mat44_linear(rigid) * res
        world[f, j] = wp.mat44(lin[0, 0], lin[0, 1], lin[0, 2], rigid[0, 3],
                               lin[1, 0], lin[1, 1], lin[1, 2], rigid[1, 3],
                               lin[2, 0], lin[2, 1], lin[2, 2], rigid[2, 3],
                               0.0, 0.0, 0.0, 1.0)


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


def forward_kinematics(parents, skeleton_start, local, world_dq, world_residual, world, *, device,
                       frame_offset=0, frame_count=None):
    """Launch FK over frames ``frame_offset .. frame_offset + frame_count`` of ``local`` (F, J)
    mat44; fills the three (F, J) outputs in place."""
    count = local.shape[0] - frame_offset if frame_count is None else frame_count
    wp.launch(forward_kinematics_kernel, dim=(count, skeleton_start.shape[0] - 1),
              inputs=[parents, skeleton_start, local, frame_offset],
              outputs=[world_dq, world_residual, world], device=device)


def bind_relative(world, inverse_bind, skinning, *, device):
    """Launch ``skinning[f, j] = world[f, j] @ inverse_bind[j]``."""
    wp.launch(bind_relative_kernel, dim=world.shape, inputs=[world, inverse_bind],
              outputs=[skinning], device=device)
