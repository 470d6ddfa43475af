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
* Materials: ``.glb`` frames embed each mesh's base-colour material and texture
  (:mod:`dqskin.readers.materials`), one glTF mesh per source mesh; ``.obj`` frames name one
  ``.mtl`` file (``Kd``, ``d``, ``map_Kd``) written beside them with the texture images, once
  for all frames.
* Space: the points as skinned (world space by default, in the scene's length unit). ``.glb``
  files put them under one node whose matrix takes them to glTF's space (metres, +Y up): the
  accessors hold the points themselves. ``.obj`` and ``.ply`` files state the space, up axis and
  unit in a comment.
* Every format but ``.ply`` needs triangles: a mesh without faces (curves, points) is left out
  of them (:attr:`MeshLayout.skipped` says which), an error only when no mesh is left; ``.ply``
  keeps its points as vertices.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ..errors import InputError, Param, output_exists
from ..files.atomic import CommitOnSuccess, atomic_group, named_error
from ..topology import fan_corners

if TYPE_CHECKING:
    import trimesh

    from ..readers.materials import BaseColor
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
    fan = fan_corners(counts, counts >= 3)
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
    meshes : list of dqskin.Mesh
        The meshes the files hold, in order.
    ranges : list of (slice, slice)
        Per mesh of :attr:`meshes`, its rows of the vertices and of :attr:`faces`.
    skipped : list of str
        One line per mesh the format cannot hold (no faces), left out.

    Raises
    ------
    InputError
        No mesh the format can hold; UVs that cannot be matched to the mesh.
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
        self.skipped = [f"skipped {m.name} (no faces; {suffix} files hold triangle meshes)"
                        for m in meshes if suffix in FACES_REQUIRED and len(m.faces) == 0]
        self.meshes = [m for m in meshes if suffix not in FACES_REQUIRED or len(m.faces)]
        if meshes and not self.meshes:
            raise InputError(f"no mesh to write: {suffix} files hold triangle meshes and "
                             f"{', '.join(m.name for m in meshes)}: no faces; write .ply, .npz "
                             "or a USD cache")
        self.ranges: list[tuple[slice, slice]] = []
        faces: list[np.ndarray] = []
        uv_rows: list[np.ndarray] = []
        offset = face_offset = 0
        for m in self.meshes:
            vert, tris, nidx, uv = self._split(m, want_uvs, uv_top_left, uv_interpolation)
            self.parts.append((m, vert, nidx))
            faces.append(tris + offset)
            uv_rows.append(uv if uv is not None else np.zeros((len(vert), 2)))
            self.ranges.append((slice(offset, offset + len(vert)),
                                slice(face_offset, face_offset + len(tris))))
            offset += len(vert)
            face_offset += len(tris)
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
    groups : sequence of (slice, slice, BaseColor or None, str), optional
        Per source mesh: its rows of the vertices and of ``faces``, its material and its name
        (``.glb``: one glTF node and mesh each, so named, with its material; ``.obj``: one
        ``usemtl`` group each, materials in :meth:`material_path`). Default: one group, no
        material.
    to_gltf : (4, 4) float, optional
        ``.glb``: the matrix of the node holding the meshes (the points' space → glTF's
        metres, +Y up); identity when None.
    comment : str, optional
        One line for ``.obj`` and ``.ply`` headers (the space, up axis and unit).

    Use as a context manager (commits on success, removes every temporary file on an exception),
    or call :meth:`commit` / :meth:`discard`.
    """

    def __init__(self, pattern: str | os.PathLike, faces: npt.ArrayLike,
                 uvs: npt.ArrayLike | None = None, *, overwrite: bool = True,
                 groups: Sequence[tuple[slice, slice, BaseColor | None, str]] | None = None,
                 to_gltf: npt.ArrayLike | None = None, comment: str | None = None) -> None:
        self.pattern = str(pattern)
        self.suffix = Path(self.pattern).suffix.lower()
        if self.suffix not in SUFFIXES:
            raise InputError(f"{self.pattern}: not a mesh file type ({' '.join(SUFFIXES)})")
        self.faces = np.asarray(faces, np.int64).reshape(-1, 3)
        if uvs is not None and self.suffix not in WITH_ATTRIBUTES:
            raise InputError(f"{self.pattern}: {self.suffix} files cannot hold UVs")
        self.uvs = None if uvs is None else np.asarray(uvs, np.float64)
        self.groups = list(groups) if groups else [(slice(None), slice(None), None, "mesh")]
        if self.suffix not in (".obj", ".glb") or self.uvs is None:
            self.groups = [(v, f, None, n) for v, f, _, n in self.groups]
        self.to_gltf = None if to_gltf is None else np.asarray(to_gltf, np.float64)
        self.comment = " ".join(str(comment).split()) if comment else None
        self.group = atomic_group(overwrite=overwrite)
        self.paths: list[Path] = []
        self._materials: dict[BaseColor, str] = {}  # material → its name in the files
        for _, _, c, _ in self.groups:
            if c is not None and c not in self._materials:
                name, k = c.name, 1
                while name in self._materials.values():
                    name, k = f"{c.name}_{k}", k + 1
                self._materials[c] = name
        self._pbr_cache: dict[BaseColor, object] = {}  # material → trimesh's PBRMaterial
        self._shared_written = False

    def material_path(self) -> Path | None:
        """The ``.mtl`` file ``.obj`` frames name (None: no material, or not ``.obj``):
        ``out/frame_{:04d}.obj`` → ``out/frame.mtl``."""
        if self.suffix != ".obj" or not self._materials:
            return None
        p = Path(self.pattern)
        stem = re.sub(r"\{[^{}]*\}", "", p.stem).strip("_-. ") or "materials"
        return p.with_name(stem + ".mtl")

    def write(self, frame_numbers: Iterable[int], points: Sequence[npt.ArrayLike] | np.ndarray,
              normals: Sequence[npt.ArrayLike] | np.ndarray | None = None) -> list[Path]:
        """Write frames ``frame_numbers`` (F,) with positions ``points`` (F, K, 3) and
        optionally unit ``normals`` (F, K, 3) to temporary files."""
        if normals is not None and self.suffix not in WITH_ATTRIBUTES:
            raise InputError(f"{self.pattern}: {self.suffix} files cannot hold vertex normals")
        paths = frame_paths(self.pattern, frame_numbers)
        if not self._shared_written:
            self._write_materials()
        for k, (path, pts) in enumerate(zip(paths, points)):
            tmp = self.group.add(path)
            nrm = None if normals is None else np.asarray(normals[k], np.float64)
            try:
                if self.suffix == ".obj":
                    Path(tmp).write_text(self._obj(np.asarray(pts, np.float64), nrm))
                elif self.suffix == ".glb":
                    self._glb(np.asarray(pts, np.float64), nrm).export(
                        tmp, file_type="glb", include_normals=nrm is not None)
                else:
                    self._plain(np.asarray(pts, np.float64), nrm, tmp)
            except OSError as exc:  # (a full disk: naming the frame's file)
                raise named_error(path, exc) from None
            except Exception as exc:  # trimesh raises many types
                raise InputError(f"{path}: trimesh cannot write it ({exc})") from None
            self.paths.append(path)
        return paths

    def _write_materials(self) -> None:
        """The ``.mtl`` file and texture images of ``.obj`` frames (once)."""
        self._shared_written = True
        mtl = self.material_path()
        if mtl is None:
            return
        lines = ["# dqskin: materials of " + Path(self.pattern).name]
        for c, name in self._materials.items():
            r, g, b, a = c.factor
            lines += ["", f"newmtl {name}", f"Kd {r:.6g} {g:.6g} {b:.6g}", f"d {a:.6g}",
                      "Ka 0 0 0", "Ks 0 0 0", "illum 1"]
            if c.image is not None:
                image = mtl.with_name(f"{mtl.stem}_{name}{c.image_suffix}")
                Path(self.group.add(image)).write_bytes(c.image)
                self.paths.append(image)
                lines.append(f"map_Kd {image.name}")
        Path(self.group.add(mtl)).write_text("\n".join(lines) + "\n")
        self.paths.append(mtl)

    def _obj(self, pts: np.ndarray, nrm: np.ndarray | None) -> str:
        """The text of one ``.obj`` frame (vertex, UV and normal indices all equal)."""
        out = [f"# {self.comment}"] if self.comment else []
        mtl = self.material_path()
        if mtl is not None:
            out.append(f"mtllib {mtl.name}")
        out.append(_rows("v", pts))
        if self.uvs is not None:
            out.append(_rows("vt", self.uvs))
        if nrm is not None:
            out.append(_rows("vn", nrm))
        corner = "{0}/{0}/{0}" if self.uvs is not None and nrm is not None else \
            "{0}/{0}" if self.uvs is not None else "{0}//{0}" if nrm is not None else "{0}"
        for _, fs, c, name in self.groups:
            out.append(f"g {re.sub(r'[^A-Za-z0-9_./-]', '_', name)}")
            if c is not None:
                out.append(f"usemtl {self._materials[c]}")
            tri = self.faces[fs] + 1
            if len(tri):
                fmt = "f " + " ".join(corner.replace("0", str(i)) for i in range(3))
                out.append("\n".join(fmt.format(*row) for row in tri.tolist()))
        return "\n".join(out) + "\n"

    def _glb(self, pts: np.ndarray, nrm: np.ndarray | None) -> trimesh.Scene:
        """One ``.glb`` frame: a glTF mesh per group under the :attr:`to_gltf` node."""
        import trimesh
        from trimesh.visual import TextureVisuals
        from trimesh.visual.material import PBRMaterial
        scene = trimesh.Scene()
        root = np.eye(4) if self.to_gltf is None else self.to_gltf
        for vs, fs, c, name in self.groups:
            v = np.arange(len(pts))[vs]
            lo = int(v[0]) if len(v) else 0
            visual = None
            if self.uvs is not None:
                visual = TextureVisuals(uv=self.uvs[vs], material=self._pbr(c, PBRMaterial))
            mesh = trimesh.Trimesh(pts[vs], self.faces[fs] - lo, process=False,
                                   vertex_normals=None if nrm is None else nrm[vs],
                                   visual=visual)
            scene.add_geometry(mesh, node_name=name, geom_name=name, transform=root)
        return scene

    def _pbr(self, c: BaseColor | None, kind: type) -> object:
        """trimesh's PBRMaterial of ``c`` (its texture decoded once)."""
        if c is None:
            return kind()
        cached = self._pbr_cache
        if c not in cached:
            image = None
            if c.image is not None:
                import io

                from PIL import Image
                image = Image.open(io.BytesIO(c.image))
                image.load()
            cached[c] = kind(name=self._materials[c], baseColorFactor=list(c.factor),
                             baseColorTexture=image, metallicFactor=0.0, roughnessFactor=1.0)
        return cached[c]

    def _plain(self, pts: np.ndarray, nrm: np.ndarray | None, tmp: Path) -> None:
        """``.ply``, ``.stl``, ``.off`` through trimesh (one mesh)."""
        import trimesh
        from trimesh.visual import TextureVisuals
        from trimesh.visual.material import PBRMaterial
        visual = (None if self.uvs is None else
                  TextureVisuals(uv=self.uvs, material=PBRMaterial()))  # no texture image
        mesh = trimesh.Trimesh(pts, self.faces, process=False, vertex_normals=nrm, visual=visual)
        exported = mesh.export(file_type=self.suffix.lstrip("."))
        data = exported if isinstance(exported, bytes) else str(exported).encode()
        if self.suffix == ".ply" and self.comment:  # a comment line after the format line
            head, sep, rest = data.partition(b"\n")
            data = head + sep + f"comment {self.comment}\n".encode() + rest
        Path(tmp).write_bytes(data)

    def commit(self) -> list[Path]:
        """Put every written file in place; returns their paths."""
        return self.group.commit()

    def discard(self) -> None:
        self.group.discard()


def _rows(tag: str, values: np.ndarray) -> str:
    """``tag x y z`` lines, 9 significant digits (float32 round-trips)."""
    cols = values.shape[1]
    fmt = tag + (" %.9g" * cols)
    return "\n".join(fmt % tuple(r) for r in values.tolist())


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
