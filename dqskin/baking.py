"""Bake a skinned animation to files: the library behind ``dqskin skin``.

:func:`bake` skins a scene chunk by chunk (:meth:`dqskin.Scene.skin_chunks`, so memory stays
bounded) and hands each chunk to the writer the output's suffix selects: a USD point cache
(:mod:`dqskin.formats.usd_cache`), one ``.npz`` (:mod:`dqskin.formats.npz`) or one mesh file per
frame (:mod:`dqskin.formats.mesh_files`). Every output is written atomically
(:mod:`dqskin.formats.atomic`) and checked first (:mod:`dqskin.validation`).
"""

import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ._warp import Device
from .animation import Interpolation
from .formats import format_of, gltf, mesh_files, npz, usd, usd_cache
from .formats.atomic import atomic_path, check_interrupted, check_parent
from .scene import Scene
from .skinning import Method, SignReference
from .validation import check_skinned

__all__ = ["OUTPUT_SUFFIXES", "bake", "check_output", "output_kind"]

OUTPUT_SUFFIXES = usd_cache.CACHE_EXTENSIONS + npz.SUFFIXES + mesh_files.SUFFIXES
"""Suffixes :func:`bake` writes (mesh files take a per-frame pattern like ``f_{:04d}.obj``)."""


def output_kind(out: str | Path) -> str:
    """"usd", "npz" or "frames" for an output path; ValueError for anything else."""
    suffix = Path(str(out)).suffix.lower()
    if suffix in usd_cache.CACHE_EXTENSIONS:
        return "usd"
    if suffix in npz.SUFFIXES:
        return "npz"
    if suffix in mesh_files.SUFFIXES:
        return "frames"
    raise ValueError(f"--out {out}: unsupported output type; use "
                     f"{'/'.join(usd_cache.CACHE_EXTENSIONS)}, {'/'.join(npz.SUFFIXES)}, or a "
                     "per-frame pattern like out/frame_{:04d}.obj "
                     f"({' '.join(mesh_files.SUFFIXES)})")


def check_output(out: str | Path, inputs: list, force: bool) -> Path:
    """``out`` as a Path; ValueError if it is one of ``inputs``, FileExistsError if it exists
    and not ``force``, NotADirectoryError if a folder above it is a file."""
    out = Path(out)
    for src in inputs:
        if out.resolve() == Path(src).resolve():
            raise ValueError(f"{out}: refusing to overwrite the input")
    check_parent(out)
    if out.exists() and not force:
        raise FileExistsError(f"{out}: exists (use --force to overwrite)")
    return out


def _plural(n, word, plural=None):
    return f"{n} {word if n == 1 else plural or word + 's'}"


def bake(scene: Scene, out: str | Path, times: npt.ArrayLike | None = None, *,
         method: Method | None = None, interp: Interpolation = "trs", device: Device = None,
         chunk: int = 256, normals: bool = True, velocities: bool = True, force: bool = False,
         progress: bool = False, sign_reference: SignReference = "largest_weight") -> str:
    """Skin ``scene`` at ``times`` and write ``out``.

    Every chunk's joint transforms are checked as they are sampled
    (:meth:`dqskin.Scene.local_transforms`) and every skinned chunk before it is written
    (:func:`dqskin.validation.check_skinned`: no NaN or infinite result in any format); a refusal
    leaves nothing behind, because the output appears only when complete
    (:mod:`dqskin.formats.atomic`); without ``force`` its name is claimed exclusively, so of two
    runs writing the same file the one finishing second fails.

    Parameters
    ----------
    scene : dqskin.Scene
    out : str or Path
        ``.usd/.usda/.usdc`` (USD input only: a point cache of the source stage with points,
        extent, and normals and velocities as asked), ``.npz`` (points and faces), or a per-frame
        pattern ``dir/f_{:04d}.obj`` (``.obj .ply .stl .off .glb``; all meshes in one file; a
        name without ``{}`` only for one frame; ``.obj/.ply/.glb`` also get skinned normals and
        UVs, see :mod:`dqskin.formats.mesh_files`). Per-frame files are committed together.
    times : (F,) float, optional
        Default ``scene.times``.
    method : {"lbs", "dqs", "blend", "cor"} or None
        None: each mesh's own.
    interp : str
        Joint interpolation (:data:`dqskin.animation.INTERPOLATIONS`).
    chunk : int
        Frames skinned at a time.
    sign_reference : {"largest_weight", "running_sum"}
        Sign rule of the rotation blends (:data:`dqskin.skinning.SignReference`) for the skinned
        meshes (not yet for rigidly bound prims, which keep the default).
    normals : bool
        Skin normals into USD caches and ``.obj/.ply/.glb`` files.
    velocities : bool
        Write velocities (units per second) into USD caches.
    force : bool
        Overwrite existing outputs (never the input); the last writer wins.
    progress : bool
        A tqdm bar over frames on stderr (for three chunks or more, and only when stderr is a
        terminal).

    Returns
    -------
    str
        A one-line summary of what was written.
    """
    t = scene.times if times is None else np.atleast_1d(np.asarray(times, dtype=np.float64))
    kind = output_kind(out)
    if int(chunk) < 1:
        raise ValueError(f"--chunk {chunk}: must be at least 1")
    names = [m.name for m in scene.meshes]
    args = dict(method=method, device=device, interp=interp)
    sign = dict(sign_reference=sign_reference)  # (the meshes only: rigid prims use the default)
    src = scene.path
    counts = f"{_plural(len(names), 'mesh', 'meshes')} × {_plural(len(t), 'frame')}"
    if kind == "usd":
        if format_of(src) is not usd:
            raise ValueError(f"--out {out}: a USD point cache copies the input stage, so it needs "
                             "a USD input; for glTF write .npz or per-frame .obj/.ply/.glb files")
        check_output(out, [src], force)
        wrote_velocities = False
        with usd_cache.UsdCacheWriter(scene, out, overwrite=force, **args) as writer:
            for sl, res in _chunks(scene, t, chunk, progress, normals=normals,
                                   velocities=velocities, **args, **sign):
                check_skinned(src, res)
                writer.write(t[sl], res.points, res.normals, res.velocities)
                wrote_velocities |= bool(res.velocities)
        return (f"wrote {out}: {counts} "
                f"({method or 'asset method'}{', velocities' if wrote_velocities else ''})")
    if kind == "npz":
        check_output(out, [src], force)
        with atomic_path(out, overwrite=force) as tmp:  # claimed for the whole run
            pts = {m.name: np.empty((len(t), len(m.points), 3), np.float32)
                   for m in scene.meshes}
            for sl, res in _chunks(scene, t, chunk, progress, **args, **sign):
                check_skinned(src, res)
                for name in names:
                    pts[name][sl] = res.points[name]
            npz.save_npz(tmp, t, names, [pts[n] for n in names], [m.faces for m in scene.meshes])
        return f"wrote {out}: {counts}"
    suffix = Path(str(out)).suffix.lower()
    numbers = _frame_numbers(scene, t)
    paths = mesh_files.frame_paths(str(out), numbers)
    for p in paths:
        check_output(p, [src], force)
    gltf_input = format_of(src) is gltf
    layout = mesh_files.MeshLayout(
        scene.meshes, suffix, normals=normals, uv_top_left=gltf_input,
        uv_interpolation=None if gltf_input else _usd_uv_interpolation(src))
    with mesh_files.FrameWriter(str(out), layout.faces, layout.uvs, overwrite=force) as writer:
        for sl, res in _chunks(scene, t, chunk, progress, normals=layout.normals, **args,
                               **sign):
            check_skinned(src, res)
            points, nrm = layout.frames(res.points, res.normals)
            writer.write(numbers[sl], points, nrm)
    extras = [w for w, on in (("normals", layout.normals), ("UVs", layout.uvs is not None)) if on]
    span = f"{paths[0]}" if len(paths) == 1 else f"{paths[0]} … {paths[-1]}"
    return (f"wrote {_plural(len(paths), 'file')} {span}: {counts}"
            + (f" ({', '.join(extras)})" if extras else ""))


def _usd_uv_interpolation(path):
    """``mesh name → interpolation of its primvars:st`` from the USD stage at ``path``, opened
    on first use (only asked when UV counts leave the mapping ambiguous)."""
    stage = []

    def lookup(name):
        from pxr import Usd, UsdGeom
        if not stage:
            stage.append(Usd.Stage.Open(str(path)))
        prim = stage[0].GetPrimAtPath(name) if stage[0] else None
        pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st") if prim else None
        return str(pv.GetInterpolation()) if pv else None
    return lookup


def _frame_numbers(scene, times):
    from .times import frame_numbers
    return frame_numbers(times, seconds=format_of(scene.path) is gltf)


def _chunks(scene, times, chunk, progress, **skin_args):
    """:meth:`Scene.skin_chunks` with a progress bar over frames (only on a terminal)."""
    from tqdm import tqdm

    bar = tqdm(total=len(times), unit="frame", desc="skinning", file=sys.stderr,
               disable=not progress or len(times) <= 2 * chunk or not sys.stderr.isatty())
    try:
        for sl, res in scene.skin_chunks(times, chunk, **skin_args):
            check_interrupted()  # in case a library swallowed it
            yield sl, res
            bar.update(sl.stop - sl.start)
    finally:
        bar.close()
