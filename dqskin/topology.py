"""Triangle-mesh topology helpers shared by the metrics and the renderer."""

import numpy as np
import numpy.typing as npt

from .errors import InputError

__all__ = ["check_faces", "fan_corners", "incidence"]


def check_faces(faces: npt.ArrayLike, vertex_count: int) -> np.ndarray:
    """Validate triangles and return them as (T, 3) int32.

    Raises ValueError naming ``faces`` for a wrong shape, no faces, non-integer indices or an
    index outside ``[0, vertex_count)``.
    """
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"faces: expected (T, 3) triangles, got {f.shape}")
    if f.shape[0] == 0:
        raise InputError("faces: mesh has no faces")
    if not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"faces: expected integers, got {f.dtype}")
    if f.min() < 0 or f.max() >= vertex_count:
        raise InputError(f"faces: vertex index out of range [0, {vertex_count})")
    return f.astype(np.int32)


def incidence(items_of: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Index → incident items as CSR ``(offsets (count+1,), items)`` int32, from an (N, k) table
    (e.g. faces (T, 3) → for each vertex the faces that use it)."""
    flat = items_of.reshape(-1)
    order = np.argsort(flat, kind="stable")
    offsets = np.zeros(count + 1, dtype=np.int64)
    np.cumsum(np.bincount(flat, minlength=count), out=offsets[1:])
    return offsets.astype(np.int32), (order // items_of.shape[1]).astype(np.int32)


def fan_corners(counts: npt.ArrayLike, keep: npt.ArrayLike,
                starts: npt.ArrayLike | None = None) -> np.ndarray:
    """(T, 3) int64 positions, in a face-vertex index array, of the corners of the fan triangles
    (first corner, ``k + 1``, ``k + 2``) of the polygons where ``keep`` (bool, one per polygon)
    is set, polygon after polygon. Polygon ``p`` has ``counts[p]`` corners from ``starts[p]``
    (default: the polygons one after the other, ``cumsum(counts) - counts``); a kept polygon
    needs three corners at least."""
    counts = np.asarray(counts, np.int64)
    ntri = np.where(keep, counts - 2, 0)
    start = np.cumsum(counts) - counts if starts is None else np.asarray(starts, np.int64)
    face = np.repeat(np.arange(counts.size), ntri)
    k = np.arange(face.size) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    first = start[face]
    return np.stack([first, first + k + 1, first + k + 2], axis=1)
