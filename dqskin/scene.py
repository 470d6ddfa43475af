"""The loaded scene: skinned meshes, their skeletons and animations, skinned per frame on a device.

Loaders (:mod:`dqskin.readers.usd`, :mod:`dqskin.readers.gltf`) fill these containers;
:meth:`Scene.skin` runs the same engine (:mod:`dqskin.pipeline`) for every format: animation →
local transforms → forward kinematics (dual quaternions) → skinning transforms
→ per-vertex skinning → the space asked for (:mod:`dqskin.spaces`).
"""

from __future__ import annotations

import numbers
from collections.abc import Generator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from .animation import Deformer, TransformTrack, check_times, sample
from .errors import InputError, Param, UnknownNameError
from .options import CorOptions, Interpolation, Method, SkinOptions
from .skeleton import Skeleton
from .validation import check_transforms

# Warp, the kernels and the skinning engine load when a scene is first skinned, not when it is
# loaded (``dqskin info`` reads a scene without them)
if TYPE_CHECKING:
    from ._warp import Device
    from .kernels import buffers as KB
    from .pipeline import SkinnedFrames
    from .skinning import Skinner

__all__ = ["DEFAULT_BLEND", "Mesh", "Scene", "SkinnedFrames"]


def __getattr__(name: str) -> Any:
    if name == "SkinnedFrames":  # defined by the skinning engine, loaded on first use
        from .pipeline import SkinnedFrames
        return SkinnedFrames
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

DEFAULT_BLEND = 0.5
"""DQS fraction of ``method="blend"`` for meshes without their own ``blend_weights``."""


@dataclass
class Mesh:
    """One skinned mesh, ready for :class:`dqskin.Skinner`.

    Attributes
    ----------
    name : str
        USD prim path or glTF node name (unique within the scene).
    points : (V, 3) float32
        Rest points in mesh space.
    faces : (T, 3) int32
        Triangles (polygons fan-triangulated); empty for point-only prims.
    joint_indices, joint_weights : (V, K) int32, float32
        Influences, indices into ``scene.skeletons[skeleton]`` joint order.
    skeleton : int
        Index into ``scene.skeletons``.
    geom_bind_transform : (4, 4) float64
        Mesh space → skeleton (bind) space.
    skinning_method : {"lbs", "dqs"}
        What the asset asks for.
    normals : (N, 3) float32 or None
        Rest normals in mesh space; ``normal_vertex`` (N,) int32 maps each to its vertex when
        they are face-varying (None when per-vertex).
    tangents : (V, 4) float32 or None
        Rest tangents in mesh space, per vertex: direction ``(x, y, z)`` and handedness ``w``
        (±1, glTF's bitangent sign).
    output_transforms : dqskin.animation.TransformTrack or None
        Skeleton (bind) space → the mesh's local space, keyed over time (USD: the prim's own
        space; glTF, BVH and rigged meshes: world, their local space being the world). Identity
        when None.
    world_transforms : dqskin.animation.TransformTrack or None
        Skeleton (bind) space → world space over time: the stage's world, in its own length
        unit and up axis (``Scene.meters_per_unit``, ``Scene.up_axis``; no unit conversion).
        USD: the Skeleton prim's local-to-world, so that ``world_transforms`` equals the prim's
        local-to-world composed with ``output_transforms``. None when it equals
        ``output_transforms`` (glTF, BVH and rigged meshes; USD prims whose local-to-world is
        the identity).
    deformer : dqskin.animation.Deformer or None
        Rest points (and normals, tangents) changing over time before skinning: blend shapes,
        glTF morph targets, time-sampled points.
    face_vertex_counts, face_vertex_indices : int32 arrays or None
        Original polygon topology (kept by writers).
    uvs : (U, 2) float32 or None
    blend_weights : (V,) float32 or None
        DQS fraction per vertex for ``method="blend"``; None means ½ everywhere.
    """

    name: str
    points: np.ndarray
    faces: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    skeleton: int = 0
    geom_bind_transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    skinning_method: str = "lbs"
    normals: np.ndarray | None = None
    normal_vertex: np.ndarray | None = None
    output_transforms: TransformTrack | None = None
    world_transforms: TransformTrack | None = None
    deformer: Deformer | None = None
    face_vertex_counts: np.ndarray | None = None
    face_vertex_indices: np.ndarray | None = None
    uvs: np.ndarray | None = None
    blend_weights: np.ndarray | None = None
    tangents: np.ndarray | None = None

    def __post_init__(self) -> None:
        # read-only arrays: a Skinner uploaded from them stays valid (replace a mesh, then call
        # Scene.invalidate, to change one)
        for name in ("points", "faces", "joint_indices", "joint_weights", "normals",
                     "blend_weights", "tangents"):
            a = getattr(self, name)
            if isinstance(a, np.ndarray):
                a = a.view()  # the caller's array stays writable
                a.flags.writeable = False
                setattr(self, name, a)

    def blend_or_default(self) -> np.ndarray:
        """(V,) float32 blend weights, ½ where none were given."""
        if self.blend_weights is not None:
            return np.asarray(self.blend_weights, np.float32)
        return np.full(len(self.points), DEFAULT_BLEND, np.float32)


@dataclass
class Scene:
    """Everything a loader read from one file.

    Attributes
    ----------
    path : str
    meshes : list of Mesh
    skeletons : list of Skeleton
    times : (T,) float64
        The asset's sample times (USD time codes, glTF seconds); ``[0.]`` for static assets.
    time_codes_per_second : float
        Frames per second of ``times`` (1 for glTF, whose times are seconds).
    up_axis : str
        "Y" or "Z": the up axis of world space (``space="world"``).
    meters_per_unit : float
        Metres per length unit of every space (points, velocities per second); results are
        never rescaled by it.
    clips : list of str
        Animation clip names available (glTF); the loaded one is ``clip``.
    frame_rate : float or None
        The output frame rate the file asks for (:func:`dqskin.times.frame_rate`): 24 for glTF,
        whose times are seconds; None: ``time_codes_per_second`` (the times are frames: USD
        time codes, BVH frames). A reader of another format sets its file's own rate here.

    Each mesh's ``skeleton`` indexes ``skeletons`` (checked on construction); each skeleton carries
    the animation that drives it (``Skeleton.animation``; :attr:`animations` lists them). Skinners
    are uploaded once per mesh, device and centers-of-rotation settings (:meth:`skinner`); after
    replacing a mesh, call :meth:`invalidate`.
    """

    path: str
    meshes: list
    skeletons: list
    times: np.ndarray
    time_codes_per_second: float = 1.0
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    clips: list = field(default_factory=list)
    clip: str | None = None
    frame_rate: float | None = None
    _skinners: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        for m in self.meshes:
            if not 0 <= m.skeleton < len(self.skeletons):
                raise InputError(f"{self.path}: mesh {m.name!r}: skeleton {m.skeleton} out of "
                                 f"range for {len(self.skeletons)} skeletons")

    @property
    def animations(self) -> list:
        """The animation (or None: rest pose) of each skeleton, in ``skeletons`` order (a new
        list: set ``Skeleton.animation`` to change one)."""
        return [s.animation for s in self.skeletons]

    def invalidate(self, name: str | None = None) -> None:
        """Drop the uploaded skinner of mesh ``name`` (every mesh when None)."""
        for key in [k for k in list(self._skinners) if name is None or k[0] == name
                    or (k[0] == "meshes" and name in k[1])]:  # batches (dqskin.crowd) too
            self._skinners.pop(key, None)  # (list, pop: other threads may skin meanwhile)

    def skinner(self, mesh: Mesh, device: Device = None, cor: CorOptions | None = None) -> Skinner:
        """The :class:`dqskin.Skinner` of ``mesh`` on ``device`` with the centers-of-rotation
        settings ``cor`` (default :class:`~dqskin.options.CorOptions`), uploaded once and
        reused."""
        from ._warp import resolve_device
        from .skinning import Skinner
        cor = CorOptions() if cor is None else cor
        key = (mesh.name, str(resolve_device(device)), cor)
        sk = self._skinners.get(key)
        if sk is None:
            sk = Skinner(mesh.points, mesh.joint_indices, mesh.joint_weights,
                         geom_bind_transform=mesh.geom_bind_transform,
                         blend_weights=mesh.blend_or_default(), faces=mesh.faces,
                         device=device, cor=cor)
            self._skinners[key] = sk
        return sk

    def mesh(self, name: str) -> Mesh:
        """The mesh called ``name`` (KeyError naming the known meshes)."""
        for m in self.meshes:
            if m.name == name:
                return m
        raise UnknownNameError(f"{self.path}: no mesh {name!r}; meshes: "
                               f"{[m.name for m in self.meshes]}")

    def local_transforms(self, times: npt.ArrayLike, skeleton: int = 0, *,
                         interp: Interpolation = SkinOptions.interp) -> np.ndarray:
        """(F, J, 4, 4) float64 local joint transforms of one skeleton at ``times``.

        ``interp`` is :data:`dqskin.options.INTERPOLATIONS`: "trs" is the asset's own sampler
        (what glTF and USD players show); the others interpolate the keys with dual quaternions.
        ValueError naming the skeleton, time and joint when a transform is NaN, infinite or
        beyond float32 range.
        """
        skel: Skeleton = self.skeletons[skeleton]
        anim = skel.animation
        t = check_times(times)
        if anim is None:
            return np.broadcast_to(skel.rest_transforms, (t.shape[0],) + skel.rest_transforms.shape)
        local = anim.local_transforms(t) if interp == "trs" else sample(anim, t, interp)
        return check_transforms(f"{self.path}: {skel.name or 'skeleton'}: joint transforms", local,
                                skel.joint_names, t)

    def skinning_transforms(self, times: npt.ArrayLike, skeleton: int = 0, *, device: Device = None,
                            interp: Interpolation = SkinOptions.interp) -> np.ndarray:
        """(F, J, 4, 4) float32 bind-relative transforms of one skeleton at ``times``."""
        return self.skeletons[skeleton].skinning_transforms(
            self.local_transforms(times, skeleton, interp=interp), device=device)

    def skin(self, times: npt.ArrayLike | None = None, method: Method | None = None, *,
             options: SkinOptions | None = None, **changes: Any) -> SkinnedFrames:
        """Skin every mesh at ``times`` (:func:`dqskin.pipeline.skin_scene`, the one skinning
        path of the engine).

        Parameters
        ----------
        times : (F,) float, optional
            Scene time unit; default ``self.times``.
        method : {"lbs", "dqs", "blend", "cor"} or None
            Shorthand for ``options.method``; None keeps it (default: each mesh's own
            ``skinning_method``). "cor" computes each mesh's centers of rotation from its faces
            on first use (:mod:`dqskin.cor`, cached on disk).
        options : dqskin.SkinOptions, optional
            What to skin and how (default: :class:`~dqskin.options.SkinOptions` defaults).
        **changes
            Fields of :class:`~dqskin.options.SkinOptions` replacing those of ``options``
            (``normals=True``, ``space="skeleton"``, ``sign_reference=...``, ...).

        Returns
        -------
        SkinnedFrames
            Meshes without normals (tangents) are left out of ``normals`` (``tangents``);
            velocities are in length units per second.

        Raises
        ------
        dqskin.errors.InputError
            An option out of range, or joint transforms or velocities that are not finite.
        """
        opts = SkinOptions.build(options, **changes)
        if method is not None:
            opts = opts.replace(method=method)
        from .pipeline import skin_scene
        return skin_scene(self, self.times if times is None else times, opts, self._skinners)

    def skin_chunks(self, times: npt.ArrayLike, chunk: "int | list[int]", *,
                    buffers: KB.BufferPool | None = None, options: SkinOptions | None = None,
                    **changes: Any) -> Generator[tuple[slice, SkinnedFrames], None, None]:
        """Yield ``(slice, SkinnedFrames)`` for consecutive chunks of ``chunk`` frames (or of
        the sizes in a list ``chunk``, which must add up to the frame count), so memory stays
        bounded; ``options`` and ``changes`` as for :meth:`skin`.

        The next chunk is skinned on a worker thread while the caller consumes the current one
        (Warp launches and NumPy release the GIL, so the two overlap). The chunks' large arrays
        are reused from one chunk to the next once the caller has dropped them
        (:func:`dqskin.kernels.buffers.reusing`): results the caller keeps stay its own. The
        skeletons' poses are sampled for several chunks at once
        (:func:`dqskin.pipeline.chunk_skinner`). ``buffers``: the
        :class:`~dqskin.kernels.buffers.BufferPool` to take them from and give them back to
        (e.g. one per process across many calls); default, one of this call's.
        """
        from .kernels import buffers as KB
        from .pipeline import chunk_skinner
        t = check_times(times)
        sizes = list(chunk) if isinstance(chunk, (list, tuple)) else [chunk]
        if not sizes or any(isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1
                            for n in sizes):
            raise InputError(Param("chunk", chunk), ": expected whole numbers of frames >= 1")
        if isinstance(chunk, (list, tuple)):
            ends = np.cumsum(chunk, dtype=np.int64)
            if ends[-1] != len(t):
                raise InputError(Param("chunk", chunk), f": the sizes add up to {ends[-1]} "
                                 f"frames, not {len(t)}")
            slices = [slice(int(e - n), int(e)) for n, e in zip(chunk, ends)]
        else:
            slices = [slice(lo, min(lo + chunk, len(t))) for lo in range(0, len(t), chunk)]
        pool = KB.BufferPool() if buffers is None else buffers
        opts = SkinOptions.build(options, **changes)
        if not slices:  # no times
            return
        skin_chunk = chunk_skinner(self, t, slices, opts, self._skinners)

        def skin(k: int) -> SkinnedFrames:
            with KB.reusing(pool):
                return skin_chunk(k)

        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="dqskin-skin") as ex:
            fut = ex.submit(skin, 0)
            for k, sl in enumerate(slices):
                res = fut.result()
                if k + 1 < len(slices):
                    fut = ex.submit(skin, k + 1)
                yield sl, res
                del res  # the caller's to keep or drop: its buffers can serve the next chunk
