"""Retargeting: a capture's motion on an embedded skeleton (:func:`dqskin.embedding.embed_skeleton`)
of the same joints, another body's proportions and rest pose.

Per joint, the rest-pose difference is taken out: the embedded bind rotation of joint ``j`` is the
capture's turned by ``A_j`` (its bones onto the body's), so giving joint ``j`` the capture's world
rotation ``W_j(t)`` turns the body's bone by the capture's ``W_j(t)·B_j⁻¹``: **world bone
directions follow the capture's** at every frame, whatever the two rest poses (an A-pose body on
an I-pose capture). Locally this is the capture's own local rotations on the body's bone offsets.
The root's translation from its rest position is scaled by the ratio of the legs' lengths (the
bones from the root to the lowest joint), so that strides fit the new legs; its height is scaled
likewise and then set so that the body's lowest joint is, on a quarter of the frames, no higher
than in its bind pose (standing): the feet reach the floor when the capture's do.
"""

import numpy as np

from .animation import KeyedAnimation
from .readers.bvh import BvhMotion
from .skeleton import Skeleton

__all__ = ["leg_length", "retarget", "world_transforms"]

_CONTACT_PERCENTILE = 25  # of the lowest joint's height over the frames: a foot on the floor


def world_transforms(parents: np.ndarray, local: np.ndarray) -> np.ndarray:
    """(F, J, 4, 4) float64 world transforms of local ones (F, J, 4, 4), parents first."""
    world = np.empty_like(local)
    for j, p in enumerate(parents):
        world[:, j] = local[:, j] if p < 0 else world[:, p] @ local[:, j]
    return world


def leg_length(skeleton: Skeleton, up: int = 1) -> float:
    """The summed bone lengths from the root to the lowest joint of the bind pose (a foot)."""
    pos = skeleton.bind_transforms[:, :3, 3]
    j = int(np.argmin(pos[:, up]))
    total = 0.0
    while skeleton.parents[j] >= 0:
        p = skeleton.parents[j]
        total += float(np.linalg.norm(pos[j] - pos[p]))
        j = p
    return total


def retarget(motion: BvhMotion, embedded: Skeleton, *, up: int = 1) -> Skeleton:
    """The embedded skeleton driven by ``motion`` (see the module docstring).

    Parameters
    ----------
    motion : BvhMotion
        The capture; its rest pose (every channel zero) is the bind pose of ``embedded``'s
        source skeleton (``motion.skeleton()``).
    embedded : dqskin.Skeleton
        ``embed_skeleton(mesh, motion.skeleton(), ...)``: same joints, bind pose in the body.
    up : int
        The up axis (Y by default, as BVH).

    Returns
    -------
    dqskin.Skeleton
        ``embedded``'s joints and bind pose with a :class:`dqskin.KeyedAnimation` at the
        capture's frame numbers: (F, J, 4, 4) local transforms, the capture's local rotations on
        the body's bone offsets, the root's translation scaled by the legs' ratio.
    """
    source = motion.skeleton()
    local_c = motion.local_transforms()
    world_c = world_transforms(source.parents, local_c)
    bind_e = embedded.bind_transforms
    bind_c = source.bind_transforms
    J = embedded.joint_count
    # world rotation of the body's joint: W_c(t) · B_c⁻¹ · A⁻¹ · Q with Q = A · B_c: W_c(t)
    rot_world = world_c[:, :, :3, :3] @ np.swapaxes(bind_c[:, :3, :3], -1, -2) \
        @ bind_c[:, :3, :3]
    ratio = leg_length(embedded, up) / max(leg_length(source, up), 1e-300)
    floor_c = float(world_c[:, :, up, 3].min())
    floor_e = float(bind_e[:, up, 3].min())
    local = np.tile(np.eye(4), (motion.frame_count, J, 1, 1))
    for j in range(J):
        p = embedded.parents[j]
        if p < 0:
            local[:, j, :3, :3] = rot_world[:, j]
            t = bind_e[j, :3, 3] + ratio * (world_c[:, j, :3, 3] - bind_c[j, :3, 3])
            t[:, up] = floor_e + ratio * (world_c[:, j, up, 3] - floor_c)
            local[:, j, :3, 3] = t
        else:
            local[:, j, :3, :3] = np.swapaxes(rot_world[:, p], -1, -2) @ rot_world[:, j]
            local[:, j, :3, 3] = bind_e[p, :3, :3].T @ (bind_e[j, :3, 3] - bind_e[p, :3, 3])
    # feet on the floor: the body's lowest joint, over the frames (a quarter of them lower), as
    # high as in its bind pose (standing)
    low = world_transforms(embedded.parents, local)[:, :, up, 3].min(1)
    root = embedded.parents < 0
    local[:, root, up, 3] += floor_e - float(np.percentile(low, _CONTACT_PERCENTILE))
    anim = KeyedAnimation(np.arange(motion.frame_count, dtype=np.float64), local,
                          name=motion.path)
    return embedded.with_animation(anim)
