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

With the body's skin known (its points and influences), :func:`feet_on_the_floor` sets the root's
height at every frame instead: the skinned body's lowest point is as high above the rest mesh's
floor as the capture's lowest joint is above the capture's floor level, in % of each one's
height. The feet stand on the floor exactly when the capture's do, and lift (a heel, a swing) as
much; horizontal motion is unchanged, so they slide no more than the capture's.
"""

import numpy as np
import numpy.typing as npt

from .animation import KeyedAnimation
from .errors import InputError, Param
from .geometry import end_site_points
from .readers.bvh import BvhMotion
from .skeleton import Skeleton

__all__ = ["feet_on_the_floor", "leg_length", "retarget", "world_transforms"]

_CONTACT_PERCENTILE = 25  # of the lowest joint's height over the frames: a foot on the floor
_FLOOR_PERCENTILE = 50  # of the capture's lowest joint over the frames: its floor level


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


def _capture_floor(motion: BvhMotion, up: int = 1) -> tuple[np.ndarray, float, float]:
    """The capture's lowest joint per frame and its floor level.

    Returns
    -------
    low : (F,) float64
        The lowest joint's height at every frame (BVH units).
    level : float
        The floor level: the lowest joint's median height over the frames (a foot is down on
        most frames of a capture).
    height : float
        The capture's height in its rest pose (joints and End Sites).
    """
    source = motion.skeleton()
    low = world_transforms(source.parents, motion.local_transforms())[:, :, up, 3].min(1)
    rest = source.bind_transforms
    ends = end_site_points(rest, motion.end_sites)[:, up]
    height = float(np.ptp(np.concatenate([rest[:, up, 3], ends])))
    return low, float(np.percentile(low, _FLOOR_PERCENTILE)), height


def feet_on_the_floor(skeleton: Skeleton, motion: BvhMotion, points: npt.ArrayLike,
                      joint_indices: npt.ArrayLike, joint_weights: npt.ArrayLike, *,
                      up: int = 1, band: float = 0.1) -> Skeleton:
    """The retargeted skeleton with its root's height set at every frame so that the skinned
    (linear blend) body's lowest point follows the capture's lowest joint (module docstring).

    Parameters
    ----------
    skeleton : dqskin.Skeleton
        :func:`retarget`'s result: keyed local transforms, one key per capture frame, the world
        as its space.
    motion : BvhMotion
        The capture it was retargeted from.
    points : (V, 3) float
        The body's rest points (bind pose, the skeleton's space).
    joint_indices, joint_weights : (V, K) int, (V, K) float
        The body's influences.
    up : int
        The up axis (Y by default).
    band : float
        Only the points within this share of the body's height above its floor are skinned
        (the feet).

    Returns
    -------
    dqskin.Skeleton
        The same joints and bind pose; the roots' local translations moved along ``up``.
    """
    anim = skeleton.animation
    assert isinstance(anim, KeyedAnimation), "a retargeted skeleton has keyed local transforms"
    P = np.asarray(points, np.float64)
    floor, height = float(P[:, up].min()), float(np.ptp(P[:, up]))
    feet = np.nonzero(P[:, up] <= floor + band * height)[0]
    idx = np.asarray(joint_indices)[feet]
    w = np.asarray(joint_weights, np.float64)[feet]
    ph = np.append(P[feet], np.ones((len(feet), 1)), axis=1)
    local = anim.local_transforms(anim.key_times).copy()
    # the up row of every joint's skinning matrix, (F, J, 4)
    row = np.einsum("fjk,jkl->fjl", world_transforms(skeleton.parents, local)[:, :, up, :],
                    np.linalg.inv(skeleton.bind_transforms))
    y = np.zeros((len(local), len(feet)))
    for k in range(idx.shape[1]):
        y += w[:, k] * np.einsum("fvl,vl->fv", row[:, idx[:, k]], ph)
    low_c, level_c, height_c = _capture_floor(motion, up)
    if len(low_c) != len(local):
        raise InputError(Param("skeleton"), f": {len(local)} keys for the capture's "
                         f"{len(low_c)} frames (not retargeted from this motion)")
    target = floor + (low_c - level_c) * height / max(height_c, 1e-300)
    local[:, skeleton.parents < 0, up, 3] += (target - y.min(1))[:, None]
    return skeleton.with_animation(KeyedAnimation(anim.key_times, local, name=anim.name))
