"""dqskin: dual-quaternion and linear-blend character skinning on NVIDIA Warp.

Conventions (one place each): quaternions ``(..., 4)`` ``(w, x, y, z)``; dual quaternions
``(..., 8)`` ``(rw, rx, ry, rz, dw, dx, dy, dz)`` with pose ``r + ε·½·t·r``; 4×4 matrices in the
column-vector convention ``p' = M @ [p, 1]``; joints ordered parents first, ``parents[j] == -1``
for roots; float32 on the device.
"""

from . import dq, dual, quat
from .animation import Animation, KeyedAnimation
from .baking import bake
from .formats import load, load_mesh
from .scene import Mesh, Scene, SkinnedFrames
from .skeleton import Skeleton, forward_kinematics
from .skinning import METHODS, Skinner, skin_normals, skin_points

__all__ = ["METHODS", "Animation", "KeyedAnimation", "Mesh", "Scene", "Skeleton", "Skinner",
           "SkinnedFrames", "bake", "dq", "dual", "forward_kinematics", "load", "load_mesh", "quat",
           "skin_normals", "skin_points"]
