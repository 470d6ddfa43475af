"""Bake a skinned animation to files: the library behind ``dqskin skin``.

:func:`bake` skins a scene chunk by chunk (:meth:`dqskin.Scene.skin_chunks`, so memory stays
bounded) and hands each chunk to the writer the output's suffix selects: a USD point cache
(:mod:`dqskin.formats.usd_cache`), one ``.npz`` (:mod:`dqskin.formats.npz`) or one mesh file per
frame (:mod:`dqskin.formats.mesh_files`). Every output is written atomically.
"""

import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ._warp import Device
from .animation import Interpolation
from .formats import format_of, gltf, mesh_files, npz, usd, usd_cache
from .scene import Scene
from .skinning import Method

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
    and not ``force``."""
    out = Path(out)
    for src in inputs:
        if out.resolve() == Path(src).resolve():
            raise ValueError(f"{out}: refusing to overwrite the input")
    if out.exists() and not force:
        raise FileExistsError(f"{out}: exists (use --force to overwrite)")
    return out


def bake(scene: Scene, out: str | Path, times: npt.ArrayLike | None = None, *,
         method: Method | None = None, interp: Interpolation = "trs", device: Device = None,
         chunk: int = 256, normals: bool = True, velocities: bool = True, force: bool = False,
         progress: bool = False) -> str:
    """Skin ``scene`` at ``times`` and write ``out``.

    Parameters
    ----------
    scene : dqskin.Scene
    out : str or Path
        ``.usd/.usda/.usdc`` (USD input only: a point cache of the source stage with points,
        extent, and normals and velocities as asked), ``.npz`` (points and faces), or a per-frame
        pattern ``dir/f_{:04d}.obj`` (``.obj .ply .stl .off .glb``; all meshes in one file).
    times : (F,) float, optional
        Default ``scene.times``.
    method : {"lbs", "dqs", "blend"} or None
        None: each mesh's own.
    interp : str
        Joint interpolation (:data:`dqskin.animation.INTERPOLATIONS`).
    chunk : int
        Frames skinned at a time.
    normals, velocities : bool
        Skin normals and write velocities (units per second) into USD caches.
    force : bool
        Overwrite existing outputs (never the input).
    progress : bool
        A tqdm bar over frames on stderr (for three chunks or more).

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
    if kind == "usd":
        if format_of(scene.path) is not usd:
            raise ValueError(f"--out {out}: a USD point cache copies the input stage, so it needs "
                             "a USD input; for glTF write .npz or per-frame .obj/.ply/.glb files")
        check_output(out, [scene.path], force)
        wrote_velocities = False
        with usd_cache.UsdCacheWriter(scene, out, **args) as writer:
            for sl, res in _chunks(scene, t, chunk, progress, normals=normals,
                                   velocities=velocities, **args):
                writer.write(t[sl], res.points, res.normals, res.velocities)
                wrote_velocities |= bool(res.velocities)
        return (f"wrote {out}: {len(names)} meshes × {len(t)} frames "
                f"({method or 'asset method'}{', velocities' if wrote_velocities else ''})")
    if kind == "npz":
        check_output(out, [scene.path], force)
        pts = {m.name: np.empty((len(t), len(m.points), 3), np.float32) for m in scene.meshes}
        for sl, res in _chunks(scene, t, chunk, progress, **args):
            for name in names:
                pts[name][sl] = res.points[name]
        npz.write_npz(out, t, names, [pts[n] for n in names], [m.faces for m in scene.meshes])
        return f"wrote {out}: {len(names)} meshes × {len(t)} frames"
    numbers = _frame_numbers(scene, t)
    paths = mesh_files.frame_paths(str(out), numbers)
    for p in paths:
        check_output(p, [scene.path], force)
    offsets = np.cumsum([0] + [len(m.points) for m in scene.meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(scene.meshes, offsets)])
    for sl, res in _chunks(scene, t, chunk, progress, **args):
        stacked = np.concatenate([res.points[n] for n in names], axis=1)
        mesh_files.write_frames(str(out), numbers[sl], stacked, faces, force=force)
    return f"wrote {len(paths)} files {paths[0]} … {paths[-1]}"


def _frame_numbers(scene, times):
    from .times import frame_numbers
    return frame_numbers(times, seconds=format_of(scene.path) is gltf)


def _chunks(scene, times, chunk, progress, **skin_args):
    """:meth:`Scene.skin_chunks` with a progress bar over frames."""
    from tqdm import tqdm

    bar = tqdm(total=len(times), unit="frame", desc="skinning", file=sys.stderr,
               disable=not progress or len(times) <= 2 * chunk)
    for sl, res in scene.skin_chunks(times, chunk, **skin_args):
        yield sl, res
        bar.update(sl.stop - sl.start)
    bar.close()
