"""File I/O entry points: :func:`load` for characters, :func:`load_mesh` for plain geometry, and the
per-frame writers (mesh files through trimesh, ``.npz``). The USD point cache lives in
:mod:`dqskin.usd_cache`.
"""

import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["USD_SUFFIXES", "GLTF_SUFFIXES", "MESH_SUFFIXES", "atomic_path", "frame_paths", "load",
           "load_mesh", "write_frames"]

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
GLTF_SUFFIXES = (".gltf", ".glb")
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb")


def load(path, *, clip=None):
    """Read a skinned character.

    Parameters
    ----------
    path : str or Path
        ``.usd/.usda/.usdc/.usdz`` (UsdSkel) or ``.gltf/.glb`` (glTF 2.0 skins).
    clip : str or int, optional
        glTF animation to load (name or index); the first by default.

    Returns
    -------
    dqskin.scene.Scene
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such file")
    suffix = p.suffix.lower()
    if suffix in USD_SUFFIXES:
        if clip is not None:
            raise ValueError(f"{p}: --clip applies to glTF files; USD has one animation per skeleton")
        from .usd import load_usd
        return load_usd(p)
    if suffix in GLTF_SUFFIXES:
        from .gltf import load_gltf
        return load_gltf(p, clip=clip)
    raise ValueError(f"{p}: unsupported file type {suffix!r}; expected one of "
                     f"{', '.join(USD_SUFFIXES + GLTF_SUFFIXES)}")


def load_mesh(path):
    """Geometry of a plain mesh file through trimesh: ``(points (V, 3) float32, faces (T, 3) int32)``."""
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


def _umask():
    """The process umask, read without changing it (Linux ``/proc``), else set-and-restore."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


class atomic_path:
    """Context manager yielding a temporary path beside ``path``, moved onto it on success.

    The temporary file keeps the extension so format-sniffing writers (USD, trimesh) work.
    """

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self):
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=self.path.suffix,
                                   dir=self.path.parent)
        os.close(fd)
        self.tmp = Path(tmp)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            os.chmod(self.tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
        return False


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
        e.g. ``"out/frame_{:04d}.obj"``; ``.obj .ply .stl .off .glb``.
    frame_numbers : (F,) int
    points : (F, V, 3) float
    faces : (T, 3) int
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
