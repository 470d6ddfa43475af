"""One validation for every command and output format: what ``dqskin info`` lists as problems is
exactly what ``dqskin skin`` (every writer) and the Python API refuse.

* :func:`check_transforms`: 4×4 joint transforms must be finite and representable in float32
  (the device precision); the error names the argument, frame and joint.
* :func:`check_skinned`: skinned results (points, normals, velocities) must be finite; the error
  names the mesh, what and the time.
* :func:`scene_problems`: every problem of a loaded scene at its times, as lines (``info``);
  :func:`check_scene` raises the first (``skin`` checks the transforms before writing anything,
  then every skinned chunk with :func:`check_skinned`).
"""

import numpy as np

__all__ = ["FLOAT32_MAX", "check_scene", "check_skinned", "check_transforms", "scene_problems"]

FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest magnitude a value may have to survive the device's float32."""


def _where(index, joint_names=None, times=None):
    """"frame F, joint 'name'" (or "time T, ...") for a flat (frame, joint) index."""
    f, j = (int(i) for i in index[-2:])
    joint = repr(joint_names[j]) if joint_names is not None and j < len(joint_names) else str(j)
    frame = f"time {float(times[f]):g}" if times is not None else f"frame {f}"
    return f"{frame}, joint {joint}"


def check_transforms(name, transforms, joint_names=None, times=None):
    """Raise ValueError unless every entry of ``transforms`` (..., J, 4, 4) is finite and within
    float32 range; the message names ``name``, the first bad frame (flattened leading axes; its
    time when ``times`` is given) and joint (by name when ``joint_names`` is given). Returns the
    transforms as float64."""
    x = np.asarray(transforms)
    if np.iscomplexobj(x):
        raise ValueError(f"{name}: complex values are not transforms")
    x = np.asarray(x, dtype=np.float64)
    lead = x.reshape((-1,) + x.shape[-3:]) if x.ndim >= 3 else x.reshape(1, -1, 4, 4)
    finite = np.isfinite(lead).all(axis=(-2, -1))
    if not finite.all():
        where = _where(np.argwhere(~finite)[0], joint_names, times)
        raise ValueError(f"{name}: NaN or infinite entry at {where}")
    big = (np.abs(lead) > FLOAT32_MAX).any(axis=(-2, -1))
    if big.any():
        where = _where(np.argwhere(big)[0], joint_names, times)
        raise ValueError(f"{name}: entry beyond float32 range (|x| > {FLOAT32_MAX:.3g}) at {where}")
    return x


def check_skinned(path, result):
    """Raise ValueError if any array of a :class:`dqskin.scene.SkinnedFrames` is not finite (joint
    transforms too large for float32, or degenerate), naming the mesh, the array and the time."""
    for what in ("points", "normals", "velocities"):
        for mesh, a in getattr(result, what).items():
            bad = ~np.isfinite(np.asarray(a)).all(axis=tuple(range(1, np.ndim(a))))
            if bad.any():
                t = float(result.times[int(np.argmax(bad))])
                raise ValueError(f"{path}: {mesh}: skinned {what} are NaN or infinite at time "
                                 f"{t:g} (joint transforms out of float32 range?)")


def scene_problems(scene, times=None, *, skin=True, device=None):
    """Every problem of ``scene`` at ``times`` (default its own): unusable bind transforms,
    non-finite or out-of-range animated joint transforms, and with ``skin`` non-finite skinned
    results. Returns a list of one-line messages (empty when the scene can be skinned and
    written)."""
    t = scene.times if times is None else np.atleast_1d(np.asarray(times, dtype=np.float64))
    problems = []
    usable = set()
    for s, skel in enumerate(scene.skeletons):
        try:
            skel.inverse_bind_transforms  # noqa: B018  (raises for a singular bind pose)
            scene.local_transforms(t, s)  # raises for NaN, infinite or out-of-range transforms
            usable.add(s)
        except ValueError as exc:
            problems.append(str(exc))
    if skin and usable and scene.meshes and all(m.skeleton in usable for m in scene.meshes):
        try:
            check_skinned(scene.path, scene.skin(t, device=device))
        except ValueError as exc:
            problems.append(str(exc))
    return problems


def check_scene(scene, times=None, *, skin=False, device=None):
    """Raise the first of :func:`scene_problems` as a ValueError (nothing when there is none).
    Writers check the joint transforms up front (``skin=False``) and each skinned chunk with
    :func:`check_skinned` as it comes."""
    problems = scene_problems(scene, times, skin=skin, device=device)
    if problems:
        raise ValueError(problems[0] if len(problems) == 1 else
                         f"{problems[0]} (and {len(problems) - 1} more problems; see dqskin info)")
