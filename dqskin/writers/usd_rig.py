"""A scene written as a UsdSkel rig: what usd-core (and Blender, for LBS) skin themselves.

:func:`write_rig` writes one ``SkelRoot`` (``/Root``) holding, per skeleton, a ``Skeleton`` with
its joints (hierarchy paths), ``bindTransforms`` and ``restTransforms``, a ``SkelAnimation`` child
with the animation (``translations``, ``rotations``, ``scales`` from
``UsdSkelAnimation::SetTransforms``) sampled at every frame of the output frame rate
(:mod:`dqskin.times`), whole frame numbers as time codes, bound through
``skel:animationSource``; and every mesh as a ``Mesh`` (with its rest normals) with
``SkelBindingAPI``: ``skel:skeleton``, ``primvars:skel:jointIndices`` and ``jointWeights``
(vertex interpolation, ``elementSize`` K), ``primvars:skel:geomBindTransform`` and
``primvars:skel:skinningMethod`` (``classicLinear`` for "lbs", ``dualQuaternion`` for "dqs";
a "blend" mesh: the one nearer its mean blend weight, and its per-vertex weights as
``primvars:dqskin:blendWeights``, which dqskin reads back as the "blend" method).
A skeleton placed in the world (in a USD scene its prim's local-to-world, time-sampled when
animated: a converter's ``Z_UP`` group, say) is written with its meshes under an ``Xform``
(``/Root/Placement``) whose ``xformOp:transform`` is that placement: UsdSkel takes skinned
points to the world by the skeleton's transform, and Blender's importer, which ignores a skinned
mesh's own transform, sees the mesh in its skeleton's space. Matrices are transposed here, at
the USD boundary (Gf is row-vector). Joint names become valid USD identifiers
(``Tf.MakeValidIdentifier``, made unique among siblings).

The file is written atomically (:mod:`.atomic`); ``.usd`` is crate, ``.usda`` text.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError, Param
from ..files.atomic import atomic_path
from ..readers import gltf
from ..readers.usd_xform import LocalToWorld, XformChain
from ..scene import Scene
from .usd_cache import check_not_input, export_layer

if TYPE_CHECKING:
    from pxr import Usd, UsdGeom, Vt

    from ..scene import Mesh
    from ..skeleton import Skeleton

__all__ = ["RIG_SUFFIXES", "joint_paths", "rig_stage", "write_rig"]

RIG_SUFFIXES = (".usd", ".usda", ".usdc")

_METHODS = {"lbs": "classicLinear", "dqs": "dualQuaternion"}


def joint_paths(joint_names: Sequence[str], parents: np.ndarray) -> list[str]:
    """UsdSkel joint paths (``"Hips/Spine/Chest"``) from names and parents: each name made a
    valid identifier, unique among its siblings."""
    from pxr import Tf
    paths: list[str] = []
    taken: dict[int, set[str]] = {}
    for name, p in zip(joint_names, parents):
        base = Tf.MakeValidIdentifier(str(name).split("/")[-1]) or "joint"
        prefix = paths[p] + "/" if p >= 0 else ""
        used = taken.setdefault(int(p), set())
        leaf, k = base, 1
        while leaf in used:
            leaf, k = f"{base}_{k}", k + 1
        used.add(leaf)
        paths.append(prefix + leaf)
    return paths


def _prim_name(name: str, taken: set[str]) -> str:
    from pxr import Tf
    base = Tf.MakeValidIdentifier(str(name).strip("/").split("/")[-1]) or "Mesh"
    leaf, k = base, 1
    while leaf in taken:
        leaf, k = f"{base}_{k}", k + 1
    taken.add(leaf)
    return leaf


def _matrices(m: np.ndarray) -> Vt.Matrix4dArray:
    """(N, 4, 4) column-vector float64 → ``Vt.Matrix4dArray`` (row-vector, transposed)."""
    from pxr import Vt
    return Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(np.transpose(m, (0, 2, 1))))


def _source_stage(scene: Scene) -> Usd.Stage | None:
    """The USD stage ``scene`` was read from, or None (glTF, BVH, a missing file)."""
    from pxr import Usd

    from ..readers import usd
    if Path(scene.path).suffix.lower() not in usd.SUFFIXES or not Path(scene.path).is_file():
        return None
    return Usd.Stage.Open(str(scene.path))


def _skeleton_to_world(scene: Scene, skel: Skeleton, source: Usd.Stage | None,
                       times: np.ndarray) -> np.ndarray:
    """(F, 4, 4) skeleton space → world at ``times``: the source Skeleton prim's
    local-to-world (its xform ops and its ancestors', time-sampled ones evaluated at every time)
    for a USD scene, else the skeleton's ``world_transform`` (identity for glTF and BVH)."""
    prim = source.GetPrimAtPath(skel.name) if source is not None and skel.name and \
        str(skel.name).startswith("/") else None
    if prim:
        track = XformChain(LocalToWorld().ops(prim), (), name=f"{scene.path}: {skel.name}")
        return track.at(times)
    return np.broadcast_to(np.asarray(skel.world_transform, np.float64), (len(times), 4, 4))


def _author_placement(xformable: Usd.Prim, world: np.ndarray, codes: np.ndarray) -> None:
    """Give ``xformable`` the transform ``world`` (F, 4, 4) at time ``codes``: one value when
    constant, else a time sample per code."""
    from pxr import Gf, Usd, UsdGeom
    op = UsdGeom.Xformable(xformable).AddTransformOp()
    if np.allclose(world, world[:1], rtol=0, atol=1e-12):
        op.Set(Gf.Matrix4d(world[0].T.tolist()))
        return
    for m, t in zip(world, codes):
        op.Set(Gf.Matrix4d(m.T.tolist()), Usd.TimeCode(float(t)))


def _author_normals(mesh: UsdGeom.Mesh, m: Mesh, corners: int) -> None:
    """The rest normals of ``m`` on ``mesh``: per vertex, or per face corner (``faceVarying``)
    when each of ``corners`` face-vertex indices has its own; none otherwise."""
    from pxr import UsdGeom, Vt
    if m.normals is None:
        return
    n = np.asarray(m.normals, np.float32).reshape(-1, 3)
    if m.normal_vertex is None and len(n) == len(m.points):
        interp = UsdGeom.Tokens.vertex
    elif m.normal_vertex is not None and len(n) == corners and m.face_vertex_indices is not None \
            and np.array_equal(np.asarray(m.normal_vertex), np.asarray(m.face_vertex_indices)):
        interp = UsdGeom.Tokens.faceVarying
    else:
        return
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(n))
    mesh.SetNormalsInterpolation(interp)


def write_rig(scene: Scene, out: str | os.PathLike, *, force: bool = False,
              fps: float | None = None) -> str:
    """Write ``scene`` as a UsdSkel rig at ``out`` (``.usd/.usda/.usdc``).

    Parameters
    ----------
    scene : dqskin.Scene
        Skeletons with their animations, sampled at every frame of the output frame rate
        (:func:`dqskin.times.frame_rate`: a USD scene's own time codes, a BVH's frames, glTF
        seconds × 24), whole frame numbers being the rig's time codes; and meshes with their
        influences.
    out : path
    force : bool
        Replace an existing file (otherwise the name is claimed exclusively); never a file the
        scene was read from (a USD scene's layers: InputError).
    fps : float, optional
        Output frame rate (default :func:`dqskin.times.frame_rate`).

    Returns
    -------
    str
        A one-line summary.
    """
    from ..times import FRAMES_CEILING, frame_rate, select
    out = Path(out)
    if out.suffix.lower() not in RIG_SUFFIXES:
        raise InputError(Param("out", out), f": a rig is written as {'/'.join(RIG_SUFFIXES)}")
    sel = select(scene.times, scene.time_codes_per_second, fps=fps, rate=frame_rate(scene),
                 max_frames=FRAMES_CEILING)
    source = _source_stage(scene)
    if source is not None:
        check_not_input(out, source, scene.path)
    stage, _ = _rig_stage(scene, sel.times, sel.frames, sel.rate, source)
    stage.GetRootLayer().documentation = f"dqskin rig of {scene.path}"
    claim = atomic_path(out, overwrite=force)
    try:
        export_layer(stage.GetRootLayer(), claim, out)
        claim.commit()
    except BaseException:
        claim.discard()
        raise
    n = len(scene.meshes)
    joints = sum(s.joint_count for s in scene.skeletons)
    return (f"wrote {out}: UsdSkel rig, {n} mesh{'es' if n != 1 else ''}, {joints} joints, "
            f"{len(sel.times)} animation samples at {sel.rate:g} fps")


def rig_stage(scene: Scene, times: np.ndarray, codes: np.ndarray,
              rate: float) -> tuple[Usd.Stage, dict[str, str]]:
    """``scene`` as a UsdSkel rig in a new in-memory stage (see the module docstring).

    Parameters
    ----------
    scene : dqskin.Scene
    times : (F,) float64
        Asset times (``scene.times`` unit) the animations are sampled at.
    codes : (F,) float64
        The rig's time code of each of ``times``.
    rate : float
        The rig's ``timeCodesPerSecond`` and ``framesPerSecond``.

    Returns
    -------
    (Usd.Stage, dict)
        The stage, and each mesh's prim path by ``Mesh.name``.
    """
    return _rig_stage(scene, times, codes, rate, _source_stage(scene))


def _rig_stage(scene: Scene, times: np.ndarray, codes: np.ndarray, rate: float,
               source: Usd.Stage | None) -> tuple[Usd.Stage, dict[str, str]]:
    """:func:`rig_stage` with the stage ``scene`` was read from (:func:`_source_stage`)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    from ..readers import format_of
    from ..readers.usd import BLEND_WEIGHTS
    times = np.asarray(times, np.float64)
    codes = np.asarray(codes, np.float64)
    stage = Usd.Stage.CreateInMemory()
    stage.SetStartTimeCode(float(codes[0]))
    stage.SetEndTimeCode(float(codes[-1]))
    stage.SetTimeCodesPerSecond(float(rate))
    stage.SetFramesPerSecond(float(rate))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if scene.up_axis == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, float(scene.meters_per_unit))
    root = UsdSkel.Root.Define(stage, "/Root")
    stage.SetDefaultPrim(root.GetPrim())
    taken = {"Skeleton"}
    skel_paths, groups = [], []  # per skeleton: its path, the prim holding it and its meshes
    for s, skel in enumerate(scene.skeletons):
        suffix = f"_{s}" if s else ""
        group = Sdf.Path("/Root")
        world = _skeleton_to_world(scene, skel, source, times)
        if not np.allclose(world, np.eye(4), rtol=0, atol=1e-12):
            group = group.AppendChild("Placement" + suffix)
            taken.add(group.name)
            _author_placement(UsdGeom.Xform.Define(stage, group), world, codes)
        path = group.AppendChild("Skeleton" + suffix)
        taken.add(path.name)
        us = UsdSkel.Skeleton.Define(stage, path)
        joints = Vt.TokenArray(joint_paths(skel.joint_names, skel.parents))
        us.CreateJointsAttr(joints)
        us.CreateBindTransformsAttr(_matrices(skel.bind_transforms))
        us.CreateRestTransformsAttr(_matrices(skel.rest_transforms))
        skel_paths.append(path)
        groups.append(group)
        if skel.animation is None:
            continue
        anim = UsdSkel.Animation.Define(stage, path.AppendChild("Animation"))
        anim.CreateJointsAttr(joints)
        local = scene.local_transforms(times, s)
        for f, t in enumerate(codes):
            anim.SetTransforms(_matrices(local[f]), Usd.TimeCode(float(t)))
        UsdSkel.BindingAPI.Apply(us.GetPrim()).CreateAnimationSourceRel().SetTargets(
            [anim.GetPath()])
    paths: dict[str, str] = {}
    top_left = format_of(scene.path) is gltf  # glTF UVs: origin top-left; USD's bottom-left
    for m in scene.meshes:
        mesh = UsdGeom.Mesh.Define(stage, groups[m.skeleton].AppendChild(_prim_name(m.name,
                                                                                    taken)))
        paths[m.name] = str(mesh.GetPath())
        pts = np.asarray(m.points, np.float32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        if m.face_vertex_counts is not None and m.face_vertex_indices is not None:
            counts, indices = m.face_vertex_counts, m.face_vertex_indices
        else:
            counts = np.full(len(m.faces), 3, np.int32)
            indices = np.asarray(m.faces, np.int32).ravel()
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.asarray(counts, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(indices, np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        if len(pts):
            mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, pts.min(0))),
                                                 Gf.Vec3f(*map(float, pts.max(0)))]))
        st_interp = None if m.uvs is None else UsdGeom.Tokens.vertex if len(m.uvs) == len(pts) \
            else UsdGeom.Tokens.faceVarying if len(m.uvs) == len(indices) else None
        if st_interp is not None:  # (per vertex, or per face corner)
            st = np.array(m.uvs, np.float32).reshape(-1, 2)
            if top_left:
                st[:, 1] = 1.0 - st[:, 1]
            UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
                "st", Sdf.ValueTypeNames.TexCoord2fArray, st_interp).Set(
                Vt.Vec2fArray.FromNumpy(st))
        _author_normals(mesh, m, len(indices))
        bind = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        bind.CreateSkeletonRel().SetTargets([skel_paths[m.skeleton]])
        idx = np.asarray(m.joint_indices, np.int32)
        wts = np.asarray(m.joint_weights, np.float32)
        K = idx.shape[1] if idx.ndim == 2 else 1
        bind.CreateJointIndicesPrimvar(False, K).Set(Vt.IntArray.FromNumpy(idx.ravel()))
        bind.CreateJointWeightsPrimvar(False, K).Set(Vt.FloatArray.FromNumpy(wts.ravel()))
        bind.CreateGeomBindTransformAttr(Gf.Matrix4d(np.asarray(m.geom_bind_transform,
                                                                np.float64).T.tolist()))
        if m.skinning_method in _METHODS:
            bind.CreateSkinningMethodAttr(_METHODS[m.skinning_method])
        elif m.skinning_method == "blend":  # UsdSkel's nearest method, and the weights
            b = m.blend_or_default()
            bind.CreateSkinningMethodAttr(_METHODS["dqs" if b.mean() >= 0.5 else "lbs"])
            UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
                BLEND_WEIGHTS, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).Set(
                Vt.FloatArray.FromNumpy(b))
    return stage, paths
