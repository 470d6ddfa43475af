"""Skeletons: joint hierarchy, bind and rest transforms, forward kinematics on the device."""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import TYPE_CHECKING, Literal, overload

import numpy as np
import numpy.typing as npt

from .animation import Animation
from .errors import InputError
from .shapes import as_real
from .validation import FLOAT32_MAX, check_finite, location

# Warp and the FK kernels load on the first forward kinematics, not with the skeleton (a loaded
# scene needs neither: ``dqskin info``)
if TYPE_CHECKING:
    import warp as wp

    from ._warp import Device
    from .kernels import fk as FK

__all__ = ["LocalTransforms", "Skeleton", "check_parents", "forward_kinematics"]

LocalTransforms = npt.ArrayLike | tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike | None]
"""Parent-relative joint poses: (..., J, 4, 4) matrices, or (translations (..., J, 3), rotations
(..., J, 4) ``(w, x, y, z)``, scales (..., J, 3) or None)."""


def check_parents(parents: npt.ArrayLike, where: str = "parents") -> np.ndarray:
    """Validate a joint hierarchy: (J,) ints in [-1, J), parents before children, no cycles.

    Returns the parents as int32; raises ValueError naming ``where`` and the offending joint. An
    empty sequence is an empty hierarchy (callers that need joints say so).
    """
    p = as_real(where, parents)
    if p.ndim == 1 and p.size == 0:
        return p.astype(np.int32)
    if p.ndim != 1 or not np.issubdtype(p.dtype, np.integer):
        raise InputError(f"{where}: expected a 1-D integer array, got shape {p.shape} {p.dtype}")
    j = np.arange(p.shape[0])
    bad = np.nonzero((p < -1) | (p >= p.shape[0]))[0]
    if bad.size:
        raise InputError(f"{where}: joint {bad[0]} has parent {p[bad[0]]} out of range "
                         f"[-1, {p.shape[0]})")
    bad = np.nonzero(p >= j)[0]
    if bad.size:
        k = int(bad[0])
        # distinguish a cycle from a mere ordering problem
        seen, cur = set(), k
        while cur >= 0 and cur not in seen:
            seen.add(cur)
            cur = int(p[cur])
        if cur >= 0:
            raise InputError(f"{where}: cycle in the joint hierarchy through joint {cur}")
        raise InputError(f"{where}: joint {k} comes before its parent {int(p[k])}; joints must be "
                         "ordered parents first")
    return p.astype(np.int32)


def _joint_label(j, joint_names=None):
    """``'name'`` (quoted) when names are known, else the joint index."""
    return repr(joint_names[j]) if joint_names is not None else str(j)


def _joint_list(mask, joint_names=None, limit=5):
    """"joint 'a'" / "joints 'a', 'b' and 3 more" for the True entries of a (J,) mask."""
    bad = [int(j) for j in np.nonzero(mask)[0]]
    text = ", ".join(_joint_label(j, joint_names) for j in bad[:limit])
    more = f" and {len(bad) - limit} more" if len(bad) > limit else ""
    return f"joint{'s' if len(bad) > 1 else ''} {text}{more}"


def _check_quaternions(rot, lead, joint_names=None):
    """Raise ValueError for a rotation the device cannot normalize: zero, or a squared norm outside
    float32's normal range (the kernels normalize in float32)."""
    r32 = np.asarray(rot, np.float32)
    fast = np.einsum("...i,...i->...", r32, r32)  # float32, one pass, no float64 copies
    if fast.size == 0 or (fast.min() >= 2 * np.finfo(np.float32).tiny
                          and fast.max() <= FLOAT32_MAX / 2):
        return  # clear of both limits by more than float32 rounding: the common case
    n2 = np.sum(np.square(r32.astype(np.float64)), axis=-1)
    bad = ~((n2 >= np.finfo(np.float32).tiny) & (n2 <= FLOAT32_MAX))
    if bad.any():
        index = np.argwhere(bad)[0]
        where = location(index, lead, joint_names)
        if n2[tuple(index)] == 0:
            raise InputError(f"rotations: zero quaternion at {where}")
        raise InputError(f"rotations: quaternion of norm {float(np.sqrt(n2[tuple(index)])):.3g} "
                         f"at {where} cannot be normalized in float32")


def _check_matrices(name, m, count, joint_names=None):
    """(count, 4, 4) float64, finite and within float32 range, else ValueError naming ``name``
    and the joints."""
    a = as_real(name, m).astype(np.float64)
    if a.shape != (count, 4, 4):
        raise InputError(f"{name}: expected ({count}, 4, 4), got {a.shape}")
    bad = ~np.isfinite(a).all(axis=(1, 2))
    if bad.any():
        raise InputError(f"{name}: NaN or infinite entries at {_joint_list(bad, joint_names)}")
    bad = (np.abs(a) > FLOAT32_MAX).any(axis=(1, 2))
    if bad.any():
        raise InputError(f"{name}: entries beyond float32 range (|x| > {FLOAT32_MAX:.4g}) at "
                         f"{_joint_list(bad, joint_names)}")
    return a


def _names(label, joint_names):
    """Joint names as a list of str."""
    try:
        return [str(n) for n in joint_names]
    except TypeError:
        raise InputError(f"{label}: joint_names: expected a sequence of names, got "
                         f"{type(joint_names).__name__}") from None


def _check_unique(label, names):
    """ValueError naming every joint name that occurs more than once."""
    seen, dups = set(), []
    for n in names:
        if n in seen and n not in dups:
            dups.append(n)
        seen.add(n)
    if dups:
        plural = "s" if len(dups) > 1 else ""
        raise InputError(f"{label}: joint_names: duplicate joint name{plural} "
                         f"{', '.join(map(repr, dups))}")


def _world_transform(label, m):
    """(4, 4) float64 finite skeleton → world transform (identity for None)."""
    if m is None:
        return np.eye(4)
    a = as_real(f"{label}: world_transform", m).astype(np.float64)
    if a.shape != (4, 4):
        raise InputError(f"{label}: world_transform: expected (4, 4), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{label}: world_transform: NaN or infinite entries")
    return a


def _invert_bind(label, bind, joint_names):
    """(J, 4, 4) inverses of finite bind transforms; ValueError naming the joints whose bind
    transform is singular: condition number beyond ``1/eps`` (float64), or an inverse that float32
    cannot hold."""
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(bind)
    singular = ~(cond < 1.0 / np.finfo(np.float64).eps)
    inv = np.tile(np.eye(4), (bind.shape[0], 1, 1))
    if not singular.all():
        try:
            inv[~singular] = np.linalg.inv(bind[~singular])
        except np.linalg.LinAlgError:
            singular[:] = True
    singular |= ~(np.abs(inv) <= FLOAT32_MAX).all(axis=(1, 2))
    if singular.any():
        raise InputError(f"{label}: bind_transforms: singular bind transform at "
                         f"{_joint_list(singular, joint_names)}")
    return inv


class Skeleton:
    """A joint hierarchy with its bind and rest pose.

    Parameters
    ----------
    joint_names : sequence of str, length J
        Unique names; a skeleton has at least one joint (no influence could refer to an empty
        one).
    parents : (J,) int
        Parent of each joint, ``-1`` for roots; parents come before children.
    bind_transforms : (J, 4, 4) float, optional
        World-space (skeleton-space) bind pose of each joint, column-vector convention. Identity
        by default. Finite, within float32 and invertible (skinning uses the inverses).
    rest_transforms : (J, 4, 4) float, optional
        Local (parent-relative) rest pose, used where no animation drives a joint. Defaults to the
        local transforms implied by ``bind_transforms``.
    name : str
        Where the skeleton came from (USD prim path, glTF skin name); used in messages.

    world_transform : (4, 4) float, optional
        Skeleton space → world space (USD: the Skeleton prim's local-to-world at the default
        time; identity for glTF, whose skeleton space is the world). Used for orientation only,
        e.g. which skeleton axis points up when rendering.
    animation : dqskin.animation.Animation, optional
        What drives the joints (USD: the bound SkelAnimation; glTF: the loaded clip); None holds
        the skeleton in its rest pose.

    Raises
    ------
    ValueError
        No joints, duplicate joint names, an invalid hierarchy, transforms of the wrong shape,
        NaN, infinite or beyond float32, or singular bind transforms; the message names the
        skeleton, the argument and the joints.
    """

    def __init__(self, joint_names: Sequence[str], parents: npt.ArrayLike,
                 bind_transforms: npt.ArrayLike | None = None,
                 rest_transforms: npt.ArrayLike | None = None, *, name: str = "",
                 world_transform: npt.ArrayLike | None = None,
                 animation: Animation | None = None) -> None:
        self.name = name
        self.animation = animation
        label = name or "skeleton"
        self.joint_names = _names(label, joint_names)
        self.parents = check_parents(parents, f"{label}: parents")
        J = self.joint_count
        if len(self.joint_names) != J:
            raise InputError(f"{label}: {len(self.joint_names)} joint names for {J} parents")
        if J == 0:
            raise InputError(f"{label}: no joints (a skeleton needs at least one joint)")
        _check_unique(label, self.joint_names)
        self.bind_transforms = (np.tile(np.eye(4), (J, 1, 1)) if bind_transforms is None else
                                _check_matrices(f"{label}: bind_transforms", bind_transforms, J,
                                                self.joint_names))
        self._inverse_bind = _invert_bind(label, self.bind_transforms, self.joint_names)
        if rest_transforms is None:
            rest = self.bind_transforms.copy()
            has_parent = self.parents >= 0
            rest[has_parent] = (self._inverse_bind[self.parents[has_parent]]
                                @ self.bind_transforms[has_parent])
            self.rest_transforms = _check_matrices(f"{label}: rest_transforms (from the bind "
                                                   "transforms)", rest, J, self.joint_names)
        else:
            self.rest_transforms = _check_matrices(f"{label}: rest_transforms", rest_transforms,
                                                   J, self.joint_names)
        self.world_transform = _world_transform(label, world_transform)

    def with_animation(self, animation: Animation | None) -> "Skeleton":
        """A copy of this skeleton (sharing its arrays) driven by ``animation``."""
        other = copy.copy(self)
        other.animation = animation
        return other

    @property
    def joint_count(self) -> int:
        return int(self.parents.shape[0])

    @property
    def inverse_bind_transforms(self) -> np.ndarray:
        """(J, 4, 4) float64 inverses of the bind transforms (ValueError naming the joints whose
        bind transform is singular)."""
        if self._inverse_bind is None:
            self._inverse_bind = _invert_bind(self.name or "skeleton", self.bind_transforms,
                                              self.joint_names)
        return self._inverse_bind

    @overload
    def forward_kinematics(self, local_transforms: LocalTransforms | None = None, *,
                           device: Device = None, return_dq: Literal[False] = False
                           ) -> np.ndarray: ...

    @overload
    def forward_kinematics(self, local_transforms: LocalTransforms | None = None, *,
                           device: Device = None, return_dq: Literal[True]
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def forward_kinematics(self, local_transforms: LocalTransforms | None = None, *,
                           device: Device = None, return_dq: bool = False
                           ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World (skeleton-space) joint transforms from local ones.

        Parameters
        ----------
        local_transforms : (..., J, 4, 4) float or (translations, rotations, scales), optional
            Parent-relative joint transforms (see :func:`forward_kinematics`); the rest pose
            when omitted.
        return_dq : bool
            Also return the rigid part as dual quaternions and the residual scale/shear.

        Returns
        -------
        world : (..., J, 4, 4) float32
        dq : (..., J, 8) float32, only with ``return_dq`` -- ``(rw, rx, ry, rz, dw, dx, dy, dz)``
        residual : (..., J, 3, 3) float32, only with ``return_dq`` -- ``world = [R·S | t]``

        Raises
        ------
        ValueError
            Local transforms of the wrong shape, NaN, infinite or beyond float32, or zero
            quaternions; the message names the argument, the frame and the joint, e.g.
            ``rotations: NaN at frame 3, joint 'Hips'``.
        """
        from ._warp import resolve_device
        local = self.rest_transforms if local_transforms is None else local_transforms
        out, shape = _forward_kinematics(self.parents, local, resolve_device(device),
                                         self.joint_names)
        return _results(out, shape, return_dq)

    @overload
    def skinning_transforms(self, local_transforms: LocalTransforms | None = None, *,
                            device: Device = None, as_warp: Literal[False] = False
                            ) -> np.ndarray: ...

    @overload
    def skinning_transforms(self, local_transforms: LocalTransforms | None = None, *,
                            device: Device = None, as_warp: Literal[True]) -> wp.array: ...

    def skinning_transforms(self, local_transforms: LocalTransforms | None = None, *,
                            device: Device = None, as_warp: bool = False
                            ) -> np.ndarray | wp.array:
        """Bind-relative skinning transforms ``world ∘ inverse(bind)``.

        Parameters
        ----------
        local_transforms : (..., J, 4, 4) float, optional
            Parent-relative transforms; rest pose when omitted.
        as_warp : bool
            Return the device array (F, J) of ``wp.mat44`` (leading axes flattened), ready for
            :meth:`dqskin.Skinner.skin` without leaving the device.

        Returns
        -------
        (..., J, 4, 4) float32, or a Warp array with ``as_warp``.

        Raises
        ------
        ValueError
            Local transforms of the wrong shape, NaN, infinite or beyond float32 (naming the
            argument, frame and joint), zero quaternions; a singular bind transform.
        """
        import warp as wp

        from ._warp import resolve_device
        from .kernels import buffers as KB
        from .kernels import fk as FK
        local = self.rest_transforms if local_transforms is None else local_transforms
        d = resolve_device(device)
        inverse_bind = self.inverse_bind_transforms.astype(np.float32)
        poses, shape = _forward_kinematics(self.parents, local, d, joint_names=self.joint_names)
        world = poses.matrices.reshape((-1, self.joint_count))
        inv: wp.array = wp.array(inverse_bind, dtype=wp.mat44, device=d)
        out = KB.empty(world.shape, wp.mat44, d)
        FK.bind_relative(world=world, inverse_bind=inv, skinning=out, device=d)
        return out if as_warp else out.numpy().reshape(*shape, 4, 4)


def _trs_arrays(pose, J, joint_names=None):
    """Checked float32 (translations, rotations, scales) of a TRS pose, and its batch shape."""
    if len(pose) != 3:
        raise InputError("local_transforms: a TRS pose is (translations, rotations, scales)")
    tr, rot, sc = pose
    rot = as_real("rotations", rot)
    if rot.ndim < 2 or rot.shape[-2:] != (J, 4):
        raise InputError(f"rotations: expected (..., {J}, 4) (w, x, y, z), got {rot.shape}")
    batch = rot.shape[:-2]
    tr = as_real("translations", tr)
    sc = np.ones(batch + (J, 3), np.float32) if sc is None else as_real("scales", sc)
    for name, a in (("translations", tr), ("scales", sc)):
        if a.shape != batch + (J, 3):
            raise InputError(f"{name}: expected {batch + (J, 3)}, got {a.shape}")
    for name, a in (("translations", tr), ("rotations", rot), ("scales", sc)):
        check_finite(name, a, len(batch), joint_names)
    tr, rot, sc = (np.ascontiguousarray(a, np.float32) for a in (tr, rot, sc))
    _check_quaternions(rot, len(batch), joint_names)
    return (tr, rot, sc), batch


def _matrix_array(local_transforms, J):
    """float32 contiguous (..., J, 4, 4) local matrices (the input itself when it is one), their
    batch shape, and the input as an array. Not checked for finite values: the FK kernel flags
    them (:func:`_check_matrices_after`), which saves a host pass over every pose."""
    loc = as_real("local_transforms", local_transforms)
    if loc.ndim < 3 or loc.shape[-3:] != (J, 4, 4):
        raise InputError(f"local_transforms: expected (..., {J}, 4, 4), got {loc.shape}")
    with np.errstate(over="ignore"):  # beyond float32 becomes inf: flagged by the kernel
        return np.ascontiguousarray(loc, np.float32), loc.shape[:-3], loc


def _check_matrices_after(out, loc, batch, joint_names=None):
    """Raise the host check's ValueError (naming the frame and joint) when the FK kernel
    flagged a non-finite local matrix (NaN, inf, or a float64 value beyond float32)."""
    if out.invalid.numpy()[0]:
        check_finite("local_transforms", loc, len(batch), joint_names)
        raise InputError("local_transforms: NaN or infinite values")  # (not reached)


def _device_array(a, dtype, device):
    """Flat (n,) Warp array of ``dtype`` over contiguous float32 ``a``: on the CPU a view of
    ``a`` (the kernels only read it), else an upload."""
    import warp as wp
    flat = a.reshape(-1, *dtype._shape_)
    return wp.array(flat, dtype=dtype, device=device, copy=not wp.get_device(device).is_cpu)


def _local_arrays(local_transforms, J, device, joint_names=None):
    """Check local poses and put them on the device, flat (B·J,): (..., J, 4, 4) matrices, or a
    (translations, rotations, scales) tuple of (..., J, 3), (..., J, 4) ``(w, x, y, z)``,
    (..., J, 3) or None. Returns (arrays, batch, matrices): TRS values are checked on the host
    (finite, within float32, non-zero quaternions: ValueError naming the argument, frame and
    joint); ``matrices``, the given matrices (None for TRS), are checked after the launch by
    :func:`_check_matrices_after`."""
    import warp as wp
    if isinstance(local_transforms, (tuple, list)):
        host, batch = _trs_arrays(local_transforms, J, joint_names)
        return tuple(_device_array(a, t, device)
                     for a, t in zip(host, (wp.vec3, wp.vec4, wp.vec3))), batch, None
    loc, batch, given = _matrix_array(local_transforms, J)
    return _device_array(loc, wp.mat44, device), batch, given


def _forward_kinematics(parents, local_transforms, device, joint_names=None):
    """Launch FK; returns the filled :class:`dqskin.kernels.fk.WorldPoses` (flat (B·J,)) and
    their shape ``batch + (J,)``."""
    import warp as wp

    from .kernels import fk as FK
    par = check_parents(parents)
    J = par.shape[0]
    if J == 0:
        raise InputError("parents: no joints")
    d = device
    local, batch, given = _local_arrays(local_transforms, J, d, joint_names)
    B = int(np.prod(batch, dtype=np.int64))
    out = FK.world_poses(B * J, d)
    par_w: wp.array = wp.array(par, dtype=wp.int32, device=d)
    start: wp.array = wp.array(np.array([0, J], np.int32), dtype=wp.int32, device=d)
    FK.forward_kinematics(parents=par_w, skeleton_start=start, local=local, out=out, device=d)
    if given is not None:
        _check_matrices_after(out, given, batch, joint_names)
    return out, batch + (J,)


def _results(out: FK.WorldPoses, shape: tuple[int, ...], return_dq: bool = False
             ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World matrices (and, with ``return_dq``, dual quaternions and residuals: the identity
    where the kernel flagged a joint rigid) as NumPy arrays of ``shape`` (..., J) joints."""
    w = out.matrices.numpy().reshape(*shape, 4, 4)
    if not return_dq:
        return w
    rigid = out.rigid.numpy().reshape(shape).astype(bool)
    residual = np.where(rigid[..., None, None], np.eye(3, dtype=np.float32),
                        out.residuals.numpy().reshape(*shape, 3, 3))
    return w, out.dqs.numpy().reshape(*shape, 8), residual


@overload
def forward_kinematics(parents: npt.ArrayLike, local_transforms: LocalTransforms, *,
                       device: Device = None, return_dq: Literal[False] = False) -> np.ndarray: ...


@overload
def forward_kinematics(parents: npt.ArrayLike, local_transforms: LocalTransforms, *,
                       device: Device = None, return_dq: Literal[True]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def forward_kinematics(parents: npt.ArrayLike, local_transforms: LocalTransforms, *,
                       device: Device = None, return_dq: bool = False
                       ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward kinematics for one hierarchy over any batch of poses, in one launch.

    The hierarchy is concatenated as dual quaternions; scale and shear ride along as a residual
    3×3 (see :mod:`dqskin.kernels.fk`), so non-rigid skeletons come out exact.

    Parameters
    ----------
    parents : (J,) int
        Parents first, ``-1`` for roots.
    local_transforms : (..., J, 4, 4) float, or (translations, rotations, scales)
        Parent-relative transforms, column-vector convention; or TRS poses as animations store
        them: translations (..., J, 3), unit rotations (..., J, 4) ``(w, x, y, z)``, scales
        (..., J, 3) or None, composed as ``T·R·S``. The leading axes (frames, characters) are
        flattened into one launch.

    Returns
    -------
    world : (..., J, 4, 4) float32
    dq, residual : (..., J, 8), (..., J, 3, 3) float32 with ``return_dq``.

    Raises
    ------
    ValueError
        Invalid hierarchy; local transforms of the wrong shape, NaN, infinite or beyond float32,
        or zero quaternions: the message names the argument (``local_transforms``,
        ``translations``, ``rotations``, ``scales``), the frame (batch index) and the joint index.
    """
    from ._warp import resolve_device
    out, shape = _forward_kinematics(parents, local_transforms, resolve_device(device))
    return _results(out, shape, return_dq)
