"""The loaded scene: skinned meshes, their skeletons and animations, skinned per frame on a device.

Loaders (:mod:`dqskin.usd`, :mod:`dqskin.gltf`) fill these containers; :meth:`Scene.skin` runs the
same engine for every format: animation → local transforms → forward kinematics (dual
quaternions) → skinning transforms → per-vertex skinning → output space.
"""

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .skeleton import Skeleton
from ._warp import resolve_device
from .skinning import Skinner

__all__ = ["Animation", "Mesh", "Scene"]


class Animation:
    """Keyed local joint transforms of one skeleton (format loaders subclass it).

    Attributes
    ----------
    key_times : (K,) float64
        Times of the keys, in the scene's time unit (USD time codes, glTF seconds).
    """

    key_times = np.zeros(0)

    def local_transforms(self, times):
        """Parent-relative joint transforms at ``times``.

        Parameters
        ----------
        times : (F,) float

        Returns
        -------
        (F, J, 4, 4) float64, column-vector convention.
        """
        raise NotImplementedError


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
    output_transforms : callable or None
        ``f(times) -> (F, 4, 4)``: skeleton space → the space results are reported in (USD: the
        prim's local space; glTF: world). Identity when None.
    rest_points_at : callable or None
        ``f(times) -> (F, V, 3)`` rest points with blend shapes applied; ``rest_normals_at`` the
        same for normals.
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
    output_transforms: Callable | None = None
    rest_points_at: Callable | None = None
    rest_normals_at: Callable | None = None
    face_vertex_counts: np.ndarray | None = None
    face_vertex_indices: np.ndarray | None = None
    uvs: np.ndarray | None = None
    blend_weights: np.ndarray | None = None

    def blend_or_default(self):
        """(V,) float32 blend weights, ½ where none were given."""
        if self.blend_weights is not None:
            return np.asarray(self.blend_weights, np.float32)
        return np.full(len(self.points), 0.5, np.float32)


@dataclass
class Scene:
    """Everything a loader read from one file.

    Attributes
    ----------
    path : str
    meshes : list of Mesh
    skeletons : list of Skeleton
    animations : list of (Animation or None)
        One per skeleton; None poses the skeleton at rest.
    times : (T,) float64
        The asset's sample times (USD time codes, glTF seconds); ``[0.]`` for static assets.
    time_codes_per_second : float
        Frames per second of ``times`` (1 for glTF, whose times are seconds).
    up_axis : str
    meters_per_unit : float
    clips : list of str
        Animation clip names available (glTF); the loaded one is ``clip``.
    """

    path: str
    meshes: list
    skeletons: list
    animations: list
    times: np.ndarray
    time_codes_per_second: float = 1.0
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    clips: list = field(default_factory=list)
    clip: str | None = None
    _skinners: dict = field(default_factory=dict, repr=False, compare=False)

    def skinner(self, mesh, device=None):
        """The :class:`dqskin.Skinner` of ``mesh`` on ``device``, uploaded once and reused."""
        key = (mesh.name, str(resolve_device(device)))
        sk = self._skinners.get(key)
        if sk is None:
            sk = Skinner(mesh.points, mesh.joint_indices, mesh.joint_weights,
                         geom_bind_transform=mesh.geom_bind_transform,
                         blend_weights=mesh.blend_or_default(), device=device)
            self._skinners[key] = sk
        return sk

    def mesh(self, name):
        """The mesh called ``name`` (KeyError naming the known meshes)."""
        for m in self.meshes:
            if m.name == name:
                return m
        raise KeyError(f"{self.path}: no mesh {name!r}; meshes: {[m.name for m in self.meshes]}")

    def local_transforms(self, times, skeleton=0, *, interp="trs"):
        """(F, J, 4, 4) float64 local joint transforms of one skeleton at ``times``.

        ``interp`` is :data:`dqskin.motion.INTERPOLATIONS`: "trs" is the asset's own sampler
        (what glTF and USD players show); the others interpolate the keys with dual quaternions.
        """
        skel: Skeleton = self.skeletons[skeleton]
        anim = self.animations[skeleton]
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if anim is None:
            return np.broadcast_to(skel.rest_transforms, (t.shape[0],) + skel.rest_transforms.shape)
        if interp == "trs":
            return anim.local_transforms(t)
        from .motion import sample
        return sample(anim, t, interp)

    def skinning_transforms(self, times, skeleton=0, *, device=None, interp="trs"):
        """(F, J, 4, 4) float32 bind-relative transforms of one skeleton at ``times``."""
        return self.skeletons[skeleton].skinning_transforms(
            self.local_transforms(times, skeleton, interp=interp), device=device)

    def skin(self, times=None, method=None, *, device=None, normals=False, interp="trs"):
        """Skin every mesh at ``times``.

        Parameters
        ----------
        times : (F,) float, optional
            Default: ``self.times``.
        method : {"lbs", "dqs", "blend"} or None
            None uses each mesh's own ``skinning_method``.
        normals : bool
            Also return skinned normals.
        interp : str
            Joint interpolation between keys (:data:`dqskin.motion.INTERPOLATIONS`).

        Returns
        -------
        dict name → (F, V, 3) float32 points in each mesh's output space, and with ``normals`` a
        second dict name → (F, N, 3) float32 (meshes without normals omitted).
        """
        t = self.times if times is None else np.atleast_1d(np.asarray(times, dtype=np.float64))
        xforms = {}
        points, norms = {}, {}
        for m in self.meshes:
            if m.skeleton not in xforms:
                xforms[m.skeleton] = self.skinning_transforms(t, m.skeleton, device=device,
                                                              interp=interp)
            x = xforms[m.skeleton]
            meth = method or m.skinning_method
            sk = self.skinner(m, device)
            rest = None if m.rest_points_at is None else m.rest_points_at(t)
            out = None if m.output_transforms is None else np.asarray(m.output_transforms(t))
            points[m.name] = sk.skin(x, meth, points=rest, output_transforms=out)
            if normals and m.normals is not None:
                rn = m.normals if m.rest_normals_at is None else m.rest_normals_at(t)
                norms[m.name] = sk.skin_vectors(x, rn, meth, kind="normal",
                                                vector_vertex=m.normal_vertex, output_transforms=out)
        return (points, norms) if normals else points
