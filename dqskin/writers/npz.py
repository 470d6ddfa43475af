"""Skinned frames as one NumPy ``.npz`` archive.

What the archive holds: ``times`` (F,) (the asset's time unit), ``names`` (M,), and per mesh
``i`` (in ``names`` order) ``points_i`` (F, V_i, 3) float32 and ``faces_i`` (T_i, 3); a bake
(:func:`dqskin.bake`) adds ``frames`` (F,) (frame numbers at ``fps``), ``fps``, ``space``
(``"world"`` by default: the points a USD cache of the same bake shows through its prims'
local-to-world), ``up_axis`` and ``meters_per_unit`` (the points are in the scene's length unit,
never rescaled).
"""

import os
from collections.abc import Iterable, Mapping

import numpy as np
import numpy.typing as npt

from ..files.atomic import atomic_path

__all__ = ["SUFFIXES", "save_npz", "write_npz"]

SUFFIXES = (".npz",)


def save_npz(path: str | os.PathLike, times: npt.ArrayLike, names: Iterable[str],
             points: Iterable[npt.ArrayLike], faces: Iterable[npt.ArrayLike], *,
             info: Mapping[str, npt.ArrayLike] | None = None) -> None:
    """Write the archive to ``path`` as is (not atomic: :func:`write_npz`, or a path from
    :class:`dqskin.files.atomic.atomic_path`); ``info``: more named arrays (scalars, strings)."""
    extra = {k: np.asarray(v) for k, v in (info or {}).items()}
    with open(path, "wb") as fh:
        np.savez(fh, allow_pickle=False, times=np.asarray(times, np.float64),
                 names=np.array(list(names)),
                 **{f"points_{i}": p for i, p in enumerate(points)},
                 **{f"faces_{i}": f for i, f in enumerate(faces)}, **extra)


def write_npz(path: str | os.PathLike, times: npt.ArrayLike, names: Iterable[str],
              points: Iterable[npt.ArrayLike], faces: Iterable[npt.ArrayLike], *,
              overwrite: bool = True, info: Mapping[str, npt.ArrayLike] | None = None) -> None:
    """Write ``times``, ``names`` and per mesh ``i`` (in ``names`` order) ``points_i`` and
    ``faces_i``, atomically.

    Parameters
    ----------
    path : str or os.PathLike
    times : (F,) float64
    names : sequence of str, length M
    points : sequence of (F, V_i, 3) float32, length M
    faces : sequence of (T_i, 3) int32, length M
    overwrite : bool
        Replace an existing ``path``; False fails (FileExistsError) if it exists when the file is
        complete (:class:`~dqskin.files.atomic.atomic_path`).
    info : dict str → array-like, optional
        More arrays to store (``frames``, ``fps``, ``space``, ...).
    """
    with atomic_path(path, overwrite=overwrite) as tmp:
        save_npz(tmp, times, names, points, faces, info=info)
