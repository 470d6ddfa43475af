"""The spaces skinned results are reported in, and the transform track that takes a mesh there.

Skinning produces points in skeleton (bind) space; a :class:`~dqskin.scene.Mesh` carries the
tracks that move them on: ``output_transforms`` (skeleton → the mesh's local space) and
``world_transforms`` (skeleton → world). Normals follow a track by its inverse transpose and
velocities by the chain rule through its time derivative (:meth:`dqskin.Scene.skin`).
"""

from typing import TYPE_CHECKING, Literal, cast, get_args

from .errors import InputError, Param

if TYPE_CHECKING:
    from .animation import TransformTrack
    from .scene import Mesh

__all__ = ["SPACES", "Space", "check_space", "space_track"]

Space = Literal["local", "world", "skeleton"]
"""Where results are reported:

``"local"``
    The mesh's own space (a USD prim's local space; the world for glTF, BVH and rigged meshes).
``"world"``
    World space, in the scene's length unit and up axis (``Scene.meters_per_unit``,
    ``Scene.up_axis``): a USD prim's local-to-world applied to its local space.
``"skeleton"``
    The skeleton's (bind) space, before any transform of the mesh or skeleton prims.
"""

SPACES = get_args(Space)
"""Every :data:`Space`, in order."""


def check_space(space: str) -> Space:
    """``space`` when it is one of :data:`SPACES`, else :class:`~dqskin.errors.InputError`."""
    if space not in SPACES:
        raise InputError(Param("space", space),
                         f": must be one of {', '.join(map(repr, SPACES))}")
    return cast(Space, space)


def space_track(mesh: "Mesh", space: Space) -> "TransformTrack | None":
    """The track taking ``mesh``'s skeleton-space results to ``space`` (None: none needed).

    Parameters
    ----------
    mesh : dqskin.scene.Mesh
    space : {"local", "world", "skeleton"}

    Returns
    -------
    dqskin.animation.TransformTrack or None
        ``mesh.output_transforms`` for "local"; ``mesh.world_transforms`` for
        "world", falling back to ``output_transforms`` when None; None for "skeleton".

    Raises
    ------
    InputError
        ``space`` is not one of :data:`SPACES`.
    """
    if check_space(space) == "skeleton":
        return None
    if space == "world" and mesh.world_transforms is not None:
        return mesh.world_transforms
    return mesh.output_transforms
