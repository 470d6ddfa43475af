"""Crowds: many skinned meshes and skeletons in one launch each.

Skinning one character at a time costs one FK launch per skeleton and one skinning launch per
mesh and frame block; a crowd of small characters is then bound by launch overhead, not by the
kernels. Here every skeleton of a batch is concatenated on one joint axis (FK's kernel already
walks many skeletons, ``skeleton_start``), and every mesh on one vertex axis: points moved to
their skeleton's bind space, joint indices offset onto the concatenated joints, so a single
:class:`dqskin.Skinner` skins every instance with the existing kernels, one launch per method.

* :class:`JointBatch`: skeletons → one FK launch → (F, ΣJ) skinning transforms on the device.
* :class:`MeshBatch`: meshes → one :class:`~dqskin.skinning.Skinner` (one influence layout).
* :class:`Crowd`: instances of characters (any :class:`dqskin.Scene`: meshes, skeletons,
  animations), each with a time offset and a root transform, built in code.

:mod:`dqskin.pipeline` skins a :class:`dqskin.Scene` of many meshes (a USD stage referencing many
characters) with the same batches; it and a :class:`Crowd` skin them with :func:`skin_batch`.
"""

import numbers
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt
import warp as wp

from ._warp import Device, resolve_device
from .animation import check_times
from .errors import InputError, Param
from .influences import Influences
from .kernels import buffers as KB
from .kernels import fk as FK
from .options import Interpolation, Method, SkinOptions
from .skinning import Skinner
from .validation import check_transforms

if TYPE_CHECKING:
    from .scene import Mesh, Scene
    from .skeleton import Skeleton

__all__ = ["BATCH_METHODS", "Crowd", "JointBatch", "MeshBatch", "skin_batch"]

BATCH_METHODS = ("lbs", "dqs", "blend")
"""Methods a :class:`MeshBatch` skins in one launch (the others need per-mesh data)."""


def _ranges(counts: Sequence[int]) -> tuple[list[slice], int]:
    starts = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
    return [slice(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:])], int(starts[-1])


class JointBatch:
    """Skeletons concatenated on one joint axis, posed with one FK launch.

    Parameters
    ----------
    skeletons : sequence of dqskin.Skeleton
    device : str, optional

    Attributes
    ----------
    joints : list of slice
        Each skeleton's joints on the concatenated axis.
    joint_count : int
    """

    def __init__(self, skeletons: "Iterable[Skeleton]", device: Device = None) -> None:
        self.device = resolve_device(device)
        self.skeletons = list(skeletons)
        self.joints, self.joint_count = _ranges([s.joint_count for s in self.skeletons])
        parents = np.concatenate([np.where(s.parents >= 0, s.parents + sl.start, -1)
                                  for s, sl in zip(self.skeletons, self.joints)])
        starts = [sl.start for sl in self.joints] + [self.joint_count]
        inverse_bind = np.concatenate([s.inverse_bind_transforms for s in self.skeletons])
        d = self.device
        self._parents: wp.array = wp.array(parents.astype(np.int32), dtype=wp.int32, device=d)
        self._starts: wp.array = wp.array(np.asarray(starts, np.int32), dtype=wp.int32, device=d)
        self._inverse_bind: wp.array = wp.array(inverse_bind.astype(np.float32), dtype=wp.mat44,
                                                device=d)

    def skinning_transforms(self, local_transforms: Sequence[np.ndarray]) -> wp.array:
        """(F, ΣJ) ``wp.mat44`` bind-relative transforms on the device, from each skeleton's
        checked (F, J, 4, 4) local transforms (one host copy, uploaded on a GPU and read in place
        on the CPU, one FK launch, one bind-relative launch)."""
        F = local_transforms[0].shape[0]
        host = np.empty((F, self.joint_count, 4, 4), np.float32)
        for sl, local in zip(self.joints, local_transforms):
            host[:, sl] = local
        d = self.device
        # on the CPU the kernel reads the host copy in place (no second copy)
        device_local: wp.array = wp.array(host.reshape(-1, 4, 4), dtype=wp.mat44, device=d,
                                copy=not wp.get_device(d).is_cpu)
        shape = (F, self.joint_count)
        poses = FK.world_poses(F * self.joint_count, d)
        FK.forward_kinematics(parents=self._parents, skeleton_start=self._starts,
                              local=device_local,
                              out=poses, device=d)
        world = poses.matrices.reshape(shape)
        out = KB.empty(shape, wp.mat44, d)
        FK.bind_relative(world=world, inverse_bind=self._inverse_bind, skinning=out, device=d)
        return out


class MeshBatch:
    """Meshes concatenated on one vertex axis, skinned by one :class:`~dqskin.skinning.Skinner`.

    Parameters
    ----------
    meshes : sequence of dqskin.Mesh
    joint_offsets : sequence of int
        Where each mesh's skeleton starts on the concatenated joint axis
        (:attr:`JointBatch.joints`).
    joint_counts : sequence of int
        Joints of each mesh's skeleton (its indices must stay below).
    device : str, optional

    Each mesh's rest points are moved to bind space by its ``geom_bind_transform``; influences
    are zero-padded to the largest ``K``; ``blend_weights`` default to ½ as per mesh.

    Attributes
    ----------
    vertices : list of slice
        Each mesh's vertices on the concatenated axis.
    skinner : dqskin.Skinner
    """

    def __init__(self, meshes: "Iterable[Mesh]", joint_offsets: Sequence[int],
                 joint_counts: Sequence[int], device: Device = None) -> None:
        self.meshes = list(meshes)
        influences, self.vertices = Influences.concatenate(
            [(m.joint_indices, m.joint_weights) for m in self.meshes], joint_offsets,
            joint_counts, [m.name for m in self.meshes])
        V = influences.vertex_count
        points = np.empty((V, 3), np.float32)
        blend = np.empty(V, np.float32)
        for m, sl in zip(self.meshes, self.vertices):
            g = np.asarray(m.geom_bind_transform, np.float64)
            points[sl] = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
            blend[sl] = m.blend_or_default()
        self.skinner = Skinner(points, influences, None, blend_weights=blend, device=device)
        # bind_normals of rest normals, by meshes: made once, as the rest points above are
        self._rest_normals: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, list[slice]]] = {}

    @property
    def vertex_count(self) -> int:
        return self.skinner.vertex_count

    def bind_points(self, per_mesh: dict[int, np.ndarray], frames: int) -> np.ndarray | None:
        """(F, V, 3) float32 bind-space rest points: ``per_mesh`` maps a mesh index to its
        (F, Vm, 3) mesh-space points (deformed), the others keep their rest points; None when no
        mesh has any."""
        if not per_mesh:
            return None
        rest = self.skinner._points.numpy()  # (1, V, 3) bind space, float32
        out = np.repeat(rest, frames, axis=0)
        for i, p in per_mesh.items():
            g = np.asarray(self.meshes[i].geom_bind_transform, np.float64)
            out[:, self.vertices[i]] = p @ g[:3, :3].T + g[:3, 3]
        return out

    def bind_velocities(self, per_mesh: dict[int, np.ndarray],
                        frames: int) -> np.ndarray | None:
        """(F, V, 3) float32 bind-space rest-point velocities (zero for meshes not in
        ``per_mesh``); None when no mesh has any."""
        if not per_mesh:
            return None
        out = np.zeros((frames, self.vertex_count, 3), np.float32)
        for i, v in per_mesh.items():
            g = np.asarray(self.meshes[i].geom_bind_transform, np.float64)
            out[:, self.vertices[i]] = v @ g[:3, :3].T
        return out

    def bind_normals(self, meshes: Sequence[int], per_mesh: dict[int, np.ndarray],
                     frames: int) -> tuple[np.ndarray, np.ndarray, list[slice]]:
        """``(vectors (Fp, N, 3) float32 bind space, vector_vertex (N,) int32, slices)`` of the
        normals of ``meshes`` (indices): a mesh's deformed normals in ``per_mesh`` (F, N, 3),
        else its rest normals; normals move by the inverse transpose of the geom-bind linear
        part. Rest normals only: made once per ``meshes`` (read-only arrays)."""
        rest = not any(i in per_mesh for i in meshes)
        done = self._rest_normals.get(tuple(meshes)) if rest else None
        if done is not None:
            return done
        blocks, vv, counts = [], [], []
        per_frame = any(np.ndim(per_mesh[i]) == 3 for i in meshes if i in per_mesh)
        for i in meshes:
            m = self.meshes[i]
            g = np.asarray(m.geom_bind_transform, np.float64)[:3, :3]
            try:
                ginv = np.linalg.inv(g)
            except np.linalg.LinAlgError:
                raise InputError(f"{m.name}: geom_bind_transform: singular, normals cannot "
                                 "follow") from None
            n = np.asarray(per_mesh.get(i, m.normals), np.float64) @ ginv  # (G⁻ᵀ·n)ᵀ = nᵀ·G⁻¹
            blocks.append(np.broadcast_to(n, (frames,) + n.shape[-2:]) if per_frame else n)
            start = self.vertices[i].start
            vv.append((np.arange(len(m.points)) if m.normal_vertex is None
                       else np.asarray(m.normal_vertex, np.int64)) + start)
            counts.append(n.shape[-2])
        slices, _ = _ranges(counts)
        axis = 1 if blocks[0].ndim == 3 else 0
        vectors = np.concatenate(blocks, axis=axis).astype(np.float32)
        result = vectors, np.concatenate(vv).astype(np.int32), slices
        if rest:
            vectors.flags.writeable = result[1].flags.writeable = False
            self._rest_normals[tuple(meshes)] = result
        return result


def skin_batch(batch: MeshBatch, skinning_transforms: npt.ArrayLike | wp.array, method: Method,
               options: SkinOptions, *, points: npt.ArrayLike | None = None,
               as_warp: bool = False) -> np.ndarray | wp.array:
    """(F, V, 3) float32 points of every mesh of ``batch`` (bind space, or crowd space for a
    :class:`Crowd`) in one launch: its skinner with ``method`` and ``options``' sign rule;
    ``points`` (F, V, 3) bind-space rest points when deformed. ``as_warp``: the device array."""
    return batch.skinner.skin(skinning_transforms, method, points=points,
                              sign_reference=options.sign_reference, as_warp=as_warp)


class _Batch(NamedTuple):
    """A :class:`Crowd`'s instances as launched: the list they were built from, every skeleton
    (:class:`JointBatch`), every mesh (:class:`MeshBatch`) and the ``"instance/mesh"`` names."""

    instances: list
    joints: "JointBatch"
    meshes: "MeshBatch"
    names: list


@dataclass(frozen=True)
class Instance:
    """One placed character of a :class:`Crowd`."""

    name: str
    character: "Scene"
    """A :class:`dqskin.Scene` (meshes, skeletons and their animations)."""
    time_offset: float
    """The instance shows its animation at ``t - time_offset`` (a USD layer offset)."""
    root_transform: np.ndarray
    """(4, 4) float64: the character's skeleton space → crowd space."""


class Crowd:
    """Many instances of characters, skinned with one FK launch for every skeleton and one
    skinning launch for every vertex, per call.

    Parameters
    ----------
    device : str, optional
        Warp device; CUDA when present, else CPU.

    Examples
    --------
    >>> crowd = Crowd()
    >>> for k in range(100):
    ...     crowd.add(scene, time_offset=0.1 * k, root_transform=placement[k])
    >>> points = crowd.skin(times, "dqs")          # (F, V, 3), every instance
    >>> parts = crowd.split(points)                # "instance/mesh" → (F, Vm, 3)

    Each instance's root transform is composed onto its skeleton's root joints (the skeleton is
    placed, then skinned), so a point comes out in crowd space: ``root · skinned`` exactly for
    rigid or uniformly scaled roots (and for any root under LBS with weights summing to one).
    Output transforms of the meshes (glTF node or USD prim transforms) are not applied: results
    are in each instance's skeleton space moved by its root.
    """

    def __init__(self, device: Device = None) -> None:
        self.device = resolve_device(device)
        self.instances: list[Instance] = []
        self._batch: _Batch | None = None  # of the instances, built on first use after a change
        self._version = 0  # add() count: a batch built from an older list is not kept

    def add(self, character: "Scene", *, time_offset: float = 0.0,
            root_transform: npt.ArrayLike | None = None, name: str | None = None) -> str:
        """Place one more instance of ``character`` (a :class:`dqskin.Scene`); returns its name
        (default ``"i<index>"``). InputError (a ValueError) for a non-finite offset or root
        transform, a repeated name, or a character without meshes."""
        if not getattr(character, "meshes", None):
            raise InputError("character: no skinned meshes")
        if isinstance(time_offset, bool) or not isinstance(time_offset, numbers.Real) \
                or not np.isfinite(time_offset):
            raise InputError(Param("time_offset", time_offset), ": expected a finite number")
        off = float(time_offset)
        root = np.eye(4) if root_transform is None else check_transforms(
            "root_transform", np.asarray(root_transform, np.float64).reshape(1, 4, 4))[0]
        if not np.allclose(root[3], [0, 0, 0, 1]):
            raise InputError("root_transform: last row must be (0, 0, 0, 1)")
        name = f"i{len(self.instances)}" if name is None else str(name)
        if any(i.name == name for i in self.instances):
            raise InputError(f"instance name {name!r} used twice")
        self.instances = [*self.instances, Instance(name, character, off, root)]
        self._version += 1
        self._batch = None
        return name

    def _build(self):
        """The :class:`_Batch` of the current instances (built once after a change). One
        object, replaced whole: a call that took it keeps a consistent set of instances, skeletons
        and meshes while another thread adds instances."""
        batch, version = self._batch, self._version
        if batch is not None:
            return batch
        instances = self.instances
        if not instances:
            raise InputError("crowd: no instances (add some first)")
        skeletons: "list[Skeleton]" = []
        meshes: "list[Mesh]" = []
        offsets: list[int] = []
        counts: list[int] = []
        names: list[str] = []
        for inst in instances:
            first = len(skeletons)
            skeletons.extend(inst.character.skeletons)
            for m in inst.character.meshes:
                meshes.append(m)
                offsets.append(first + m.skeleton)
                counts.append(inst.character.skeletons[m.skeleton].joint_count)
                names.append(f"{inst.name}/{m.name}")
        joints = JointBatch(skeletons, self.device)
        batch = _Batch(instances, joints, MeshBatch(
            meshes, [joints.joints[s].start for s in offsets], counts, self.device), names)
        if self._version == version:  # (else an add() came meanwhile: used once, not kept)
            self._batch = batch
        return batch

    @property
    def vertex_count(self) -> int:
        return self._build().meshes.vertex_count

    @property
    def joint_count(self) -> int:
        return self._build().joints.joint_count

    @property
    def slices(self) -> dict:
        """``"instance/mesh"`` → slice of the vertex axis of :meth:`skin`'s result."""
        batch = self._build()
        return dict(zip(batch.names, batch.meshes.vertices))

    def split(self, points: np.ndarray) -> dict:
        """``"instance/mesh"`` → (F, Vm, 3) views of a (F, V, 3) result of :meth:`skin`."""
        return {name: points[:, sl] for name, sl in self.slices.items()}

    def local_transforms(self, times: npt.ArrayLike, *,
                         interp: Interpolation = SkinOptions.interp) -> list:
        """Every instance skeleton's (F, J, 4, 4) local transforms at ``times`` (each at ``t −
        time_offset``), root transforms composed onto root joints. Instances of the same
        character skeleton are sampled in one call."""
        return self._local_transforms(times, self.instances, interp)

    @staticmethod
    def _local_transforms(times, instances, interp):
        t = check_times(times)
        F = t.shape[0]
        groups: dict[tuple[int, int], list[int]] = {}
        for k, inst in enumerate(instances):
            for s in range(len(inst.character.skeletons)):
                groups.setdefault((id(inst.character), s), []).append(k)
        per = {}
        for (_, s), ks in groups.items():
            character = instances[ks[0]].character
            tt = np.concatenate([t - instances[k].time_offset for k in ks])
            local = np.asarray(character.local_transforms(tt, s, interp=interp), np.float64)
            roots = character.skeletons[s].parents < 0
            for n, k in enumerate(ks):
                loc = local[n * F:(n + 1) * F]
                root = instances[k].root_transform
                if not np.array_equal(root, np.eye(4)):
                    loc = loc.copy()
                    loc[:, roots] = root @ loc[:, roots]
                per[(k, s)] = loc
        return [per[(k, s)] for k, inst in enumerate(instances)
                for s in range(len(inst.character.skeletons))]

    def pose(self, local_transforms: list) -> wp.array:
        """(F, ΣJ) ``wp.mat44`` skinning transforms on the device from :meth:`local_transforms`'
        list, in one FK launch."""
        return self._pose(self._build(), local_transforms)

    @staticmethod
    def _pose(batch, local_transforms):
        if len(local_transforms) != len(batch.joints.skeletons):
            raise InputError(f"local_transforms: {len(local_transforms)} skeletons for "
                             f"{len(batch.joints.skeletons)}")
        return batch.joints.skinning_transforms(local_transforms)

    def skinning_transforms(self, times: npt.ArrayLike, *,
                            interp: Interpolation = SkinOptions.interp) -> wp.array:
        """(F, ΣJ) ``wp.mat44`` skinning transforms of every instance skeleton, crowd space:
        :meth:`local_transforms` then :meth:`pose`."""
        return self._skinning_transforms(self._build(), times, interp)

    def _skinning_transforms(self, batch, times, interp):
        return self._pose(batch, self._local_transforms(times, batch.instances, interp))

    def skin(self, times: npt.ArrayLike, method: Method | None = None, *,
             options: SkinOptions | None = None, as_warp: bool = False,
             **changes: Any) -> np.ndarray | wp.array:
        """Skin every instance at ``times`` with one method (:func:`skin_batch`).

        Parameters
        ----------
        times : (F,) float
            Crowd time (each instance samples ``t − time_offset`` of its character's time unit).
        method : {"dqs", "lbs", "blend"}, optional
            Shorthand for ``options.method``; a crowd skins "dqs" when neither gives one.
        options : dqskin.SkinOptions, optional
            ``method``, ``interp`` and ``sign_reference`` ("largest_weight" only) apply; a
            crowd skins points only (InputError naming normals, tangents, velocities or another
            sign rule when asked, or a device other than the crowd's). ``space`` and
            ``blend_shapes`` do not apply: the points are the skinned bind points in crowd
            space (each instance's skeleton space through its root transform).
        as_warp : bool
            Return the device array (F, V) ``wp.vec3`` without a copy.
        **changes
            Fields of :class:`~dqskin.options.SkinOptions` replacing those of ``options``.

        Returns
        -------
        (F, V, 3) float32
            Every instance's points in crowd space, in :attr:`slices` order.
        """
        opts = SkinOptions.build(options, **changes)
        meth: Method = method or opts.method or "dqs"
        opts = opts.replace(method=meth)
        refused = [Param(k, getattr(opts, k)) for k in ("normals", "tangents", "velocities")
                   if getattr(opts, k)]
        if opts.sign_reference != "largest_weight":
            refused.append(Param("sign_reference", opts.sign_reference))
        if opts.device is not None and str(resolve_device(opts.device)) != str(self.device):
            refused.append(Param("device", opts.device))  # (the crowd's: Crowd(device=...))
        if refused:
            parts: list[str | Param] = ["a crowd skins points only, in crowd space, with the "
                                        "largest-weight sign rule; not "]
            for i, p in enumerate(refused):
                parts += [", " if i else "", p]
            raise InputError(*parts)
        self._check_method(meth)
        batch = self._build()  # one set of instances for the transforms and the skinning
        return skin_batch(batch.meshes, self._skinning_transforms(batch, times, opts.interp),
                          meth, opts, as_warp=as_warp)

    def skin_transforms(self, skinning_transforms: wp.array, method: Method = "dqs", *,
                        as_warp: bool = False) -> np.ndarray | wp.array:
        """Skin every instance with given (F, ΣJ) skinning transforms (:meth:`pose`,
        :meth:`skinning_transforms`, or a (F, ΣJ, 4, 4) array): one launch."""
        self._check_method(method)
        return self._build().meshes.skinner.skin(skinning_transforms, method, as_warp=as_warp)

    @staticmethod
    def _check_method(method):
        if method not in BATCH_METHODS:
            raise InputError(f"method must be one of {list(BATCH_METHODS)} for a crowd, got "
                             f"{method!r}")
