"""File formats: what dqskin reads and writes, one module per format.

Each format module owns its suffixes (``SUFFIXES``) and its loader; :func:`load` dispatches on
them. Characters: :mod:`.usd` (UsdSkel) and :mod:`.gltf` (glTF 2.0 skins); motion capture:
:mod:`.bvh` (a skeleton and its animation, no mesh). Outputs:
:mod:`.usd_cache` (USD point caches), :mod:`.npz`, :mod:`.mesh_files` (one trimesh file per
frame; also :func:`load_mesh` for plain geometry). Every writer goes through
:func:`.atomic.atomic_path`.
"""

import os
from pathlib import Path
from types import ModuleType

from ..errors import InputError
from ..scene import Scene
from . import bvh, gltf, usd
from .atomic import atomic_path
from .mesh_files import load_mesh

__all__ = ["CHARACTER_SUFFIXES", "atomic_path", "format_of", "load", "load_mesh"]

_LOADERS = {**{s: usd.load for s in usd.SUFFIXES}, **{s: gltf.load for s in gltf.SUFFIXES},
            **{s: bvh.load for s in bvh.SUFFIXES}}

CHARACTER_SUFFIXES = tuple(_LOADERS)
"""Suffixes :func:`load` reads."""


def format_of(path: str | os.PathLike) -> ModuleType | None:
    """The format module that reads ``path`` (:mod:`.usd` or :mod:`.gltf`), by suffix, or None."""
    suffix = Path(path).suffix.lower()
    return usd if suffix in usd.SUFFIXES else gltf if suffix in gltf.SUFFIXES else None


def load(path: str | os.PathLike, *, clip: str | int | None = None) -> Scene:
    """Read a skinned character.

    Parameters
    ----------
    path : str or Path
        ``.usd/.usda/.usdc/.usdz`` (UsdSkel), ``.gltf/.glb`` (glTF 2.0 skins) or ``.bvh`` (a
        skeleton and its motion, no meshes; times are frame numbers).
    clip : str or int, optional
        glTF animation to load (name or index); the first by default.

    Returns
    -------
    dqskin.scene.Scene
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file")
    loader = _LOADERS.get(p.suffix.lower())
    if loader is None:
        raise InputError(f"{p}: unsupported file type {p.suffix.lower()!r}; expected one of "
                         f"{', '.join(CHARACTER_SUFFIXES)}")
    return loader(p, clip=clip)
