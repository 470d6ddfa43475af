"""Write skinned results as a USD point cache: a new stage with time-sampled points, no skinning.

The source stage (never modified) is flattened into one new layer, so topology, UVs, materials,
other primvars and transforms are kept as composed. Every skinned prim then gets time-sampled
``points``, ``extent`` and, when given, ``normals`` and ``velocities``; skinned prims without
points get time-sampled ``xformOp:transform`` (engine-skinned); every skeleton binding is
removed (``SkelBindingAPI``, ``skel:*`` and ``primvars:skel:*`` properties, ``SkelRoot`` retyped
``Xform``) so nothing is skinned twice, and stale ``extentsHint`` on the skinned prims' ancestors
is dropped. ``Skeleton`` prims are kept but deactivated (unbound from their animation they would
be drawn in the rest pose); ``SkelAnimation`` prims stay as inert data.
"""

import os
import tempfile

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

from .usd import load_rigid_prims, rigid_transforms

__all__ = ["CACHE_EXTENSIONS", "write_usd_cache"]

CACHE_EXTENSIONS = (".usda", ".usdc", ".usd")
"""Extensions :func:`write_usd_cache` writes (``.usd`` is binary crate)."""

_SKEL_API = "SkelBindingAPI"


def _frames(name, what, a, frames, count=None):
    """Check ``a`` is ``(frames, count, 3)`` finite; float32."""
    x = np.asarray(a, dtype=np.float32)
    if x.ndim != 3 or x.shape[0] != frames or x.shape[2] != 3 or (
            count is not None and x.shape[1] != count):
        want = f"({frames}, {'N' if count is None else count}, 3)"
        raise ValueError(f"{what}[{name!r}]: expected shape {want}, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what}[{name!r}]: NaN or infinite values")
    return x


def _same_file(a, b):
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def _source_files(stage, source_path):
    """Every file the source stage reads (root, sublayers, references, the usdz package)."""
    files = {source_path}
    for layer in stage.GetUsedLayers():
        real = layer.realPath
        if real:
            files.add(real.split("[", 1)[0])
    return files


def _remove_skel_binding(layer):
    """Strip SkelBindingAPI, skel properties and SkelRoot types; deactivate Skeletons."""
    specs = []
    layer.Traverse(Sdf.Path.absoluteRootPath,
                   lambda p: specs.append(p) if p.IsPrimPath() else None)
    for path in specs:
        spec = layer.GetPrimAtPath(path)
        if spec.typeName == "SkelRoot":
            spec.typeName = "Xform"
        elif spec.typeName == "Skeleton":
            spec.active = False  # unbound, it would be drawn in its rest pose
        if spec.HasInfo("apiSchemas"):
            keep = [s for s in spec.GetInfo("apiSchemas").ApplyOperations([]) if s != _SKEL_API]
            if keep:
                spec.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(keep))
            else:
                spec.ClearInfo("apiSchemas")
        for prop in list(spec.properties):
            if prop.name.startswith(("skel:", "primvars:skel:")):
                spec.RemoveProperty(prop)


def _attribute(layer, prim_spec, name, type_name, variability=Sdf.VariabilityVarying, **info):
    """The attribute spec ``name`` on ``prim_spec`` with no time samples (created if needed)."""
    spec = layer.GetAttributeAtPath(prim_spec.path.AppendProperty(name))
    if spec is None:
        spec = Sdf.AttributeSpec(prim_spec, name, type_name, variability)
    if spec.HasInfo("timeSamples"):
        spec.ClearInfo("timeSamples")
    for key, value in info.items():
        spec.SetInfo(key, value)
    return spec


def _set_samples(layer, attr_path, times, frames, vt_type):
    for t, value in zip(times, frames):
        layer.SetTimeSample(attr_path, float(t), vt_type.FromNumpy(np.ascontiguousarray(value)))


def _rest_widths(prim):
    """Authored widths of curves or points (None for other prims)."""
    for schema in (UsdGeom.Curves, UsdGeom.Points):
        if prim.IsA(schema):
            attr = schema(prim).GetWidthsAttr()
            value = attr.Get(Usd.TimeCode.Default()) if attr.HasAuthoredValue() else None
            return value if value is not None else attr.Get(Usd.TimeCode.EarliestTime())
    return None


def _prim_spec(layer, path):
    """The prim spec at ``path``, created as an ``over`` (and de-instanced) if absent."""
    sdf_path = Sdf.Path(path)
    for anc in sdf_path.GetPrefixes()[:-1]:
        spec = layer.GetPrimAtPath(anc)
        if spec is not None and spec.HasInfo("instanceable") and spec.instanceable:
            spec.instanceable = False
    return layer.GetPrimAtPath(sdf_path) or Sdf.CreatePrimInLayer(layer, sdf_path)


def write_usd_cache(scene, out_path, times, points, normals=None, *, velocities=None,
                    source_path=None, method=None, device=None):
    """Write skinned points (and normals, velocities) as a new USD stage.

    Parameters
    ----------
    scene : Scene
        What :func:`dqskin.usd.load_usd` returned; its metadata (``time_codes_per_second``,
        ``up_axis``, ``meters_per_unit``) is written and its meshes' rest data checks the
        shapes.
    out_path : str or os.PathLike
        ``.usda``, ``.usdc`` or ``.usd``. Written atomically (temporary file in the same folder,
        then ``os.replace``). Must not be the source file or any layer it reads.
    times : (F,) float
        USD time codes of the frames; ``startTimeCode``/``endTimeCode`` become their min/max.
    points : dict str → (F, V, 3) float
        Per mesh (prim path, ``Mesh.name``): points in the prim's own space, as
        :meth:`Scene.skin` returns them. Meshes left out keep their rest points (unbound too).
    normals : dict str → (F, N, 3) float, optional
        Skinned normals, ``N`` = the mesh's rest normal count; written to the attribute the
        normals were read from (``primvars:normals`` loses its ``:indices``, the values being
        flattened), keeping its interpolation.
    velocities : dict str → (F, V, 3) float, optional
        Point velocities in prim-space units per second, written to ``velocities``.
    source_path : str or os.PathLike, optional
        The stage to copy; ``scene.path`` by default.
    method : {"lbs", "dqs"} or None
        Skinning method for the skinned prims without points (``Sphere``, ``Cube``, ...), baked
        as ``xformOp:transform`` samples as ``UsdSkel.BakeSkinning`` does; None uses each prim's
        own. Pass the method that produced ``points``.
    device : str, optional
        Warp device for those transforms.

    Returns
    -------
    str
        ``out_path``.

    Raises
    ------
    ValueError
        Unsupported extension, missing output folder, output equal to an input file, unknown
        mesh names, or arrays whose shape disagrees with ``times`` and the mesh.
    """
    out = os.fspath(out_path)
    src = os.fspath(scene.path if source_path is None else source_path)
    ext = os.path.splitext(out)[1].lower()
    if ext not in CACHE_EXTENSIONS:
        raise ValueError(f"{out}: cannot write extension {ext!r}; use one of "
                         f"{', '.join(CACHE_EXTENSIONS)}")
    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        raise ValueError(f"{out}: folder {folder} does not exist")
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
        raise ValueError(f"times: expected a non-empty 1-D array of finite time codes, "
                         f"got shape {t.shape}")
    F = t.shape[0]
    meshes = {m.name: m for m in scene.meshes}
    normals, velocities = normals or {}, velocities or {}
    for what, d in (("points", points), ("normals", normals), ("velocities", velocities)):
        unknown = sorted(set(d) - set(meshes))
        if unknown:
            raise ValueError(f"{what}: no mesh {unknown[0]!r} in {scene.path}; meshes: "
                             f"{sorted(meshes)}")
    pts = {n: _frames(n, "points", p, F, meshes[n].points.shape[0]) for n, p in points.items()}
    nrm = {}
    for n, v in normals.items():
        if meshes[n].normals is None:
            raise ValueError(f"normals[{n!r}]: the mesh has no rest normals to replace")
        nrm[n] = _frames(n, "normals", v, F, meshes[n].normals.shape[0])
    vel = {n: _frames(n, "velocities", v, F, meshes[n].points.shape[0])
           for n, v in velocities.items()}

    try:
        stage = Usd.Stage.Open(src, Usd.Stage.LoadAll)
    except Tf.ErrorException:
        stage = None
    if stage is None:
        raise ValueError(f"{src}: cannot open the source stage")
    if os.path.exists(out) and any(_same_file(out, f) for f in _source_files(stage, src)
                                   if os.path.exists(f)):
        raise ValueError(f"{out}: refusing to overwrite an input of {src}")

    rigid = [(r.name, rigid_transforms(scene, r, t, method, device=device))
             for r in load_rigid_prims(scene)]
    layer = stage.Flatten()
    with Sdf.ChangeBlock():
        _remove_skel_binding(layer)
        for name in sorted(set(pts) | set(nrm) | set(vel)):
            prim = stage.GetPrimAtPath(name)
            if not prim or not UsdGeom.PointBased(prim):
                raise ValueError(f"{src}: {name}: not a point-based prim")
            spec = _prim_spec(layer, name)
            for anc in Sdf.Path(name).GetPrefixes()[:-1]:
                anc_spec = layer.GetPrimAtPath(anc)
                if anc_spec is not None and "extentsHint" in anc_spec.properties:
                    anc_spec.RemoveProperty(anc_spec.properties["extentsHint"])
            if name in pts:
                p = pts[name]
                a = _attribute(layer, spec, "points", Sdf.ValueTypeNames.Point3fArray)
                _set_samples(layer, a.path, t, p, Vt.Vec3fArray)
                by_axis = np.ascontiguousarray(p.transpose(0, 2, 1))  # fast reductions
                lo, hi = by_axis.min(axis=2), by_axis.max(axis=2)
                w = _rest_widths(prim)
                if w is not None and len(w):
                    pad = 0.5 * float(np.max(np.asarray(w)))
                    lo, hi = lo - pad, hi + pad
                a = _attribute(layer, spec, "extent", Sdf.ValueTypeNames.Float3Array)
                _set_samples(layer, a.path, t, np.stack([lo, hi], axis=1), Vt.Vec3fArray)
            if name in nrm:
                pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
                if pv and pv.HasAuthoredValue():
                    attr = "primvars:normals"
                    idx = layer.GetAttributeAtPath(spec.path.AppendProperty(attr + ":indices"))
                    if idx is not None:
                        spec.RemoveProperty(idx)
                    interp = pv.GetInterpolation()
                else:
                    attr, interp = "normals", UsdGeom.PointBased(prim).GetNormalsInterpolation()
                a = _attribute(layer, spec, attr, Sdf.ValueTypeNames.Normal3fArray,
                               interpolation=interp)
                _set_samples(layer, a.path, t, nrm[name], Vt.Vec3fArray)
            if name in vel:
                a = _attribute(layer, spec, "velocities", Sdf.ValueTypeNames.Vector3fArray)
                _set_samples(layer, a.path, t, vel[name], Vt.Vec3fArray)
        for name, xf in rigid:
            spec = _prim_spec(layer, name)
            a = _attribute(layer, spec, "xformOp:transform", Sdf.ValueTypeNames.Matrix4d)
            for ti, m in zip(t, xf):
                layer.SetTimeSample(a.path, float(ti), Gf.Matrix4d(m.T.tolist()))
            order = _attribute(layer, spec, "xformOpOrder", Sdf.ValueTypeNames.TokenArray,
                               Sdf.VariabilityUniform)
            order.default = Vt.TokenArray(["xformOp:transform"])
        layer.timeCodesPerSecond = float(scene.time_codes_per_second)
        layer.framesPerSecond = float(scene.time_codes_per_second)
        layer.startTimeCode, layer.endTimeCode = float(t.min()), float(t.max())
        root = layer.pseudoRoot
        root.SetInfo(UsdGeom.Tokens.upAxis, str(scene.up_axis))
        root.SetInfo(UsdGeom.Tokens.metersPerUnit, float(scene.meters_per_unit))
        layer.documentation = f"dqskin point cache of {src}"

    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(out) + ".", suffix=ext, dir=folder)
    os.close(fd)
    try:
        args = {"format": "usdc"} if ext == ".usd" else {}
        if not layer.Export(tmp, args=args):
            raise ValueError(f"{out}: USD could not write the cache")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out
