"""Skeletons: joint hierarchy, bind and rest transforms, forward kinematics on the device."""

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import warp as wp

from ._warp import Device, resolve_device
from .kernels import fk as FK
from .kernels.dqmath import vec8

__all__ = ["LocalTransforms", "Skeleton", "check_parents", "forward_kinematics"]

LocalTransforms = npt.ArrayLike | tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike | None]
"""Parent-relative joint poses: (..., J, 4, 4) matrices, or (translations (..., J, 3), rotations
(..., J, 4) ``(w, x, y, z)``, scales (..., J, 3) or None)."""


def check_parents(parents, where="parents"):
    """Validate a joint hierarchy: (J,) ints in [-1, J), parents before children, no cycles.

    Returns the parents as int32; raises ValueError naming ``where`` and the offending joint.
    """
    p = np.asarray(parents)
    if p.ndim != 1 or not np.issubdtype(p.dtype, np.integer):
        raise ValueError(f"{where}: expected a 1-D integer array, got shape {p.shape} {p.dtype}")
    j = np.arange(p.shape[0])
    bad = np.nonzero((p < -1) | (p >= p.shape[0]))[0]
    if bad.size:
        raise ValueError(f"{where}: joint {bad[0]} has parent {p[bad[0]]} out of range "
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
            raise ValueError(f"{where}: cycle in the joint hierarchy through joint {cur}")
        raise ValueError(f"{where}: joint {k} comes before its parent {int(p[k])}; joints must be "
                         "ordered parents first")
    return p.astype(np.int32)


def _check_matrices(name, m, count):
    a = np.asarray(m, dtype=np.float64)
    if a.shape != (count, 4, 4):
        raise ValueError(f"{name}: expected ({count}, 4, 4), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: NaN or infinite entries")
    return a


class Skeleton:
    """A joint hierarchy with its bind and rest pose.

    Parameters
    ----------
    joint_names : sequence of str, length J
    parents : (J,) int
        Parent of each joint, ``-1`` for roots; parents come before children.
    bind_transforms : (J, 4, 4) float, optional
        World-space (skeleton-space) bind pose of each joint, column-vector convention. Identity
        by default.
    rest_transforms : (J, 4, 4) float, optional
        Local (parent-relative) rest pose, used where no animation drives a joint. Defaults to the
        local transforms implied by ``bind_transforms``.
    name : str
        Where the skeleton came from (USD prim path, glTF skin name); used in messages.

    world_transform : (4, 4) float, optional
        Skeleton space → world space (USD: the Skeleton prim's local-to-world at the default
        time; identity for glTF, whose skeleton space is the world). Used for orientation only,
        e.g. which skeleton axis points up when rendering.
    """

    def __init__(self, joint_names: Sequence[str], parents: npt.ArrayLike,
                 bind_transforms: npt.ArrayLike | None = None,
                 rest_transforms: npt.ArrayLike | None = None, *, name: str = "",
                 world_transform: npt.ArrayLike | None = None) -> None:
        self.name = name
        self.joint_names = [str(n) for n in joint_names]
        self.parents = check_parents(parents, f"{name or 'skeleton'}: parents")
        J = self.joint_count
        if len(self.joint_names) != J:
            raise ValueError(f"{name or 'skeleton'}: {len(self.joint_names)} joint names for "
                             f"{J} parents")
        self.bind_transforms = (np.tile(np.eye(4), (J, 1, 1)) if bind_transforms is None else
                                _check_matrices(f"{name or 'skeleton'}: bind_transforms",
                                                bind_transforms, J))
        if rest_transforms is None:
            rest = self.bind_transforms.copy()
            has_parent = self.parents >= 0
            rest[has_parent] = (np.linalg.inv(self.bind_transforms[self.parents[has_parent]])
                                @ self.bind_transforms[has_parent])
            self.rest_transforms = rest
        else:
            self.rest_transforms = _check_matrices(f"{name or 'skeleton'}: rest_transforms",
                                                   rest_transforms, J)
        self._inverse_bind = None
        self.world_transform = (np.eye(4) if world_transform is None else
                                np.asarray(world_transform, dtype=np.float64).reshape(4, 4))

    @property
    def joint_count(self):
        return int(self.parents.shape[0])

    @property
    def inverse_bind_transforms(self):
        """(J, 4, 4) float64 inverses of the bind transforms."""
        if self._inverse_bind is None:
            try:
                self._inverse_bind = np.linalg.inv(self.bind_transforms)
            except np.linalg.LinAlgError:
                raise ValueError(f"{self.name or 'skeleton'}: singular bind transform") from None
        return self._inverse_bind

    def forward_kinematics(self, local_transforms: LocalTransforms | None = None, *,
                           device: Device = None, return_dq: bool = False):
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
        """
        local = self.rest_transforms if local_transforms is None else local_transforms
        return forward_kinematics(self.parents, local, device=device, return_dq=return_dq)

    def skinning_transforms(self, local_transforms: LocalTransforms | None = None, *,
                            device: Device = None, as_warp: bool = False):
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
        """
        local = self.rest_transforms if local_transforms is None else local_transforms
        d = resolve_device(device)
        world, batch = _forward_kinematics(self.parents, local, d)
        inv = wp.array(self.inverse_bind_transforms.astype(np.float32), dtype=wp.mat44, device=d)
        out = wp.empty(world.shape, dtype=wp.mat44, device=d)
        FK.bind_relative(world=world, inverse_bind=inv, skinning=out, device=d)
        return out if as_warp else out.numpy().reshape(*batch, self.joint_count, 4, 4)


def _local_arrays(local_transforms, J, device):
    """Upload local poses: (..., J, 4, 4) matrices, or a (translations, rotations, scales) tuple of
    (..., J, 3), (..., J, 4) ``(w, x, y, z)``, (..., J, 3) or None. Returns (arrays, batch)."""
    if isinstance(local_transforms, (tuple, list)):
        if len(local_transforms) != 3:
            raise ValueError("local_transforms: a TRS pose is (translations, rotations, scales)")
        tr, rot, sc = local_transforms
        rot = np.asarray(rot, dtype=np.float32)
        if rot.ndim < 2 or rot.shape[-2:] != (J, 4):
            raise ValueError(f"rotations: expected (..., {J}, 4) (w, x, y, z), got {rot.shape}")
        batch = rot.shape[:-2]
        B = int(np.prod(batch, dtype=np.int64))
        tr = np.asarray(tr, dtype=np.float32)
        sc = (np.ones(rot.shape[:-1] + (3,), np.float32) if sc is None else
              np.asarray(sc, np.float32))
        for name, a in (("translations", tr), ("scales", sc)):
            if a.shape != batch + (J, 3):
                raise ValueError(f"{name}: expected {batch + (J, 3)}, got {a.shape}")
        arrays = tuple(wp.array(np.ascontiguousarray(a.reshape(B, J, -1)), dtype=t, device=device)
                       for a, t in ((tr, wp.vec3), (rot, wp.vec4), (sc, wp.vec3)))
        return arrays, batch
    loc = np.asarray(local_transforms, dtype=np.float32)
    if loc.ndim < 3 or loc.shape[-3:] != (J, 4, 4):
        raise ValueError(f"local_transforms: expected (..., {J}, 4, 4), got {loc.shape}")
    batch = loc.shape[:-3]
    B = int(np.prod(batch, dtype=np.int64))
    return wp.array(np.ascontiguousarray(loc.reshape(B, J, 4, 4)), dtype=wp.mat44,
                    device=device), batch


def _forward_kinematics(parents, local_transforms, device, outputs=None):
    """Launch FK; returns the (B, J) world ``wp.mat44`` array and the batch shape."""
    par = check_parents(parents)
    J = par.shape[0]
    d = device
    local, batch = _local_arrays(local_transforms, J, d)
    B = int(np.prod(batch, dtype=np.int64))
    world_dq = wp.empty((B, J), dtype=vec8, device=d)
    residual = wp.empty((B, J), dtype=wp.mat33, device=d)
    world = wp.empty((B, J), dtype=wp.mat44, device=d)
    par_w = wp.array(par, dtype=wp.int32, device=d)
    start = wp.array(np.array([0, J], np.int32), dtype=wp.int32, device=d)
    FK.forward_kinematics(parents=par_w, skeleton_start=start, local=local, world_dq=world_dq,
                          world_residual=residual, world=world, device=d)
    if outputs is not None:
        outputs.extend([world_dq, residual])
    return world, batch


def forward_kinematics(parents: npt.ArrayLike, local_transforms: LocalTransforms, *,
                       device: Device = None, return_dq: bool = False):
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
    """
    extra = []
    world, batch = _forward_kinematics(parents, local_transforms, resolve_device(device), extra)
    J = world.shape[1]
    w = world.numpy().reshape(*batch, J, 4, 4)
    if not return_dq:
        return w
    return w, extra[0].numpy().reshape(*batch, J, 8), extra[1].numpy().reshape(*batch, J, 3, 3)
