"""Plain mesh files through trimesh, one file per frame (:class:`FrameWriter`,
:class:`MeshLayout`, :func:`write_frames`); :func:`dqskin.readers.mesh.load_mesh` reads them.

What each per-frame format holds (all meshes of the scene go into one file per frame):

* ``.obj``, ``.ply``, ``.glb``: positions, triangles, skinned normals (unit length) and UVs.
  Face-varying normals or UVs (USD ``faceVarying``/``uniform``/``constant`` primvars) are made
  per-vertex by splitting the vertices where corners differ, as these formats (and trimesh) need;
  a mesh without rest normals gets area-weighted normals of its skinned triangles when another
  mesh of the file has normals, and UV (0, 0) when another mesh has UVs.
* ``.stl``, ``.off``: positions and triangles only (the formats have no per-vertex normals or
  UVs), so dqskin neither skins normals for them nor reads the UVs.
* Every format but ``.ply`` needs triangles: a mesh without faces (curves, points) is an error
  naming it; ``.ply`` keeps its points as vertices.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ..errors import InputError, Param, output_exists
from ..files.atomic import CommitOnSuccess, atomic_group, named_error

if TYPE_CHECKING:
    import trimesh

    from ..scene import Mesh

__all__ = ["FACES_REQUIRED", "SUFFIXES", "WITH_ATTRIBUTES", "FrameWriter", "MeshLayout",
           "frame_paths", "write_frames"]

SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb")
"""Mesh files trimesh reads and writes (one frame per file)."""

WITH_ATTRIBUTES = (".obj", ".ply", ".glb")
"""Per-frame formats that carry normals and UVs (``.stl``/``.off`` hold positions and faces)."""

FACES_REQUIRED = (".obj", ".stl", ".off", ".glb")
"""Per-frame formats that need triangles (``.ply`` also holds bare points)."""


def frame_paths(pattern: str | os.PathLike, frames: Iterable[int]) -> list[Path]:
    """Expand ``dir/frame_{:04d}.obj`` for each frame number; InputError when two frames would
    share a file (a name without a ``{}`` field and more than one frame)."""
    pattern = str(pattern)
    try:
        paths = [Path(pattern.format(int(f))) for f in frames]
    except (IndexError, KeyError, ValueError):
        raise InputError(Param("out", pattern), ": expected a pattern with one '{}' field for "
                         "the frame number, e.g. out/frame_{:04d}.obj") from None
    if len(set(paths)) != len(paths):
        raise InputError(Param("out", pattern), f": {len(paths)} frames but {len(set(paths))} "
                         "file name(s); one file per frame needs a '{}' field for the frame "
                         "number (e.g. out/frame_{:04d}.obj), or select one frame with ",
                         Param("times"))
    return paths


def _triangle_corners(mesh: Mesh) -> np.ndarray | None:
    """(T, 3) positions in ``face_vertex_indices`` of each triangle corner of ``mesh.faces`` (the
    loaders' fan triangulation, holes dropped, winding maybe flipped), or None."""
    counts, fvi, faces = mesh.face_vertex_counts, mesh.face_vertex_indices, mesh.faces
    if counts is None or fvi is None:
        return None
    counts = np.asarray(counts, np.int64)
    fvi = np.asarray(fvi, np.int64)
    ntri = np.where(counts >= 3, counts - 2, 0)
    start = np.cumsum(counts) - counts
    face = np.repeat(np.arange(counts.size), ntri)
    k = np.arange(face.size) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    first = start[face]
    fan = np.stack([first, first + k + 1, first + k + 2], axis=1)
    for corners in (fan, fan[:, ::-1]):
        if corners.shape == faces.shape and np.array_equal(fvi[corners], faces):
            return corners
    # some polygons were dropped (holes): walk the polygons in order
    bounds = np.concatenate([[0], np.cumsum(ntri)])
    for corners in (fan, fan[:, ::-1]):
        verts, pos, keep = fvi[corners], 0, []
        for p in np.flatnonzero(ntri):
            lo, hi = bounds[p], bounds[p + 1]
            n = hi - lo
            if pos + n <= len(faces) and np.array_equal(verts[lo:hi], faces[pos:pos + n]):
                keep.append(corners[lo:hi])
                pos += n
        if pos == len(faces):
            return np.concatenate(keep) if keep else np.zeros((0, 3), np.int64)
    return None


def _uv_interpolation(mesh: Mesh, hint: Callable[[str], str | None] | None) -> str:
    """How ``mesh.uvs`` map to the mesh: "vertex", "faceVarying", "uniform" or "constant"."""
    assert mesh.uvs is not None, "asked only for meshes with UVs"
    U, V = len(mesh.uvs), len(mesh.points)
    fvi, counts = mesh.face_vertex_indices, mesh.face_vertex_counts
    candidates = []
    if U == V:
        candidates.append("vertex")
    if fvi is not None and U == len(fvi):
        if not (candidates and np.array_equal(np.asarray(fvi), np.arange(V))):
            candidates.append("faceVarying")  # (identical to vertex when fvi is the identity)
    if counts is not None and U == len(counts):
        candidates.append("uniform")
    if U == 1:
        candidates.append("constant")
    if len(candidates) > 1:
        authored = hint(mesh.name) if hint is not None else None
        authored = "vertex" if authored == "varying" else authored
        if authored in candidates:
            return authored
    if len(candidates) == 1:
        return candidates[0]
    raise InputError(f"{mesh.name}: cannot tell how its {U} UVs map to {V} points"
                     + (f" and {len(fvi)} face corners" if fvi is not None else ""))


class MeshLayout:
    """How a scene's meshes become the vertex list of one mesh file (the same for every frame).

    Parameters
    ----------
    meshes : sequence of dqskin.Mesh
    suffix : str
        One of :data:`SUFFIXES`.
    normals : bool
        Write normals (only for :data:`WITH_ATTRIBUTES`).
    uvs : bool
        Write UVs (only for :data:`WITH_ATTRIBUTES`, when a mesh has them).
    uv_top_left : bool
        ``mesh.uvs`` have a top-left origin (glTF); trimesh's files get bottom-left (USD, OBJ).
    uv_interpolation : callable, optional
        ``mesh name → authored interpolation`` of its UVs, asked only when the counts leave it
        ambiguous.

    Attributes
    ----------
    faces : (T, 3) int64
        Triangles into the file's vertices.
    uvs : (K, 2) float64 or None
    normals : bool
    """

    def __init__(self, meshes: Sequence[Mesh], suffix: str, *, normals: bool = True,
                 uvs: bool = True, uv_top_left: bool = False,
                 uv_interpolation: Callable[[str], str | None] | None = None) -> None:
        suffix = suffix.lower()
        if suffix not in SUFFIXES:
            raise InputError(f"{suffix}: not a mesh file type ({' '.join(SUFFIXES)})")
        rich = suffix in WITH_ATTRIBUTES
        self.normals = bool(normals) and rich and any(m.normals is not None for m in meshes)
        want_uvs = bool(uvs) and rich and any(m.uvs is not None for m in meshes)
        # (mesh, vertex (K,), normal index (K,) or None)
        self.parts: list[tuple[Mesh, np.ndarray, np.ndarray | None]] = []
        faces: list[np.ndarray] = []
        uv_rows: list[np.ndarray] = []
        offset = 0
        for m in meshes:
            if suffix in FACES_REQUIRED and len(m.faces) == 0:
                raise InputError(f"{m.name}: no faces; {suffix} files hold triangle meshes "
                                 "(write .ply, .npz or a USD cache)")
            vert, tris, nidx, uv = self._split(m, want_uvs, uv_top_left, uv_interpolation)
            self.parts.append((m, vert, nidx))
            faces.append(tris + offset)
            uv_rows.append(uv if uv is not None else np.zeros((len(vert), 2)))
            offset += len(vert)
        self.faces = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
        self.uvs = np.concatenate(uv_rows) if want_uvs else None
        self.vertex_count = offset

    def _split(self, m: Mesh, want_uvs: bool, uv_top_left: bool,
               uv_interpolation: Callable[[str], str | None] | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(vertex (K,), faces (T, 3) into K, normal index (K,) or None, uvs (K, 2) or None)."""
        faces = np.asarray(m.faces, np.int64).reshape(-1, 3)
        V = len(m.points)
        has_n = self.normals and m.normals is not None
        fv_normals = has_n and m.normal_vertex is not None
        uv_interp = None
        if want_uvs and m.uvs is not None:
            uv_interp = _uv_interpolation(m, uv_interpolation)
        uvs = None
        if uv_interp is not None:
            uvs = np.asarray(m.uvs, np.float64).reshape(-1, 2).copy()
            if uv_top_left:
                uvs[:, 1] = 1.0 - uvs[:, 1]
        if not fv_normals and uv_interp in (None, "vertex"):
            vert = np.arange(V)
            return vert, faces, (vert if has_n else None), (None if uvs is None else uvs)
        corners = _triangle_corners(m)
        if corners is None:
            raise InputError(f"{m.name}: cannot match its face-varying normals or UVs to its "
                             "triangles")
        vert_c, corner_c = faces.ravel(), corners.ravel()
        keys = [vert_c[:, None]]
        uv_c = None
        if uvs is not None:
            if uv_interp == "vertex":
                uv_c = uvs[vert_c]
            elif uv_interp == "faceVarying":
                uv_c = uvs[corner_c]
            elif uv_interp == "uniform":
                counts = np.asarray(m.face_vertex_counts, np.int64)  # "uniform": known
                polygon = np.repeat(np.arange(len(counts)), counts)
                uv_c = uvs[polygon[corner_c]]
            else:
                uv_c = np.broadcast_to(uvs[0], (len(vert_c), 2))
            keys.append(np.ascontiguousarray(uv_c).view(np.int64))
        if fv_normals:
            keys.append(np.asarray(m.normals, np.float32)[corner_c].view(np.int32)
                        .astype(np.int64))
        rows = np.concatenate(keys, axis=1)
        _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
        vert = vert_c[first]
        nidx = (corner_c[first] if fv_normals else vert) if has_n else None
        return (vert, inverse.reshape(-1, 3), nidx,
                None if uv_c is None else np.ascontiguousarray(uv_c[first]))

    def frames(self, points: Mapping[str, npt.ArrayLike],
               normals: Mapping[str, npt.ArrayLike] | None = None
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-frame arrays for the file from skinned results.

        Parameters
        ----------
        points : dict mesh name → (F, V, 3)
        normals : dict mesh name → (F, N, 3), optional
            Skinned normals (:meth:`dqskin.Scene.skin` ``normals=True``).

        Returns
        -------
        (F, K, 3) float32 positions and (F, K, 3) float32 unit normals or None.
        """
        pts: list[np.ndarray] = []
        nrm: list[np.ndarray] = []
        for m, vert, nidx in self.parts:
            p = np.asarray(points[m.name], np.float32)
            pts.append(p[:, vert])
            if not self.normals:
                continue
            if nidx is not None and normals is not None and m.name in normals:
                n = np.asarray(normals[m.name], np.float32)[:, nidx]
            else:
                n = _vertex_normals(p, np.asarray(m.faces, np.int64))[:, vert]
            nrm.append(n)
        pos = np.concatenate(pts, axis=1) if pts else np.zeros((0, 0, 3), np.float32)
        if not self.normals:
            return pos, None
        n = np.concatenate(nrm, axis=1)
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
        return pos, n


def _vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, V, 3) unit area-weighted vertex normals of triangles ``faces`` over ``points``
    (F, V, 3): the renderer's kernel (:func:`dqskin.kernels.render.vertex_normals`), per frame."""
    import warp as wp

    from ..kernels import render as KR
    from ..topology import incidence
    F, V = points.shape[:2]
    out = np.zeros((F, V, 3), np.float32)
    if not len(faces) or not V:
        return out
    offsets, vf = incidence(np.asarray(faces, np.int32), V)
    arrays: dict[str, wp.array] = {
        "faces": wp.array(np.asarray(faces, np.int32).ravel(), dtype=wp.int32, device="cpu"),
        "vf_offsets": wp.array(offsets, dtype=wp.int32, device="cpu"),
        "vf_faces": wp.array(vf, dtype=wp.int32, device="cpu")}
    normals = wp.empty(V, dtype=wp.vec3, device="cpu")
    for k in range(F):
        KR.vertex_normals(points=wp.array(points[k], dtype=wp.vec3, device="cpu"), out=normals,
                          device="cpu", **arrays)
        out[k] = normals.numpy()
    return out


class FrameWriter(CommitOnSuccess):
    """One mesh file per frame, committed together: all frames appear at the end, or none.

    Parameters
    ----------
    pattern : str
        e.g. ``"out/frame_{:04d}.obj"``; one of :data:`SUFFIXES`.
    faces : (T, 3) int
    uvs : (K, 2) float, optional
        Per vertex, bottom-left origin (``.obj``/``.ply``/``.glb`` only).
    overwrite : bool
        Replace existing files; False claims each name exclusively (FileExistsError when it
        exists at commit, e.g. written by another run meanwhile).

    Use as a context manager (commits on success, removes every temporary file on an exception),
    or call :meth:`commit` / :meth:`discard`.
    """

    def __init__(self, pattern: str | os.PathLike, faces: npt.ArrayLike,
                 uvs: npt.ArrayLike | None = None, *, overwrite: bool = True) -> None:
        self.pattern = str(pattern)
        self.suffix = Path(self.pattern).suffix.lower()
        if self.suffix not in SUFFIXES:
            raise InputError(f"{self.pattern}: not a mesh file type ({' '.join(SUFFIXES)})")
        self.faces = np.asarray(faces, np.int64).reshape(-1, 3)
        if uvs is not None and self.suffix not in WITH_ATTRIBUTES:
            raise InputError(f"{self.pattern}: {self.suffix} files cannot hold UVs")
        self.uvs = None if uvs is None else np.asarray(uvs, np.float64)
        self.group = atomic_group(overwrite=overwrite)
        self.paths: list[Path] = []

    def write(self, frame_numbers: Iterable[int], points: Sequence[npt.ArrayLike] | np.ndarray,
              normals: Sequence[npt.ArrayLike] | np.ndarray | None = None) -> list[Path]:
        """Write frames ``frame_numbers`` (F,) with positions ``points`` (F, K, 3) and
        optionally unit ``normals`` (F, K, 3) to temporary files."""
        import trimesh
        if normals is not None and self.suffix not in WITH_ATTRIBUTES:
            raise InputError(f"{self.pattern}: {self.suffix} files cannot hold vertex normals")
        paths = frame_paths(self.pattern, frame_numbers)
        from trimesh.visual import TextureVisuals
        from trimesh.visual.material import PBRMaterial
        for k, (path, pts) in enumerate(zip(paths, points)):
            visual = (None if self.uvs is None else
                      TextureVisuals(uv=self.uvs, material=PBRMaterial()))  # no texture image
            mesh = trimesh.Trimesh(np.asarray(pts, np.float64), self.faces, process=False,
                                   vertex_normals=None if normals is None else normals[k],
                                   visual=visual)
            tmp = self.group.add(path)
            try:
                self._export(mesh, tmp, normals is not None)
            except OSError as exc:  # (a full disk: naming the frame's file)
                raise named_error(path, exc) from None
            except Exception as exc:  # trimesh raises many types
                raise InputError(f"{path}: trimesh cannot write it ({exc})") from None
            self.paths.append(path)
        return paths

    def _export(self, mesh: trimesh.Trimesh, tmp: Path, with_normals: bool) -> None:
        if self.suffix == ".obj":
            from trimesh.exchange.obj import export_obj
            text = export_obj(mesh, include_normals=with_normals,
                              include_texture=self.uvs is not None, write_texture=False)
            # UVs without a material: no mtllib / usemtl (nothing to point at)
            text = "\n".join(ln for ln in text.split("\n")
                             if not ln.startswith(("mtllib ", "usemtl ")))
            Path(tmp).write_text(text)
        else:
            mesh.export(tmp, file_type=self.suffix.lstrip("."))

    def commit(self) -> list[Path]:
        """Put every written file in place; returns their paths."""
        return self.group.commit()

    def discard(self) -> None:
        self.group.discard()


def write_frames(pattern: str | os.PathLike, frame_numbers: Iterable[int],
                 points: Sequence[npt.ArrayLike] | np.ndarray, faces: npt.ArrayLike, *,
                 force: bool = False, normals: Sequence[npt.ArrayLike] | np.ndarray | None = None,
                 uvs: npt.ArrayLike | None = None) -> list[Path]:
    """Write one mesh file per frame through trimesh (format from the suffix), all together.

    Parameters
    ----------
    pattern : str
        e.g. ``"out/frame_{:04d}.obj"``; one of :data:`SUFFIXES`.
    frame_numbers : (F,) int
    points : (F, V, 3) float
    faces : (T, 3) int
    force : bool
        Replace existing files (otherwise OutputExistsError, before anything is written).
    normals : (F, V, 3) float, optional
    uvs : (V, 2) float, optional

    Returns
    -------
    list of Path, the files written.
    """
    paths = frame_paths(pattern, frame_numbers)
    if not force:
        for path in paths:
            if path.exists():
                raise output_exists(path)
    if Path(str(pattern)).suffix.lower() in FACES_REQUIRED and len(np.reshape(faces, (-1, 3))) == 0:
        raise InputError(f"{pattern}: no faces to write")
    with FrameWriter(pattern, faces, uvs, overwrite=force) as writer:
        writer.write(frame_numbers, points, normals)
    return paths
