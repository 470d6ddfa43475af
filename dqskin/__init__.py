"""dqskin: dual-quaternion and linear-blend character skinning on NVIDIA Warp.

Conventions (one place each): quaternions ``(..., 4)`` ``(w, x, y, z)``; dual quaternions
``(..., 8)`` ``(rw, rx, ry, rz, dw, dx, dy, dz)`` with pose ``r + ε·½·t·r``; 4×4 matrices in the
column-vector convention ``p' = M @ [p, 1]``; joints ordered parents first, ``parents[j] == -1``
for roots; float32 on the device.
"""

import importlib

# Public name → the module that defines it. Imported on first use (PEP 562), so that
# ``python -m dqskin.cli`` can install its signal handlers before Warp and USD load.
_EXPORTS = {
    "METHODS": "skinning", "Skinner": "skinning", "skin_normals": "skinning",
    "skin_points": "skinning", "Animation": "animation", "KeyedAnimation": "animation",
    "bake": "baking", "Crowd": "crowd", "load": "readers", "load_mesh": "readers.mesh",
    "Mesh": "scene", "Scene": "scene", "SkinnedFrames": "scene", "Skeleton": "skeleton",
    "forward_kinematics": "skeleton", "dq": None, "dual": None, "quat": None,
    "automatic_weights": "autoweights", "rig_mesh": "rigging", "replace_weights": "rigging",
    "autoweights": None, "rigging": None, "errors": None, "DqskinError": "errors",
    "InputError": "errors", "Interrupted": "errors", "LimitError": "errors",
    "OutputExistsError": "errors", "UnknownNameError": "errors",
    "SkinOptions": "options", "CorOptions": "options", "BakeSettings": "baking",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dqskin' has no attribute {name!r}")
    module = importlib.import_module(f".{_EXPORTS[name] or name}", __name__)
    value = module if _EXPORTS[name] is None else getattr(module, name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
