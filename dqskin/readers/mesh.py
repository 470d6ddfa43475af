"""Plain mesh files through trimesh (``.obj``, ``.ply``, ``.stl``, ``.off``, ``.glb`` and what else
trimesh reads): geometry only, no skeleton (:func:`load_mesh`)."""

import os

import numpy as np

from ..errors import InputError
from ..files.inputs import regular_file
from ..validation import check_points

__all__ = ["load_mesh"]


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Geometry of a plain mesh file: ``(points (V, 3) float32, faces (T, 3) int32)``.

    Raises InputError (a ValueError) naming the file: not a regular file, unreadable, no
    vertices, vertices NaN, infinite, beyond float32 range or all at one point
    (:func:`dqskin.validation.check_points`)."""
    import trimesh
    p = regular_file(path)
    try:
        mesh = trimesh.load(p, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"{p}: cannot read mesh ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):  # (force="mesh" makes one of any file it reads)
        raise InputError(f"{p}: cannot read mesh (no triangles)")
    if len(mesh.vertices) == 0:
        raise InputError(f"{p}: mesh has no vertices")
    vertices = np.asarray(mesh.vertices, np.float64)
    check_points(str(p), vertices)
    return vertices.astype(np.float32), np.asarray(mesh.faces, np.int32)
