"""Plain mesh files through trimesh: read geometry (:func:`load_mesh`), write one file per frame
(:func:`write_frames`)."""

import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path

__all__ = ["SUFFIXES", "frame_paths", "load_mesh", "write_frames"]

SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb")
"""Mesh files trimesh reads and writes (one frame per file)."""


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Geometry of a plain mesh file: ``(points (V, 3) float32, faces (T, 3) int32)``."""
    import trimesh
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such file")
    try:
        mesh = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise ValueError(f"{p}: cannot read mesh ({exc})") from None
    if len(mesh.vertices) == 0:
        raise ValueError(f"{p}: mesh has no vertices")
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def frame_paths(pattern, frames):
    """Expand ``dir/frame_{:04d}.obj`` for each frame number."""
    try:
        return [Path(pattern.format(int(f))) for f in frames]
    except (IndexError, KeyError, ValueError):
        raise ValueError(f"--out {pattern!r}: expected a pattern with one '{{}}' field for the "
                         "frame number, e.g. out/frame_{:04d}.obj") from None


def write_frames(pattern, frame_numbers, points, faces, *, force=False):
    """Write one mesh file per frame through trimesh (format from the suffix).

    Parameters
    ----------
    pattern : str
        e.g. ``"out/frame_{:04d}.obj"``; one of :data:`SUFFIXES`.
    frame_numbers : (F,) int
    points : (F, V, 3) float
    faces : (T, 3) int

    Returns
    -------
    list of Path, the files written.
    """
    import trimesh
    paths = frame_paths(pattern, frame_numbers)
    for path, pts in zip(paths, points):
        if path.exists() and not force:
            raise FileExistsError(f"{path}: exists (use --force to overwrite)")
        mesh = trimesh.Trimesh(np.asarray(pts, np.float64), faces, process=False)
        with atomic_path(path) as tmp:
            mesh.export(tmp, file_type=path.suffix.lstrip(".").lower())
    return paths
