"""Plain mesh files through trimesh (``.obj``, ``.ply``, ``.stl``, ``.off``, ``.glb`` and what else
trimesh reads): geometry only, no skeleton (:func:`load_mesh`)."""

import os
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["load_mesh"]


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Geometry of a plain mesh file: ``(points (V, 3) float32, faces (T, 3) int32)``."""
    import trimesh
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file")
    if not p.is_file():
        raise InputError(f"{p}: not a regular file")
    try:
        mesh = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"{p}: cannot read mesh ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):  # (force="mesh" makes one of any file it reads)
        raise InputError(f"{p}: cannot read mesh (no triangles)")
    if len(mesh.vertices) == 0:
        raise InputError(f"{p}: mesh has no vertices")
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
