"""Write the procedural UsdSkel test rigs into ``assets/`` (see ``assets/README.md``).

Usage::

    python tools/make_assets.py [--out DIR]     # DIR defaults to the repository's assets/

Three rigs, each one ``.usda`` file with a ``SkelRoot``, a ``Skeleton``, a ``SkelAnimation`` and
closed (watertight) ``Mesh`` prims carrying vertex normals, face-varying UVs (``primvars:st``) and
vertex-interpolated joint influences:

* ``twist_cylinder.usda`` — the candy wrapper: a child joint twists 0→180° about the bone axis.
* ``bending_arm.usda`` — a forearm bends 0→150° about an axis perpendicular to the bone.
* ``humanoid.usda`` — a 17-joint figure in centimetres walking in place (48 frames, looping).

Output is deterministic: every value is rounded before it reaches USD, so one usd-core version
writes the same bytes on every machine. Conventions inside: 4×4 matrices column-vector
(``p' = M @ [p, 1]``), transposed to USD's row-vector form only when written; quaternions
``(w, x, y, z)``.
"""

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

from dqskin.files.atomic import atomic_path

__all__ = ["RigSpec", "MeshSpec", "twist_cylinder", "bending_arm", "humanoid", "author_rig",
           "write_assets", "main"]

TIME_CODES_PER_SECOND = 24.0
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "assets"


# --------------------------------------------------------------------------------------------
# Containers
# --------------------------------------------------------------------------------------------

@dataclass
class MeshSpec:
    """One skinned mesh, in skeleton space (its geomBindTransform is identity).

    Attributes
    ----------
    name : str
        Prim name under the SkelRoot.
    points : (V, 3) float64
    face_counts, face_indices : (P,) int, (sum(face_counts),) int
        Polygons, counter-clockwise seen from outside (USD ``rightHanded``).
    st, st_indices : (U, 2) float64, (sum(face_counts),) int
        Face-varying, indexed texture coordinates.
    joint_indices, joint_weights : (V, K) int, (V, K) float64
        Influences in skeleton joint order; each row sums to 1.
    color : (3,) float
        ``primvars:displayColor``.
    """

    name: str
    points: np.ndarray
    face_counts: np.ndarray
    face_indices: np.ndarray
    st: np.ndarray
    st_indices: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    color: tuple


@dataclass
class RigSpec:
    """Everything one ``.usda`` file holds.

    Attributes
    ----------
    root : str
        SkelRoot prim name (the default prim).
    doc : str
        Layer documentation string.
    meters_per_unit : float
    joints : list of str
        Joint paths, parents first.
    bind : (J, 4, 4) float64
        World-space bind transforms, column-vector convention.
    rest : (J, 4, 4) float64
        Parent-relative rest transforms (equal to the bind pose here).
    frames : (F,) int
        Time codes of the animation samples.
    translations, rotations, scales : (F, J, 3), (F, J, 4) (w, x, y, z), (F, J, 3) float64
        Parent-relative animation samples.
    meshes : list of MeshSpec
    """

    root: str
    doc: str
    meters_per_unit: float
    joints: list
    bind: np.ndarray
    rest: np.ndarray
    frames: np.ndarray
    translations: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    meshes: list


# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------

AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def quat_axis_angle(axis, degrees):
    """(4,) (w, x, y, z) rotation by ``degrees`` about ``axis`` (a key of AXES or a 3-vector)."""
    a = np.asarray(AXES.get(axis, axis) if isinstance(axis, str) else axis, dtype=np.float64)
    h = np.radians(degrees) / 2.0
    return np.concatenate([[np.cos(h)], np.sin(h) * a / np.linalg.norm(a)])


def quat_mul(a, b):
    """Hamilton product ``a ⊗ b`` of (4,) (w, x, y, z) quaternions."""
    w1, v1, w2, v2 = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def quat_conj(q):
    """Conjugate (the inverse of a unit quaternion), (w, x, y, z)."""
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_matrix(q):
    """(3, 3) rotation matrix of a unit (w, x, y, z) quaternion."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rigid(q, t):
    """(4, 4) column-convention transform: rotate by quaternion ``q``, then translate by ``t``."""
    m = np.eye(4)
    m[:3, :3] = quat_matrix(q)
    m[:3, 3] = t
    return m


def quat_product(*factors):
    """Product of ``(axis, degrees)`` rotations, leftmost applied last."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for axis, deg in factors:
        q = quat_mul(q, quat_axis_angle(axis, deg))
    return q


# --------------------------------------------------------------------------------------------
# Geometry: closed tubes
# --------------------------------------------------------------------------------------------

def ramp(t, kind):
    """Weight ramp on ``t`` clipped to [0, 1]: ``"linear"`` or ``"smooth"`` (smoothstep)."""
    t = np.clip(t, 0.0, 1.0)
    return t if kind == "linear" else t * t * (3.0 - 2.0 * t)


def tube(stations, segments):
    """A closed tube along +X: rings of ellipses between two pole vertices.

    Parameters
    ----------
    stations : (R, 3) float
        Rows ``(s, a, b)``: ring at ``x = s`` with half-axes ``a`` along Y and ``b`` along Z.
        The first and last rows are poles (``a = b = 0``); flat caps are rings sharing one ``s``.
    segments : int
        Vertices per ring.

    Returns
    -------
    points (V, 3), face_counts, face_indices, st (U, 2), st_indices — outward-facing polygons:
    quads between rings, triangle fans at the poles; UV ``u`` around (seam duplicated), ``v``
    along the profile's arc length.
    """
    st_ = np.asarray(stations, dtype=np.float64)
    s, a, b = st_.T
    R, N = len(st_), segments
    phi = 2.0 * np.pi * np.arange(N) / N
    ring = np.stack([np.repeat(s[1:-1], N), np.outer(a[1:-1], np.cos(phi)).ravel(),
                     np.outer(b[1:-1], np.sin(phi)).ravel()], axis=1)
    points = np.concatenate([[[s[0], 0, 0]], ring, [[s[-1], 0, 0]]])
    last = len(points) - 1

    def vid(i, k):  # vertex of ring i (1..R-2), column k (wraps)
        return 1 + (i - 1) * N + k % N

    def uid(i, k):  # uv of row i (0..R-1), column k (0..N, seam duplicated)
        return i * (N + 1) + k

    counts, verts, uvs = [], [], []
    for k in range(N):
        counts.append(3)
        verts += [0, vid(1, k + 1), vid(1, k)]
        uvs += [uid(0, k), uid(1, k + 1), uid(1, k)]
    for i in range(1, R - 2):
        for k in range(N):
            counts.append(4)
            verts += [vid(i, k), vid(i, k + 1), vid(i + 1, k + 1), vid(i + 1, k)]
            uvs += [uid(i, k), uid(i, k + 1), uid(i + 1, k + 1), uid(i + 1, k)]
    for k in range(N):
        counts.append(3)
        verts += [vid(R - 2, k), vid(R - 2, k + 1), last]
        uvs += [uid(R - 2, k), uid(R - 2, k + 1), uid(R - 1, k)]
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(s), np.diff((a + b) / 2.0)))])
    v = np.repeat(arc / arc[-1], N + 1)
    u = np.tile(np.arange(N + 1) / N, R).reshape(R, N + 1)
    u[[0, -1]] = (np.arange(N + 1) + 0.5) / N  # pole rows: mid-segment u
    st = np.stack([u.ravel(), v], axis=1)
    return points, np.array(counts), np.array(verts), st, np.array(uvs)


def vertex_normals(points, face_counts, face_indices):
    """(V, 3) unit area-weighted vertex normals of fan-triangulated polygons."""
    acc = np.zeros_like(points)
    start = np.concatenate([[0], np.cumsum(face_counts)[:-1]])
    for n in np.unique(face_counts):
        sel = start[face_counts == n]
        for j in range(1, n - 1):
            i0, i1, i2 = (face_indices[sel], face_indices[sel + j], face_indices[sel + j + 1])
            c = np.cross(points[i1] - points[i0], points[i2] - points[i0])
            for i in (i0, i1, i2):
                np.add.at(acc, i, c)
    return acc / np.linalg.norm(acc, axis=1, keepdims=True)


def pchip(xk, yk, x):
    """Monotone piecewise-cubic (Fritsch–Carlson) interpolation of keys ``(xk, yk)`` at ``x``."""
    xk, yk = np.asarray(xk, float), np.asarray(yk, float)
    h, d = np.diff(xk), np.diff(yk) / np.diff(xk)
    m = np.zeros_like(yk)
    m[0], m[-1] = d[0], d[-1]
    w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
    same = d[:-1] * d[1:] > 0
    m[1:-1][same] = (w1 + w2)[same] / (w1[same] / d[:-1][same] + w2[same] / d[1:][same])
    k = np.clip(np.searchsorted(xk, x, side="right") - 1, 0, len(h) - 1)
    t = (x - xk[k]) / h[k]
    return (yk[k] * (2 * t ** 3 - 3 * t ** 2 + 1) + h[k] * m[k] * (t ** 3 - 2 * t ** 2 + t)
            + yk[k + 1] * (-2 * t ** 3 + 3 * t ** 2) + h[k] * m[k + 1] * (t ** 3 - t ** 2))


def capsule_stations(keys, caps, step, cap_rings=4):
    """Stations of a tube with a smooth profile and rounded (quarter-ellipse) ends.

    Parameters
    ----------
    keys : (K, 3) float
        Profile keys ``(s, a, b)``; the tube spans ``keys[0, 0] .. keys[-1, 0]``.
    caps : (float, float)
        Length of the rounded start and end caps along ``s``.
    step : float
        Target ring spacing between the caps.
    """
    keys = np.asarray(keys, dtype=np.float64)
    s0, s1 = keys[0, 0], keys[-1, 0]
    psi = np.linspace(0.0, np.pi / 2, cap_rings + 1)[:-1]
    n = int(np.ceil((s1 - s0 - caps[0] - caps[1]) / step))
    s = np.concatenate([s0 + caps[0] * (1 - np.cos(psi)),
                        np.linspace(s0 + caps[0], s1 - caps[1], n + 1),
                        (s1 - caps[1] * (1 - np.cos(psi)))[::-1]])
    scale = np.concatenate([np.sin(psi), np.ones(n + 1), np.sin(psi)[::-1]])
    return np.stack([s, pchip(keys[:, 0], keys[:, 1], s) * scale,
                     pchip(keys[:, 0], keys[:, 2], s) * scale], axis=1)


def cylinder_stations(radius, length, side_rings, cap_rings=4):
    """Stations of a flat-capped cylinder ``0 <= x <= length``: concentric cap rings, one
    ring every ``length / side_rings`` along the side (rims shared by side and caps)."""
    cap = radius * np.arange(1, cap_rings) / cap_rings
    side = length * np.arange(side_rings + 1) / side_rings
    rows = ([(0.0, 0.0, 0.0)] + [(0.0, r, r) for r in cap] + [(x, radius, radius) for x in side]
            + [(length, r, r) for r in cap[::-1]] + [(length, 0.0, 0.0)])
    return np.array(rows)


def chain_weights(s, bounds, kind):
    """(V, n) weights of an n-joint chain along coordinate ``s``.

    ``bounds`` holds ``n - 1`` rows ``(center, width)``: the hand-over from chain joint ``k`` to
    ``k + 1`` ramps over ``center ± width / 2``. Weights are products of the ramps, so they sum
    to 1 even where ramps overlap (three influences there).
    """
    t = [ramp((s - (c - w / 2)) / w, kind) for c, w in bounds]
    out, carry = [], np.ones_like(s)
    for tk in t:
        out.append(carry * (1 - tk))
        carry = carry * tk
    return np.stack(out + [carry], axis=1)


def top_influences(weights, k):
    """(V, J) dense weights → (V, k) indices and weights, heaviest first, renormalized;
    unused slots are index 0 with weight 0."""
    order = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(weights, order, axis=1)
    w = w / w.sum(axis=1, keepdims=True)
    return np.where(w > 0, order, 0), w


def placed_tube(name, stations, segments, rotation, origin, influences, color):
    """A :func:`tube` rotated by quaternion ``rotation`` and moved to ``origin``; ``influences``
    maps the tube-frame points (V, 3) to ``(joint_indices, joint_weights)``."""
    p, counts, verts, st, st_idx = tube(stations, segments)
    idx, w = influences(p)
    world = p @ quat_matrix(rotation).T + origin
    return MeshSpec(name, world, counts, verts, st, st_idx, idx, w, color)


# --------------------------------------------------------------------------------------------
# Rigs
# --------------------------------------------------------------------------------------------

def two_joint_rig(root, doc, joints, child_x, axis, degrees_per_frame, frames, radius, length,
                  ramp_width, mesh_name):
    """A cylinder along +X skinned to a root at x = 0 and a child at ``child_x`` that rotates
    about ``axis`` (through the child joint) by ``degrees_per_frame * frame``; linear weight
    ramp ``(1 - w, w)`` of total width ``ramp_width`` centred on the child joint."""
    ident = np.array([1.0, 0.0, 0.0, 0.0])
    bind = np.stack([np.eye(4), rigid(ident, (child_x, 0.0, 0.0))])
    rest = bind.copy()
    F = len(frames)
    translations = np.tile([[0.0, 0.0, 0.0], [child_x, 0.0, 0.0]], (F, 1, 1))
    rotations = np.stack([[ident, quat_axis_angle(axis, degrees_per_frame * f)] for f in frames])
    scales = np.ones((F, 2, 3))

    def influences(p):
        w = ramp((p[:, 0] - (child_x - ramp_width / 2)) / ramp_width, "linear")
        return np.tile([0, 1], (len(p), 1)), np.stack([1 - w, w], axis=1)

    mesh = placed_tube(mesh_name, cylinder_stations(radius, length, 64), 32, ident,
                       np.zeros(3), influences, (0.8, 0.6, 0.3))
    return RigSpec(root, doc, 1.0, joints, bind, rest, np.asarray(frames), translations,
                   rotations, scales, [mesh])


def twist_cylinder():
    """The candy wrapper: radius 1, length 4 along +X, child joint at x = 2 twisting 0→180°
    about +X over frames 0..24 (7.5° per frame); linear ramp over x ∈ [1, 3] (f = 0.5)."""
    return two_joint_rig(
        "TwistCylinder",
        "Candy-wrapper rig: closed cylinder along +X, radius 1, length 4 (metersPerUnit 1). "
        "Joints root (x=0) and root/twist (x=2); root/twist rotates about +X by 7.5 deg per "
        "frame, 0..180 deg over frames 0..24. Weights (1-w, w), w linear in x from 0 at x=1 "
        "to 1 at x=3 (ramp width 0.5 of the length). Generated by tools/make_assets.py.",
        ["root", "root/twist"], 2.0, "x", 7.5, range(25), 1.0, 4.0, 2.0, "Cylinder")


def bending_arm():
    """A radius-0.5, length-4 arm along +X; the elbow (x = 2) bends 0→150° about +Z over frames
    0..30 (5° per frame); linear ramp over x ∈ [1.5, 2.5] (f = 0.25)."""
    return two_joint_rig(
        "BendingArm",
        "Bending-arm rig: closed cylinder along +X, radius 0.5, length 4 (metersPerUnit 1). "
        "Joints shoulder (x=0) and shoulder/elbow (x=2); the elbow rotates about +Z by 5 deg "
        "per frame, 0..150 deg over frames 0..30. Weights (1-w, w), w linear in x from 0 at "
        "x=1.5 to 1 at x=2.5 (ramp width 0.25 of the length). Generated by "
        "tools/make_assets.py.",
        ["shoulder", "shoulder/elbow"], 2.0, "z", 5.0, range(31), 0.5, 4.0, 1.0, "Arm")


# Bone frames (joint local X along the bone), as quaternions in world (skeleton) space.
UP = quat_axis_angle("z", 90.0)      # local X → +Y (spine, neck, head)
LEFT = np.array([1.0, 0.0, 0.0, 0.0])  # local X → +X (character's left arm)
RIGHT = quat_axis_angle("y", 180.0)  # local X → -X
DOWN = quat_axis_angle("z", -90.0)   # local X → -Y (legs)
FORWARD = quat_axis_angle("y", -90.0)  # local X → +Z (feet)

# name, parent, head position (cm), bone frame
HUMANOID_JOINTS = [
    ("pelvis", None, (0, 95, 0), UP),
    ("spine", "pelvis", (0, 108, 0), UP),
    ("chest", "spine", (0, 125, 0), UP),
    ("neck", "chest", (0, 148, 0), UP),
    ("head", "neck", (0, 158, 0), UP),
    ("shoulder_L", "chest", (17, 143, 0), LEFT),
    ("elbow_L", "shoulder_L", (45, 143, 0), LEFT),
    ("wrist_L", "elbow_L", (71, 143, 0), LEFT),
    ("shoulder_R", "chest", (-17, 143, 0), RIGHT),
    ("elbow_R", "shoulder_R", (-45, 143, 0), RIGHT),
    ("wrist_R", "elbow_R", (-71, 143, 0), RIGHT),
    ("hip_L", "pelvis", (9, 92, 0), DOWN),
    ("knee_L", "hip_L", (9, 50, 0), DOWN),
    ("ankle_L", "knee_L", (9, 8, 0), DOWN),
    ("hip_R", "pelvis", (-9, 92, 0), DOWN),
    ("knee_R", "hip_R", (-9, 50, 0), DOWN),
    ("ankle_R", "knee_R", (-9, 8, 0), DOWN),
]

WALK_FRAMES = 48
WRIST_TWIST_DEGREES = 100.0


def walk_pose(f):
    """World-axis rotations ``{joint: quaternion}`` and the pelvis position at frame ``f``.

    Each rotation is expressed in the skeleton's axes *at rest* and applied in the joint's
    frame (so it moves with the parent): the local rotation is ``B_parent⁻¹ · R · B_joint``.
    Phase ``p = 2π f / 48``; the right side runs half a cycle behind the left.
    """
    p = 2.0 * np.pi * f / WALK_FRAMES
    sin, cos = np.sin, np.cos
    rot = {
        "pelvis": quat_product(("y", 5 * sin(p))),
        "spine": quat_product(("x", 3.0), ("y", -2 * sin(p))),
        "chest": quat_product(("y", -6 * sin(p))),
        "neck": quat_product(("y", 2 * sin(p))),
        "head": quat_product(("x", 3 * sin(2 * p))),
    }
    for side, sign, ph in (("L", 1.0, p), ("R", -1.0, p + np.pi)):
        # hip flexion 5 ± 20° (forward positive); knee 5..60° peaking early in the swing
        rot[f"hip_{side}"] = quat_product(("x", -(5 + 20 * sin(ph))))
        rot[f"knee_{side}"] = quat_product(("x", 5 + 55 * ((1 + cos(ph + 0.5)) / 2) ** 2))
        rot[f"ankle_{side}"] = quat_product(("x", 10 * sin(ph - 1.0)))
        # arms lowered 75° from the T-pose, swinging against the same-side leg; elbow 15..55°
        rot[f"shoulder_{side}"] = quat_product(("x", 20 * sin(ph)), ("z", -sign * 75.0))
        rot[f"elbow_{side}"] = quat_product(("y", -sign * (35 - 20 * sin(ph))))
        rot[f"wrist_{side}"] = quat_product(("x", WRIST_TWIST_DEGREES * sin(ph)))
    pelvis = np.array([1.5 * sin(p), 94.0 + 1.2 * cos(2 * p), 0.0])
    return rot, pelvis


def humanoid():
    """A 17-joint figure, 177 cm tall (metersPerUnit 0.01), in a T-pose bind, walking in place
    over frames 0..48 (frame 48 = frame 0). Seven closed meshes: body (pelvis to head), two arms
    with hands, two legs, two feet; up to 4 influences per vertex with smoothstep ramps."""
    names = [j[0] for j in HUMANOID_JOINTS]
    J = len(names)
    index = {n: i for i, n in enumerate(names)}
    parent = [None if j[1] is None else index[j[1]] for j in HUMANOID_JOINTS]
    paths = []
    for n, par, _, _ in HUMANOID_JOINTS:
        paths.append(n if par is None else f"{paths[index[par]]}/{n}")
    head = np.array([j[2] for j in HUMANOID_JOINTS], dtype=np.float64)
    frame = [j[3] for j in HUMANOID_JOINTS]
    bind = np.stack([rigid(frame[j], head[j]) for j in range(J)])
    rest_t = np.array([head[j] if parent[j] is None else
                       quat_matrix(frame[parent[j]]).T @ (head[j] - head[parent[j]])
                       for j in range(J)])
    rest_q = [frame[j] if parent[j] is None else quat_mul(quat_conj(frame[parent[j]]), frame[j])
              for j in range(J)]
    rest = np.stack([rigid(rest_q[j], rest_t[j]) for j in range(J)])

    frames = np.arange(WALK_FRAMES + 1)
    translations = np.tile(rest_t, (len(frames), 1, 1))
    rotations = np.zeros((len(frames), J, 4))
    for fi, f in enumerate(frames):
        rot, pelvis = walk_pose(f)
        translations[fi, 0] = pelvis
        for j in range(J):
            q = quat_mul(rot[names[j]], frame[j])
            rotations[fi, j] = q if parent[j] is None else quat_mul(quat_conj(frame[parent[j]]), q)
    scales = np.ones((len(frames), J, 3))

    def dense(columns, weights):
        full = np.zeros((weights.shape[0], J))
        full[:, [index[c] for c in columns]] = weights
        return full

    def body_influences(p):
        # tube frame: s = p[:, 0] is height above the pelvis joint; -p[:, 1] is world X
        y, x = p[:, 0] + 95.0, -p[:, 1]
        chain = chain_weights(y, [(108, 20), (125, 26), (148, 8), (158, 8)], "smooth")
        lateral = ramp((np.abs(x) - 10.0) / 7.0, "smooth")
        band = ramp((y - 112.0) / 14.0, "smooth") * (1.0 - ramp((y - 142.0) / 4.0, "smooth"))
        sh = 0.4 * lateral * band
        left, right = np.where(x > 0, sh, 0.0), np.where(x < 0, sh, 0.0)
        w = np.concatenate([chain * (1.0 - sh)[:, None], left[:, None], right[:, None]], axis=1)
        return top_influences(dense(["pelvis", "spine", "chest", "neck", "head", "shoulder_L",
                                     "shoulder_R"], w), 4)

    def chain_influences(columns, bounds):
        return lambda p: top_influences(dense(columns, chain_weights(p[:, 0], bounds, "smooth")), 4)

    meshes = [placed_tube(
        "Body", capsule_stations(
            [(-16, 13, 9), (-10, 15, 10.5), (-3, 16, 11), (5, 15, 10), (13, 13.5, 9.5),
             (23, 15, 10), (33, 17, 11), (43, 18, 10.5), (48, 16, 9), (52, 9, 7),
             (55, 5.5, 5.5), (59, 5.8, 5.8), (63, 8, 8.5), (69, 9.5, 10.5), (75, 9, 10),
             (82.5, 7, 8)], caps=(6.0, 8.0), step=2.0),
        24, UP, head[index["pelvis"]], body_influences, (0.55, 0.6, 0.75))]
    for side, frame_q, sign in (("L", LEFT, 1.0), ("R", RIGHT, -1.0)):
        meshes.append(placed_tube(
            f"Arm_{side}", capsule_stations(
                [(-6, 5.5, 5.5), (0, 5.5, 5.5), (14, 4.8, 4.8), (28, 3.9, 4.0), (34, 4.0, 4.4),
                 (50, 2.6, 3.4), (54, 2.4, 3.2), (60, 2.2, 4.6), (66, 2.0, 4.6), (73, 1.6, 3.6)],
                caps=(5.0, 4.0), step=2.0),
            20, frame_q, head[index[f"shoulder_{side}"]],
            chain_influences(["chest", f"shoulder_{side}", f"elbow_{side}", f"wrist_{side}"],
                             [(0, 10), (28, 8), (50, 12)]), (0.85, 0.7, 0.6)))
        meshes.append(placed_tube(
            f"Leg_{side}", capsule_stations(
                [(-7, 7.5, 8), (2, 7.5, 8), (30, 6.2, 6.5), (42, 5.0, 5.0), (55, 5.5, 5.8),
                 (78, 3.5, 3.8), (88, 3.2, 3.5)], caps=(6.0, 3.0), step=2.0),
            20, DOWN, head[index[f"hip_{side}"]],
            chain_influences(["pelvis", f"hip_{side}", f"knee_{side}", f"ankle_{side}"],
                             [(0, 12), (42, 10), (84, 8)]), (0.3, 0.35, 0.5)))
        meshes.append(placed_tube(
            f"Foot_{side}", capsule_stations(
                [(-6, 3.5, 3.8), (2, 4.0, 4.2), (12, 3.2, 4.8), (19, 2.2, 4.2)],
                caps=(3.0, 3.0), step=2.0),
            12, FORWARD, np.array([9.0 * sign, 4.0, 0.0]),
            chain_influences([f"ankle_{side}"], []), (0.25, 0.2, 0.2)))
    doc = ("Walking humanoid: 17 joints in a T-pose bind (joint local X along each bone), "
           "centimetres (metersPerUnit 0.01), Y up, facing +Z, left = +X. Walk cycle in place "
           "over frames 0..48 at 24 fps (frame 48 = frame 0) with knee and elbow bends and "
           "+-100 deg wrist (forearm) twist. Seven closed meshes, up to 4 smoothstep-ramped "
           "influences per vertex; see assets/README.md. Generated by tools/make_assets.py.")
    return RigSpec("Humanoid", doc, 0.01, paths, bind, rest, frames, translations, rotations,
                   scales, meshes)


# --------------------------------------------------------------------------------------------
# USD authoring
# --------------------------------------------------------------------------------------------

def _rounded(a, decimals):
    """``a`` rounded to ``decimals`` places, negative zeros made positive (stable text)."""
    return np.round(np.asarray(a, dtype=np.float64), decimals) + 0.0


def _gf_matrices(m):
    return Vt.Matrix4dArray([Gf.Matrix4d(_rounded(x, 12).T.tolist()) for x in m])


def _vec3f(a, decimals):
    return Vt.Vec3fArray.FromNumpy(_rounded(a, decimals).astype(np.float32))


def _normalized_weights(w, decimals=6):
    """Round weights, then give each row's heaviest slot ``1 - sum(others)`` so rows sum to 1."""
    w = _rounded(w, decimals)
    top = np.argmax(w, axis=1)
    rows = np.arange(len(w))
    w[rows, top] = 0.0
    w[rows, top] = 1.0 - w.sum(axis=1)
    return w


def _author_mesh(stage, path, spec, skel_path, decimals):
    """Define the skinned ``UsdGeom.Mesh`` of a :class:`MeshSpec` at ``path``."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(spec.face_counts.astype(np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(spec.face_indices.astype(np.int32)))
    points = _rounded(spec.points, decimals)
    mesh.CreatePointsAttr(_vec3f(points, decimals))
    mesh.CreateExtentAttr(_vec3f(np.stack([points.min(0), points.max(0)]), decimals))
    normals = vertex_normals(spec.points, spec.face_counts, spec.face_indices)
    mesh.CreateNormalsAttr(_vec3f(normals, 6))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    pv = UsdGeom.PrimvarsAPI(mesh)
    st = pv.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray.FromNumpy(_rounded(spec.st, 6).astype(np.float32)))
    st.SetIndices(Vt.IntArray.FromNumpy(spec.st_indices.astype(np.int32)))
    mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(
        Vt.Vec3fArray([Gf.Vec3f(*spec.color)]))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel_path])
    k = spec.joint_indices.shape[1]
    binding.CreateJointIndicesPrimvar(False, k).Set(
        Vt.IntArray.FromNumpy(spec.joint_indices.astype(np.int32).ravel()))
    binding.CreateJointWeightsPrimvar(False, k).Set(
        Vt.FloatArray.FromNumpy(_normalized_weights(spec.joint_weights).astype(np.float32).ravel()))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))


def author_rig(rig):
    """The ``.usda`` text of a :class:`RigSpec` (deterministic)."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    stage = Usd.Stage.Open(layer)
    layer.documentation = rig.doc
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, rig.meters_per_unit)
    stage.SetTimeCodesPerSecond(TIME_CODES_PER_SECOND)
    stage.SetFramesPerSecond(TIME_CODES_PER_SECOND)
    stage.SetStartTimeCode(float(rig.frames[0]))
    stage.SetEndTimeCode(float(rig.frames[-1]))
    decimals = 6 if rig.meters_per_unit == 1.0 else 4  # 1 µm either way

    root = UsdSkel.Root.Define(stage, f"/{rig.root}")
    stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, f"/{rig.root}/Skeleton")
    skel.CreateJointsAttr(rig.joints)
    skel.CreateJointNamesAttr([j.rsplit("/", 1)[-1] for j in rig.joints])
    skel.CreateBindTransformsAttr(_gf_matrices(rig.bind))
    skel.CreateRestTransformsAttr(_gf_matrices(rig.rest))
    anim = UsdSkel.Animation.Define(stage, f"/{rig.root}/Anim")
    anim.CreateJointsAttr(rig.joints)
    tr, ro, sc = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
    rotations = _rounded(rig.rotations, 7)
    for i, f in enumerate(rig.frames):
        t = Usd.TimeCode(float(f))
        tr.Set(_vec3f(rig.translations[i], decimals), t)
        ro.Set(Vt.QuatfArray([Gf.Quatf(*map(float, q)) for q in rotations[i]]), t)
        sc.Set(Vt.Vec3hArray([Gf.Vec3h(*map(float, s)) for s in rig.scales[i]]), t)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])
    for m in rig.meshes:
        _author_mesh(stage, f"/{rig.root}/{m.name}", m, skel.GetPath(), decimals)
    return layer.ExportToString()


def _write_atomic(path, text):
    """Write ``text`` (UTF-8) to ``path`` through a temporary file in the same folder."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(text.encode("utf-8"))


ASSETS = {"twist_cylinder.usda": twist_cylinder, "bending_arm.usda": bending_arm,
          "humanoid.usda": humanoid}


def write_assets(out=DEFAULT_OUT):
    """Write every rig into folder ``out`` (created if missing); returns the paths written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, build in ASSETS.items():
        _write_atomic(out / name, author_rig(build()))
        written.append(out / name)
    return written


def main(argv=None):
    """Command line: ``make_assets.py [--out DIR]``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="output folder (default: %(default)s)")
    args = ap.parse_args(argv)
    for p in write_assets(args.out):
        print(f"{p}  ({p.stat().st_size / 1024:.0f} KiB)")


if __name__ == "__main__":
    main()
