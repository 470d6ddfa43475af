"""Motion derivatives: joint velocities through the hierarchy and skinned-point velocities.

Every interpolant is differentiated analytically (:mod:`dqskin.animation`): ``η̇`` from the
interpolant's derivative (the derivative of the dual-number normalization for the normalized
ones), the twist ``φ = η⁻¹·η̇ = ω/2 + ε·v/2`` (Montgomery-Smith eq. 25–26, :func:`dqskin.dq.twist`),
``Ṁ = [R·[ω]×·S + R·Ṡ | R·v]``. For ``"trs"`` the keyed TRS interpolant is differentiated (slerp:
``q̇ = q·log(qₖ*·qₖ₊₁)/Δt``; lerp: ``(xₖ₊₁ − xₖ)/Δt``), which reproduces any linear TRS player
whose key times are all in ``animation.key_times`` (glTF LINEAR, USD); STEP or CUBICSPLINE clips
are detected and rejected. World transforms are differentiated through the hierarchy by the
product rule, ``Ẇⱼ = Ẇₚ·Lⱼ + Wₚ·L̇ⱼ`` (:func:`forward_kinematics_derivative`), skinning transforms
as ``Ȧ = Ẇ·B⁻¹``, and skinned points by the chain rule through LBS or DQS
(:func:`skinned_velocities`, Warp kernels in :mod:`dqskin.kernels.velocity`).

Derivatives are per unit of the animation's time (USD time codes, glTF seconds) unless stated;
:meth:`dqskin.Scene.skin` (``velocities=True``) converts to per second. At an interior key,
where piecewise interpolants have a kink, the derivative is the mean of both sides: the velocity
a renderer's shutter interval around the key sees (UsdSkel and glTF caches are sampled exactly at
keys).

References: [K] and [MS] as in :mod:`dqskin.animation`.
"""

from collections.abc import Callable
from typing import Literal, cast

import numpy as np
import numpy.typing as npt

from . import dq
from ._warp import Device
from .animation import Animation, _motion, check_times, sample_with_derivative
from .errors import InputError
from .influences import check_influences
from .linalg import vee
from .options import DEFAULT_INTERP, DEFAULT_SIGN_REFERENCE, Interpolation, Method, SignReference
from .shapes import as_real, frames_of
from .skeleton import Skeleton, check_parents
from .skinning import Skinner

__all__ = ["forward_kinematics_derivative", "joint_twists", "moved_velocities", "per_second",
           "skinned_velocities", "skinning_transforms_with_derivative"]


def per_second(rate: float, *derivatives: npt.ArrayLike | None) -> tuple[np.ndarray | None, ...]:
    """Each of ``derivatives`` (per unit of animation time; None stays None) times ``rate``
    (time units per second), in its own float dtype. Skinned velocities are linear in the
    derivatives of the joints and of the rest points, so scaling those inputs before the kernel
    gives velocities per second without a float64 pass over every skinned point."""
    return tuple(None if d is None else np.asarray(d) * rate for d in derivatives)


def moved_velocities(v: npt.ArrayLike, out: np.ndarray, out_rate: np.ndarray | None, rate: float,
                     skinned_points: Callable[[], np.ndarray]) -> np.ndarray:
    """(F, V, 3) float32 velocities per second in a moving target space: ``O·v + rate·(Ȯ·p +
    ȯ)`` for per-second ``v`` (F, V, 3) in skeleton space, output transforms ``out`` (F, 4, 4),
    their derivatives per unit of time ``out_rate`` and ``skinned_points()`` (called only when
    the output transform moves) the skinned points ``p`` in skeleton space."""
    moved = np.einsum("fij,fvj->fvi", out[:, :3, :3], np.asarray(v, dtype=np.float64))
    if out_rate is not None and np.any(out_rate):
        p = skinned_points()
        moved += rate * (np.einsum("fij,fvj->fvi", out_rate[:, :3, :3], p)
                     + out_rate[:, None, :3, 3])
    return moved.astype(np.float32)


def forward_kinematics_derivative(parents: npt.ArrayLike, local: npt.ArrayLike,
                                  local_dot: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """World transforms and their derivatives by the product rule, float64.

    ``Wⱼ = Wₚ·Lⱼ`` and ``Ẇⱼ = Ẇₚ·Lⱼ + Wₚ·L̇ⱼ`` (roots: ``Wⱼ = Lⱼ``), exact also with scale or shear.

    Parameters
    ----------
    parents : (J,) int
        Parents first, -1 for roots.
    local, local_dot : (..., J, 4, 4) float
        Parent-relative transforms and their time derivatives.

    Returns
    -------
    world, world_dot : (..., J, 4, 4) float64
        Skeleton-space transforms and their derivatives.
    """
    par = check_parents(parents)
    loc = np.asarray(local, dtype=np.float64)
    loc_dot = np.asarray(local_dot, dtype=np.float64)
    J = par.shape[0]
    if loc.ndim < 3 or loc.shape[-3:] != (J, 4, 4) or loc_dot.shape != loc.shape:
        raise InputError(f"local {loc.shape} and local_dot {loc_dot.shape} must both be "
                         f"(..., {J}, 4, 4)")
    world = np.empty_like(loc)
    world_dot = np.empty_like(loc)
    for j, p in enumerate(par):
        if p < 0:
            world[..., j, :, :] = loc[..., j, :, :]
            world_dot[..., j, :, :] = loc_dot[..., j, :, :]
        else:
            world[..., j, :, :] = world[..., p, :, :] @ loc[..., j, :, :]
            world_dot[..., j, :, :] = (world_dot[..., p, :, :] @ loc[..., j, :, :]
                                       + world[..., p, :, :] @ loc_dot[..., j, :, :])
    return world, world_dot


def joint_twists(animation: Animation, times: npt.ArrayLike,
                 interp: Interpolation = DEFAULT_INTERP, *,
                 frame: Literal["local", "world"] = "local",
                 parents: npt.ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Angular and linear velocity of every joint, from the interpolant's analytic derivative.

    Parameters
    ----------
    animation, times, interp
        As :func:`sample_with_derivative`.
    frame : {"local", "world"}
        ``"local"``: the body twist ``φ = η⁻¹·η̇ = ω/2 + ε·v/2`` ([MS] eq. 25–26) of each joint's
        parent-relative rigid transform ``η`` (rotation and translation; a residual scale is not
        part of it): ``ω`` and ``v`` in the joint's own axes, ``ṫ = R·v`` the velocity of the joint
        origin in the parent's axes (eq. 23). ``"world"``: through the hierarchy
        (:func:`forward_kinematics_derivative`): ``ω`` the angular velocity in skeleton axes, the
        axial vector of ``Ȧ·A⁻¹`` for the world linear part ``A`` (``Ṙ·Rᵀ`` when rigid), and ``v``
        the skeleton-space velocity of the joint origin, ``d/dt`` of the world translation.
    parents : (J,) int
        Required for ``frame="world"``.

    Returns
    -------
    omega : (F, J, 3) float64
        Angular velocity [rad per unit of the animation's time].
    v : (F, J, 3) float64
        Linear velocity [length units per unit of the animation's time].
    """
    if frame == "local":
        _, _, eta, eta_dot = _motion(animation, times, interp)
        return dq.twist(eta, eta_dot, "body")
    if frame != "world":
        raise InputError(f'frame must be "local" or "world", got {frame!r}')
    if parents is None:
        raise InputError('frame="world" needs parents')
    local, local_dot, _, _ = _motion(animation, times, interp)
    world, world_dot = forward_kinematics_derivative(parents, local, local_dot)
    lin = world[..., :3, :3]
    omega = vee(world_dot[..., :3, :3] @ np.linalg.inv(lin))
    return omega, world_dot[..., :3, 3].copy()


def skinning_transforms_with_derivative(skeleton: Skeleton, animation: Animation | None,
                                        times: npt.ArrayLike,
                                        interp: Interpolation = DEFAULT_INTERP, *,
                                        local: npt.ArrayLike | None = None
                                        ) -> tuple[np.ndarray, np.ndarray]:
    """Bind-relative skinning transforms ``W·B⁻¹`` and their derivatives ``Ẇ·B⁻¹``, float64.

    Parameters
    ----------
    skeleton : dqskin.skeleton.Skeleton
    animation : dqskin.animation.Animation or None
        None holds the skeleton at rest (zero derivative).
    times : (F,) float
    interp : str
        As :func:`sample`.
    local : (F, J, 4, 4) float, optional
        The animation's local transforms at ``times`` when the caller has them
        (:func:`~dqskin.animation.sample_with_derivative`).

    Returns
    -------
    xforms, xforms_dot : (F, J, 4, 4) float64
        Column-vector convention; derivatives per unit of the animation's time.
    """
    t = check_times(times)
    if animation is None:
        rest = skeleton.rest_transforms
        local = np.broadcast_to(rest, (t.shape[0],) + rest.shape)
        local_dot = np.zeros(local.shape)
    else:
        local, local_dot = sample_with_derivative(animation, t, interp, local=local)
    world, world_dot = forward_kinematics_derivative(skeleton.parents, local, local_dot)
    inv = skeleton.inverse_bind_transforms
    return world @ inv, world_dot @ inv


# ---------------------------------------------------------------------------------------------
# skinned point velocities


def skinned_velocities(points: npt.ArrayLike, joint_indices: npt.ArrayLike,
                       joint_weights: npt.ArrayLike, skinning_transforms: npt.ArrayLike,
                       skinning_transform_derivatives: npt.ArrayLike, method: Method = "lbs", *,
                       geom_bind_transform: npt.ArrayLike | None = None,
                       point_velocities: npt.ArrayLike | None = None,
                       blend_weights: npt.ArrayLike | None = None,
                       faces: npt.ArrayLike | None = None,
                       rest_points: npt.ArrayLike | None = None,
                       sign_reference: SignReference = DEFAULT_SIGN_REFERENCE,
                       device: Device = None) -> np.ndarray:
    """Velocities of skinned points, by the chain rule (Warp, one thread per vertex).

    Same skinning semantics as :func:`dqskin.skin_points` (UsdSkel): weights used as given, DQS
    with sign alignment by ``sign_reference`` and the residual (scale/shear) path
    ``Σ wᵢ·Sᵢ·p`` on frames where any joint has one. The joint DQs and their derivatives come from
    the polar split ``A = R·S`` and its derivative (``Rᵀ·Ȧ = [ω]×·S + Ṡ``) on the device.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
        Points, mesh space: the rest points, or each frame's (e.g. after blend shapes).
    joint_indices, joint_weights : (V, K) int, (V, K) float
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        Bind-relative transforms ``A`` (world ∘ inverse bind), column-vector convention.
    skinning_transform_derivatives : same shape
        ``dA/dt``.
    method : {"lbs", "dqs", "blend", "cor"}
    geom_bind_transform : (4, 4) float, optional
        Mesh space → bind space (constant).
    point_velocities : (V, 3) or (F, V, 3) float, optional
        ``d points / dt`` in mesh space (e.g. from blend shapes); zero by default.
    blend_weights : (V,) float, optional
        DQS fraction per vertex, required for ``"blend"``.
    faces : (T, 3) int, optional
        Triangles, required for ``"cor"``.
    rest_points : (V, 3) float, optional
        Rest points (mesh space) the ``"cor"`` centers are computed from, as
        :class:`dqskin.Skinner` and :meth:`dqskin.Scene.skin` do (the centers do not follow
        blend shapes), so these are the derivatives of their positions. Default: ``points``
        when it is (V, 3); required for ``"cor"`` with per-frame (F, V, 3) points.
    sign_reference : {"largest_weight", "running_sum"}
        Sign rule of the rotation blends (:data:`dqskin.options.SignReference`).
    device : str, optional
        Warp device.

    Returns
    -------
    (V, 3) or (F, V, 3) float32
        ``d/dt`` of the skinned points, skeleton space, per unit of time of the derivatives.
    """
    x = as_real("skinning_transforms", skinning_transforms, np.float64)
    x_dot = as_real("skinning_transform_derivatives", skinning_transform_derivatives, np.float64)
    if x.ndim not in (3, 4) or x.shape[-2:] != (4, 4) or x_dot.shape != x.shape:
        raise InputError(f"skinning_transforms {x.shape} and skinning_transform_derivatives "
                         f"{x_dot.shape} must both be (J, 4, 4) or (F, J, 4, 4)")
    frames = x.shape[0] if x.ndim == 4 else 1
    idx, wts = check_influences(joint_indices, joint_weights, joint_count=x.shape[-3])
    pts, batched = frames_of("points", points, frames, idx.shape[0])
    rest = pts[0]
    if rest_points is not None:
        rest = as_real("rest_points", rest_points, np.float64)
        if rest.shape != (idx.shape[0], 3):
            raise InputError(f"rest_points: expected ({idx.shape[0]}, 3), got {rest.shape}")
    elif method == "cor" and batched:
        raise InputError('method "cor" with per-frame points needs rest_points (its centers '
                         'come from the rest mesh)')
    sk = Skinner(rest, idx, wts, geom_bind_transform=geom_bind_transform,
                 blend_weights=blend_weights, faces=faces, device=device)
    per_frame = pts.shape[0] > 1 or rest_points is not None
    return cast(np.ndarray, sk.skin_velocities(
        x, x_dot, method, points=pts if per_frame else None, point_velocities=point_velocities,
        sign_reference=sign_reference))
