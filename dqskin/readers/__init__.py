"""Readers: what dqskin reads into a :class:`~dqskin.scene.Scene`, one module per format.

Each format module owns its suffixes (``SUFFIXES``) and its loader; :func:`load` dispatches on
them. Characters: :mod:`.usd` (UsdSkel), :mod:`.gltf` (glTF 2.0 skins)
and :mod:`.fbx` (FBX skins, read by ufbx in a process of its own); motion capture:
:mod:`.bvh` (a skeleton and its animation, no mesh). Plain geometry: :mod:`.mesh`
(:func:`~.mesh.load_mesh`). Outputs: :mod:`dqskin.writers`; the file machinery they share:
:mod:`dqskin.files`. The suffixes are listed here (:data:`LOADER_SUFFIXES`) so that a format
module is imported on first use: importing this package loads neither USD nor a loader.
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

from ..errors import InputError
from ..files.inputs import regular_file
from ..limits import MAX_INPUT_GIB

if TYPE_CHECKING:
    from ..scene import Scene

__all__ = ["CHARACTER_SUFFIXES", "LOADER_SUFFIXES", "format_of", "load"]

LOADER_SUFFIXES = {"usd": (".usd", ".usda", ".usdc", ".usdz"), "gltf": (".gltf", ".glb"),
                   "bvh": (".bvh",), "fbx": (".fbx",)}
"""Loader module (of this package) → the suffixes it reads (each module's ``SUFFIXES``)."""

_LOADERS = {s: module for module, suffixes in LOADER_SUFFIXES.items() for s in suffixes}

CHARACTER_SUFFIXES = tuple(_LOADERS)
"""Suffixes :func:`load` reads."""


def _loader(name: str) -> ModuleType:
    return importlib.import_module(f".{name}", __name__)


def format_of(path: str | os.PathLike) -> ModuleType | None:
    """The format module that reads the character file ``path`` (:mod:`.usd`, :mod:`.gltf` or
    :mod:`.fbx`), by suffix, or None."""
    name = _LOADERS.get(Path(path).suffix.lower())
    return _loader(name) if name in ("usd", "gltf", "fbx") else None


def load(path: str | os.PathLike, *, clip: str | int | None = None,
         max_input_gib: float = MAX_INPUT_GIB) -> Scene:
    """Read a skinned character.

    Parameters
    ----------
    path : str or Path
        ``.usd/.usda/.usdc/.usdz`` (UsdSkel), ``.gltf/.glb`` (glTF 2.0 skins), ``.fbx`` (FBX
        skins, through ufbx; times are seconds) or ``.bvh`` (a skeleton and its motion, no
        meshes; times are frame numbers).
    clip : str or int, optional
        glTF animation or FBX animation stack to load (name or index); the first by default.
    max_input_gib : float
        Largest array a glTF, BVH or FBX file may ask for before its data is read
        (:mod:`dqskin.limits`); beyond it LimitError.

    Returns
    -------
    dqskin.scene.Scene
    """
    p = regular_file(path)
    loader = _LOADERS.get(p.suffix.lower())
    if loader is None:
        raise InputError(f"{p}: unsupported file type {p.suffix.lower()!r}; expected one of "
                         f"{', '.join(CHARACTER_SUFFIXES)}")
    return _loader(loader).load(p, clip=clip, max_input_gib=max_input_gib)
