"""The procedural rigs in ``assets/`` (written by ``tools/make_assets.py``).

Oracles: the committed bytes (the tool must reproduce them), UsdSkel's C++ (``UsdSkel.Cache``,
skinning queries, ``SkeletonQuery.ComputeSkinningTransforms`` and ``UsdSkel.SkinPoints`` as the
skinner), trimesh for closedness, and closed-form geometry of a two-joint rig written here from the
documented specification (assets/README.md), never from the tool's code.

Two-joint closed forms. A parent at identity and a child rotating by ``θ`` about a unit axis
``n`` through ``c``; a vertex with weights ``(1 - w, w)``:

* LBS: ``p' = (1 - w) p + w (c + R(θ)(p - c))``; the distance from the axis scales by
  ``|1 - w + w e^{iθ}|`` (0 at ``w = ½, θ = π``: the candy wrapper).
* DQS: the blend of ``(1, 0)`` and ``(cos θ/2, sin θ/2 n)`` about the same axis normalizes to a
  rotation by ``φ = 2 atan2(w sin θ/2, 1 - w + w cos θ/2)`` about the same axis, so distances from
  the axis are kept. At ``θ = π`` the hemisphere test sees a zero dot product; either sign is
  a valid DQS (``φ`` then uses ``-q``), both keep the radius.

Both blends commute with a common rigid motion on the left (LBS is linear; DQS normalization and
its hemisphere test are invariant under left multiplication by a unit dual quaternion), so a
humanoid limb is checked in its parent joint's skinned frame.
"""

import functools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

ROOT = Path(__file__).resolve().parents[1]
ASSETS = ROOT / "assets"
METHODS = {"lbs": "classicLinear", "dqs": "dualQuaternion"}

# The documented specification of each rig (assets/README.md).
SPEC = {
    "twist_cylinder.usda": dict(
        root="TwistCylinder", meshes=["Cylinder"], joints=["root", "root/twist"], mpu=1.0,
        frames=(0, 24), influences=2),
    "bending_arm.usda": dict(
        root="BendingArm", meshes=["Arm"], joints=["shoulder", "shoulder/elbow"], mpu=1.0,
        frames=(0, 30), influences=2),
    "humanoid.usda": dict(
        root="Humanoid", meshes=["Body", "Arm_L", "Leg_L", "Foot_L", "Arm_R", "Leg_R", "Foot_R"],
        joints=None, mpu=0.01, frames=(0, 48), influences=4),
}
# Two-joint rigs: child joint at x = 2 rotating about `axis` by `rate` degrees per frame; child
# weight ramps linearly over x in `ramp`; cylinder of `radius` along +X, 0 <= x <= 4.
TWO_JOINT = {
    "twist_cylinder.usda": dict(axis=(1.0, 0.0, 0.0), rate=7.5, ramp=(1.0, 3.0), radius=1.0),
    "bending_arm.usda": dict(axis=(0.0, 0.0, 1.0), rate=5.0, ramp=(1.5, 2.5), radius=0.5),
}
CENTER = np.array([2.0, 0.0, 0.0])

# Tolerance (scene units) for the unit-scale rigs. UsdSkel skins in float32: points of norm
# <= sqrt(4² + 1) ≈ 4.1 carry ≈ 4.1 * 6e-8 ≈ 2.5e-7 per operation, a few operations ≈ 1e-6.
# Stored quaternions are rounded to 1e-7 (angle error ≈ 2e-7 rad, ≤ 5e-7 at 2.3 units from the
# joint); weights to 1e-6 (≤ 5e-7 * |Rp - p| ≤ 1e-6 for LBS; for DQS dφ/dw ≤ 4 at w = ½, θ = π:
# ≤ 2e-6 rad · 1 unit); rest points to 1e-6. Sum ≈ 5e-6; we allow 1e-5.
TOL = 1e-5
# Humanoid (centimetres, |p| ≤ 180): float32 ≈ 180 * 6e-8 ≈ 1.1e-5 per operation, quaternion
# rounding 2e-7 rad * 80 cm ≈ 1.6e-5, weights 5e-7 * 10 cm; sum ≈ 1e-4 cm; we allow 5e-4 cm.
TOL_CM = 5e-4


# --------------------------------------------------------------------------------------------
# Loading through UsdSkel
# --------------------------------------------------------------------------------------------

class Rig:
    """An asset opened with UsdSkel: its skeleton query and skinning targets."""

    def __init__(self, name):
        self.stage = Usd.Stage.Open(str(ASSETS / name))
        root = UsdSkel.Root(self.stage.GetDefaultPrim())
        assert root, f"{name}: default prim is not a SkelRoot"
        cache = UsdSkel.Cache()
        cache.Populate(root, Usd.PrimDefaultPredicate)
        self.bindings = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
        assert len(self.bindings) == 1, f"{name}: expected one skeleton binding"
        self.skeleton = self.bindings[0].GetSkeleton()
        self.skel_query = cache.GetSkelQuery(self.skeleton)
        self.targets = {q.GetPrim().GetName(): q for q in self.bindings[0].GetSkinningTargets()}
        self.joints = [str(j) for j in self.skel_query.GetJointOrder()]

    def mesh(self, name):
        """(points (V, 3) float32, triangles (T, 3), indices (V, K), weights (V, K), query)."""
        q = self.targets[name]
        m = UsdGeom.Mesh(q.GetPrim())
        pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float32)
        counts = np.asarray(m.GetFaceVertexCountsAttr().Get())
        idx = np.asarray(m.GetFaceVertexIndicesAttr().Get())
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        tris = np.array([[idx[s], idx[s + j], idx[s + j + 1]]
                         for s, n in zip(starts, counts) for j in range(1, n - 1)])
        ji, jw = q.ComputeJointInfluences()
        k = q.GetNumInfluencesPerComponent()
        return (pts, tris, np.asarray(ji).reshape(-1, k), np.asarray(jw).reshape(-1, k), q)

    def skinning_transforms(self, time):
        """(J, 4, 4) float64, column-vector convention."""
        x = self.skel_query.ComputeSkinningTransforms(Usd.TimeCode(time))
        return np.array([np.array(m) for m in x]).transpose(0, 2, 1)

    def skin(self, name, time, method):
        """UsdSkel.SkinPoints of one mesh at ``time``: (V, 3) float64 in skeleton space."""
        pts, _, ji, jw, q = self.mesh(name)
        x = self.skel_query.ComputeSkinningTransforms(Usd.TimeCode(time))
        out = Vt.Vec3fArray.FromNumpy(pts)
        assert UsdSkel.SkinPoints(METHODS[method], q.GetGeomBindTransform(), x,
                                  Vt.IntArray.FromNumpy(ji.ravel().astype(np.int32)),
                                  Vt.FloatArray.FromNumpy(jw.ravel().astype(np.float32)),
                                  ji.shape[1], out)
        return np.asarray(out, dtype=np.float64)


@functools.lru_cache(maxsize=None)
def rig(name):
    return Rig(name)


# --------------------------------------------------------------------------------------------
# Closed forms
# --------------------------------------------------------------------------------------------

def rotate(p, axis, center, angle):
    """Rodrigues rotation of points ``p`` (V, 3) about ``axis`` through ``center`` by ``angle``
    (scalar or (V,)) radians."""
    n = np.asarray(axis, float) / np.linalg.norm(axis)
    d = np.asarray(p, float) - center
    a = np.broadcast_to(np.asarray(angle, float), (d.shape[0],))[:, None]
    return (center + d * np.cos(a) + np.cross(n, d) * np.sin(a)
            + n * (d @ n)[:, None] * (1 - np.cos(a)))


def two_joint(p, w, axis, center, theta, method, sign=1.0):
    """Closed-form LBS or DQS of a parent at identity and a child rotated by ``theta`` about
    ``axis`` through ``center``; ``sign`` = -1 takes the antipodal child quaternion (DQS)."""
    p = np.asarray(p, float)
    if method == "lbs":
        return (1 - w)[:, None] * p + w[:, None] * rotate(p, axis, center, theta)
    phi = 2 * np.arctan2(sign * w * np.sin(theta / 2), (1 - w) + sign * w * np.cos(theta / 2))
    return rotate(p, axis, center, phi)


def axis_distance(p, axis, center):
    n = np.asarray(axis, float) / np.linalg.norm(axis)
    d = np.asarray(p, float) - center
    return np.linalg.norm(d - (d @ n)[:, None] * n, axis=1)


def spec_weight(x, ramp):
    lo, hi = ramp
    return np.clip((np.asarray(x, float) - lo) / (hi - lo), 0.0, 1.0)


def rotation_of(m):
    """(axis (3,), angle degrees in (-180, 180]) of a 3×3 rotation, column convention."""
    r = Gf.Matrix3d(np.asarray(m[:3, :3], float).T.tolist()).ExtractRotation()
    axis, angle = np.array(r.GetAxis()), r.GetAngle()
    angle = (angle + 180.0) % 360.0 - 180.0
    if angle == -180.0:
        angle = 180.0
    return axis, angle


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------

def test_regenerates_byte_for_byte(tmp_path):
    subprocess.run([sys.executable, str(ROOT / "tools" / "make_assets.py"), "--out", str(tmp_path)],
                   check=True, capture_output=True)
    for name in SPEC:
        fresh, committed = (tmp_path / name).read_bytes(), (ASSETS / name).read_bytes()
        assert fresh == committed, (f"assets/{name} differs from what tools/make_assets.py writes; "
                                    "regenerate with `python tools/make_assets.py`")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(SPEC)


@pytest.mark.parametrize("name", list(SPEC))
def test_stage_and_skeleton(name):
    spec, r = SPEC[name], rig(name)
    assert (ASSETS / name).stat().st_size < 2 * 1024 * 1024
    s = r.stage
    assert UsdGeom.GetStageUpAxis(s) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(s) == spec["mpu"]
    assert s.GetTimeCodesPerSecond() == 24
    assert (s.GetStartTimeCode(), s.GetEndTimeCode()) == spec["frames"]
    assert s.GetDefaultPrim().GetName() == spec["root"]
    assert r.skeleton.GetPath() == f"/{spec['root']}/Skeleton"
    assert r.skel_query.HasBindPose() and r.skel_query.HasRestPose()
    anim = r.skel_query.GetAnimQuery()
    assert anim and [str(j) for j in anim.GetJointOrder()] == r.joints
    lo, hi = spec["frames"]
    assert list(anim.GetJointTransformTimeSamples()) == list(range(lo, hi + 1))
    if spec["joints"] is not None:
        assert r.joints == spec["joints"]
    assert sorted(r.targets) == sorted(spec["meshes"])


@pytest.mark.parametrize("name", list(SPEC))
def test_meshes_closed_and_weights_valid(name):
    spec, r = SPEC[name], rig(name)
    J = len(r.joints)
    total = 0
    for mesh_name in spec["meshes"]:
        pts, tris, ji, jw, q = r.mesh(mesh_name)
        total += len(pts)
        tm = trimesh.Trimesh(pts, tris, process=False)
        assert tm.is_watertight and tm.is_winding_consistent, mesh_name
        assert tm.volume > 0, f"{mesh_name}: faces point inward"
        assert q.GetInterpolation() == UsdGeom.Tokens.vertex
        assert ji.shape == (len(pts), spec["influences"])
        assert ji.min() >= 0 and ji.max() < J
        assert jw.min() >= 0 and np.abs(jw.sum(axis=1, dtype=np.float64) - 1).max() <= 1e-6
        m = UsdGeom.Mesh(q.GetPrim())
        assert m.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
        normals = np.asarray(m.GetNormalsAttr().Get(), float)
        assert m.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
        assert normals.shape == pts.shape
        assert np.abs(np.linalg.norm(normals, axis=1) - 1).max() <= 1e-5
        # outward: normals agree with the area-weighted face normals around each vertex
        assert np.einsum("ij,ij->i", normals, tm.vertex_normals).min() > 0.5
        st = UsdGeom.PrimvarsAPI(m).GetPrimvar("st")
        assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying and st.IsIndexed()
        uv = np.asarray(st.ComputeFlattened())
        assert uv.shape == (len(m.GetFaceVertexIndicesAttr().Get()), 2)
        assert uv.min() >= 0 and uv.max() <= 1
        gb = np.array(q.GetGeomBindTransform())
        assert np.array_equal(gb, np.eye(4))
    if name == "humanoid.usda":
        assert 15 <= J <= 20 and 2000 <= total <= 10000
        body = r.mesh("Body")[3]
        assert (body > 0).sum(axis=1).max() == 4  # the rig exercises 4 influences


# --------------------------------------------------------------------------------------------
# Two-joint rigs against closed forms
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(TWO_JOINT))
def test_weights_follow_documented_ramp(name):
    pts, _, ji, jw, _ = rig(name).mesh(SPEC[name]["meshes"][0])
    assert np.array_equal(ji, np.tile([0, 1], (len(pts), 1)))
    w = spec_weight(pts[:, 0], TWO_JOINT[name]["ramp"])
    assert np.abs(jw[:, 1] - w).max() <= 1e-6 and np.abs(jw[:, 0] - (1 - w)).max() <= 1e-6


@pytest.mark.parametrize("method", list(METHODS))
@pytest.mark.parametrize("name", list(TWO_JOINT))
def test_two_joint_rig_matches_closed_form(name, method):
    """Every vertex at several frames (including a half frame: the angle is linear in time)."""
    tj, r = TWO_JOINT[name], rig(name)
    pts = r.mesh(SPEC[name]["meshes"][0])[0]
    w = spec_weight(pts[:, 0], tj["ramp"])
    last = SPEC[name]["frames"][1]
    for f in (0, 1, 5, 12, 12.5, last - 0.5, last):
        theta = np.radians(tj["rate"] * f)
        got = r.skin(SPEC[name]["meshes"][0], f, method)
        signs = (1.0, -1.0) if (method == "dqs" and np.isclose(theta, np.pi)) else (1.0,)
        err = min(np.abs(got - two_joint(pts, w, tj["axis"], CENTER, theta, method, s)).max()
                  for s in signs)
        assert err <= TOL, f"{name} {method} frame {f}: error {err:.2e}"


@pytest.mark.parametrize("name", list(TWO_JOINT))
def test_frame_zero_is_rest_and_regions_are_rigid(name):
    tj, r = TWO_JOINT[name], rig(name)
    mesh = SPEC[name]["meshes"][0]
    pts = r.mesh(mesh)[0].astype(float)
    lo, hi = tj["ramp"]
    parent_only, child_only = pts[:, 0] <= lo, pts[:, 0] >= hi
    assert parent_only.sum() > 100 and child_only.sum() > 100
    for method in METHODS:
        assert np.abs(r.skin(mesh, 0, method) - pts).max() <= TOL
        for f in range(SPEC[name]["frames"][1] + 1):
            got = r.skin(mesh, f, method)
            want = rotate(pts[child_only], tj["axis"], CENTER, np.radians(tj["rate"] * f))
            assert np.abs(got[child_only] - want).max() <= TOL, f"{method} frame {f}"
            assert np.abs(got[parent_only] - pts[parent_only]).max() <= TOL


def test_twist_half_turn_collapses_lbs_and_dqs_keeps_radius():
    """Frame 24 (180°): at the joint cross-section (x = 2, weights ½/½) LBS shrinks the radius
    to 0 and DQS keeps it at 1; DQS keeps radius 1 along the whole side at every frame."""
    name = "twist_cylinder.usda"
    r = rig(name)
    pts, _, _, jw, _ = r.mesh("Cylinder")
    radius = axis_distance(pts, (1, 0, 0), CENTER)
    ring = (np.abs(pts[:, 0] - 2.0) < 1e-6) & (np.abs(radius - 1.0) < 1e-5)
    assert ring.sum() == 32 and np.abs(jw[ring] - 0.5).max() <= 1e-6
    lbs, dqs = r.skin("Cylinder", 24, "lbs"), r.skin("Cylinder", 24, "dqs")
    assert axis_distance(lbs[ring], (1, 0, 0), CENTER).max() <= TOL
    assert np.abs(axis_distance(dqs[ring], (1, 0, 0), CENTER) - 1.0).max() <= TOL
    side = np.abs(radius - 1.0) < 1e-5
    for f in range(25):
        d = axis_distance(r.skin("Cylinder", f, "dqs")[side], (1, 0, 0), CENTER)
        assert np.abs(d - 1.0).max() <= TOL, f"frame {f}"


# --------------------------------------------------------------------------------------------
# Humanoid
# --------------------------------------------------------------------------------------------

def walk_phase(f, side):
    return 2 * np.pi * f / 48 + (0.0 if side == "L" else np.pi)


def joint(r, name):
    return next(i for i, j in enumerate(r.joints) if j.rsplit("/", 1)[-1] == name)


def test_humanoid_loops():
    r = rig("humanoid.usda")
    assert np.abs(r.skinning_transforms(0) - r.skinning_transforms(48)).max() <= 1e-4


@pytest.mark.parametrize("side", ["L", "R"])
def test_humanoid_joint_motion(side):
    """Rest-relative rotations (UsdSkel local transforms): the wrist twists about its bone by
    100° sin(phase) measured about the skeleton's +X at rest (local +X on the left arm, local -X
    on the right, whose bone points along -X); knee and elbow bend about an axis perpendicular
    to the bone within the documented ranges (knee 5..60°, elbow 15..55°)."""
    r = rig("humanoid.usda")
    q = r.skel_query
    rest = np.array([np.array(m) for m in q.ComputeJointLocalTransforms(Usd.TimeCode(0), True)])
    wrist, knee, elbow = (joint(r, f"{n}_{side}") for n in ("wrist", "knee", "elbow"))
    bends = {knee: [], elbow: []}
    for f in range(49):
        local = np.array([np.array(m) for m in q.ComputeJointLocalTransforms(Usd.TimeCode(f))])
        rel = [np.linalg.inv(rest[j].T) @ local[j].T for j in range(len(local))]
        axis, angle = rotation_of(rel[wrist])
        want = 100.0 * np.sin(walk_phase(f, side))
        assert abs(abs(angle) - abs(want)) <= 1e-3, f"frame {f}"
        if abs(want) > 1:
            bone = 1.0 if side == "L" else -1.0  # skeleton +X in the wrist's local frame
            assert np.allclose(axis * np.sign(angle), [bone * np.sign(want), 0, 0], atol=1e-5)
        for j in bends:
            axis, angle = rotation_of(rel[j])
            assert abs(axis[0]) <= 1e-5, f"frame {f}: bend axis not perpendicular to the bone"
            bends[j].append(abs(angle))
    assert 5 - 0.5 <= min(bends[knee]) and max(bends[knee]) <= 60 + 0.5
    assert max(bends[knee]) >= 55 and min(bends[elbow]) >= 15 - 0.5
    assert max(bends[elbow]) <= 55 + 0.5 and max(bends[elbow]) >= 50


def limb_pair_check(r, mesh, parent, child, frames):
    """Vertices influenced only by ``parent`` and ``child``, seen in the parent's skinned frame,
    follow the two-joint closed forms about the child's bind position; returns the
    LBS and DQS axis-distance ratios (skinned / rest) at each frame."""
    pts, _, ji, jw, _ = r.mesh(mesh)
    P, C = joint(r, parent), joint(r, child)
    only = np.all((jw == 0) | (ji == P) | (ji == C), axis=1)
    both = only & np.any((ji == C) & (jw > 0), axis=1) & np.any((ji == P) & (jw > 0), axis=1)
    assert both.sum() >= 40, f"{mesh}: too few {parent}/{child} vertices"
    w = np.where(ji == C, jw, 0).sum(axis=1)[only]
    bind = np.array(r.skel_query.GetJointWorldBindTransforms()[C]).T
    center = bind[:3, 3]
    ratios = []
    for f in frames:
        x = r.skinning_transforms(f)
        rel = np.linalg.inv(x[P]) @ x[C]  # child relative to parent: a rotation about `center`
        axis, angle = rotation_of(rel)
        assert np.abs(rel[:3, :3] @ center + rel[:3, 3] - center).max() <= 1e-4
        theta = np.radians(angle)
        ratio = {}
        for method in METHODS:
            got = r.skin(mesh, f, method)[only]
            local = got @ np.linalg.inv(x[P])[:3, :3].T + np.linalg.inv(x[P])[:3, 3]
            want = two_joint(pts[only], w, axis, center, theta, method)
            err = np.abs(local - want).max()
            assert err <= TOL_CM, f"{mesh} {method} frame {f}: error {err:.2e} cm"
            rest_d = axis_distance(pts[only], axis, center)
            off_axis = rest_d > 0.5  # the limb's end pole lies on the axis
            ratio[method] = (axis_distance(local, axis, center)[off_axis] / rest_d[off_axis]).min()
        ratios.append(ratio)
    return ratios


@pytest.mark.parametrize("side", ["L", "R"])
def test_humanoid_forearm_twist_closed_form(side):
    """Forearm/hand vertices (elbow + wrist influences) twist as the closed forms say; at the
    frame of largest twist (100°) LBS loses radius at the ramp's middle (cos 50° ≈ 0.64) while
    DQS keeps it."""
    r = rig("humanoid.usda")
    peak = 12 if side == "L" else 36
    ratios = limb_pair_check(r, f"Arm_{side}", f"elbow_{side}", f"wrist_{side}",
                             (0, 5, peak, 30, 41))
    at_peak = ratios[2]
    assert at_peak["lbs"] < 0.7 and at_peak["dqs"] >= 1 - 1e-3


@pytest.mark.parametrize("side", ["L", "R"])
def test_humanoid_knee_bend_closed_form(side):
    r = rig("humanoid.usda")
    limb_pair_check(r, f"Leg_{side}", f"hip_{side}", f"knee_{side}", (0, 7, 19, 33, 44))
