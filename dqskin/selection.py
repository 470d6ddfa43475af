"""Which meshes a bake skins and writes: the ``prims`` patterns (``dqskin skin --prims``).

A pattern is a comma-separated list of shell-style globs (``fnmatch``, case-sensitive) matched
against each mesh's name (a USD prim path, a glTF node name); a glob also matches everything
below a path it matches (``/Root/Body`` selects ``/Root/Body/Mesh``). Globs starting with ``!``
or ``-`` exclude; the others include. Without an include glob every mesh is included, then the
excluded ones are removed: ``/Root/Body*,!*/Eyes`` or ``!/Root/Curves``.
"""

import dataclasses
from fnmatch import fnmatchcase
from typing import TYPE_CHECKING

from .errors import InputError, Param

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["matches", "select_meshes"]


def matches(name: str, glob: str) -> bool:
    """Whether mesh ``name`` is ``glob`` or below a path ``glob`` matches."""
    return fnmatchcase(name, glob) or fnmatchcase(name, glob.rstrip("/") + "/*")


def select_meshes(scene: "Scene", prims: str | None) -> tuple["Scene", list[str]]:
    """``scene`` with only the meshes ``prims`` selects (the same Scene when None), and the
    names of the meshes it leaves out.

    Parameters
    ----------
    scene : dqskin.Scene
    prims : str or None
        The pattern (see the module docstring).

    Returns
    -------
    (dqskin.Scene, list of str)
        A scene sharing everything with ``scene`` but its list of meshes.

    Raises
    ------
    InputError
        Naming ``prims``: an empty glob, an include glob that matches no mesh, or no mesh left.
    """
    if prims is None:
        return scene, []
    if not isinstance(prims, str):
        raise InputError(Param("prims", prims), ": expected comma-separated globs")
    globs = [g.strip() for g in prims.split(",")]
    if not all(globs) or any(g in ("!", "-") for g in globs):
        raise InputError(Param("prims", prims), ": an empty glob")
    include = [g for g in globs if g[0] not in "!-"]
    exclude = [g[1:] for g in globs if g[0] in "!-"]
    names = [m.name for m in scene.meshes]
    for g in include:
        if not any(matches(n, g) for n in names):
            raise InputError(Param("prims", prims), f": {g!r} matches no mesh; meshes: "
                             f"{', '.join(names)}")
    kept = [m for m in scene.meshes
            if (not include or any(matches(m.name, g) for g in include))
            and not any(matches(m.name, g) for g in exclude)]
    if not kept:
        raise InputError(Param("prims", prims), f": selects no mesh; meshes: {', '.join(names)}")
    if len(kept) == len(scene.meshes):
        return scene, []
    chosen = {id(m) for m in kept}
    left = [m.name for m in scene.meshes if id(m) not in chosen]
    return dataclasses.replace(scene, meshes=kept), left
