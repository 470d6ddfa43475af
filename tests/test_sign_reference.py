"""DQS sign reference: ``"largest_weight"`` (UsdSkel) and ``"running_sum"`` (Blender).

Every entry point (Skinner points, normals, velocities; skin_points / skin_normals; Scene.skin;
the CLI) against a float64 NumPy reference of both rules written from their definitions: each
joint quaternion is flipped onto the hemisphere of the largest-weight joint's (first on ties), or
of the sum of the blend so far (influences in input order; a zero sum flips nothing). Quaternions
come from SciPy, points are rotated by SciPy, dual parts from the Hamilton product written out.
The helpers here are imported by ``tests/test_cor.py``.
"""

import contextlib
import io
import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_motion import qmul as hamilton

import dqskin
from dqskin.cli import main
from dqskin.motion import skinned_velocities
from dqskin.skinning import Skinner

RULES = ("largest_weight", "running_sum")


# ---------------------------------------------------------------------------------------------
# float64 reference


def joint_quats(xforms):
    """(F, J, 4) (w, x, y, z) of the rotation parts of rigid (F, J, 4, 4) transforms."""
    F, J = xforms.shape[:2]
    q = Rotation.from_matrix(xforms[..., :3, :3].reshape(-1, 3, 3)).as_quat()
    return q[:, [3, 0, 1, 2]].reshape(F, J, 4)


def rotation_blend(xforms, idx, wts, rule):
    """Sign-aligned weighted sums ``(r, d)`` (F, V, 4) of the joint dual quaternions."""
    q = joint_quats(xforms)
    t = np.concatenate([np.zeros(xforms.shape[:2] + (1,)), xforms[..., :3, 3]], -1)
    d = 0.5 * hamilton(t, q)
    qs, ds = q[:, idx], d[:, idx]  # (F, V, K, 4)
    w = np.asarray(wts, np.float64)
    V = idx.shape[0]
    pivot = qs[:, np.arange(V), np.argmax(w, axis=1)]
    r = np.zeros(qs.shape[:2] + (4,))
    dd = np.zeros_like(r)
    for k in range(idx.shape[1]):
        ref = pivot if rule == "largest_weight" else r
        s = np.where(np.sum(qs[:, :, k] * ref, -1) < 0, -1.0, 1.0) * w[None, :, k]
        r = r + s[..., None] * qs[:, :, k]
        dd = dd + s[..., None] * ds[:, :, k]
    return r, dd


def rotate(r, p):
    """Rotate points ``p`` (..., 3) by the normalized quaternions ``r`` (..., 4)."""
    shape = np.broadcast_shapes(r.shape[:-1], p.shape[:-1])
    rr = np.array(np.broadcast_to(r, shape + (4,))).reshape(-1, 4)  # (SciPy wants writable)
    pp = np.array(np.broadcast_to(p, shape + (3,))).reshape(-1, 3)
    return Rotation.from_quat(rr[:, [1, 2, 3, 0]]).apply(pp).reshape(shape + (3,))


def dqs_reference(points, idx, wts, xforms, rule):
    """(F, V, 3) DQS of rigid transforms (F, J, 4, 4) with sign rule ``rule``."""
    r, d = rotation_blend(xforms, idx, wts, rule)
    n2 = np.sum(r * r, -1, keepdims=True)
    conj = r * np.array([1, -1, -1, -1])
    t = 2.0 * hamilton(d, conj)[..., 1:] / n2
    return rotate(r, points[None]) + t


def random_rig(rng, V=400, J=6, K=4, F=3, zero=0.2):
    points = rng.normal(size=(V, 3))
    idx = np.stack([rng.permutation(J)[:K] for _ in range(V)])
    wts = rng.random((V, K))
    wts[rng.random((V, K)) < zero] = 0.0
    wts = wts.astype(np.float32).astype(np.float64)
    xf = np.tile(np.eye(4), (F, J, 1, 1))
    xf[..., :3, :3] = Rotation.random(F * J, random_state=rng).as_matrix().reshape(F, J, 3, 3)
    xf[..., :3, 3] = rng.normal(size=(F, J, 3))
    xf = xf.astype(np.float32).astype(np.float64)
    return points.astype(np.float32).astype(np.float64), idx, wts, xf


def differ_fraction(a, b, tol=1e-3):
    return float(np.mean(np.linalg.norm(a - b, axis=-1) > tol))


# ---------------------------------------------------------------------------------------------
# engine vs reference


@pytest.mark.parametrize("K", [4, 6])
def test_points_match_both_rules(device, K):
    pts, idx, wts, xf = random_rig(np.random.default_rng(K), K=K)
    sk = Skinner(pts, idx, wts, device=device)
    got = {rule: sk.skin(xf, "dqs", sign_reference=rule) for rule in RULES}
    for rule in RULES:
        np.testing.assert_allclose(got[rule], dqs_reference(pts, idx, wts, xf, rule), atol=2e-5,
                                   err_msg=rule)
    # the rules really differ here (so the comparison above can fail)
    assert differ_fraction(got["largest_weight"], got["running_sum"]) > 0.1
    # default: UsdSkel's
    np.testing.assert_array_equal(sk.skin(xf, "dqs"), got["largest_weight"])


def test_running_sum_follows_input_order(device):
    pts, idx, wts, xf = random_rig(np.random.default_rng(7), K=4)
    perm = np.random.default_rng(8).permuted(np.tile(np.arange(4), (len(pts), 1)), axis=1)
    idx2, wts2 = np.take_along_axis(idx, perm, 1), np.take_along_axis(wts, perm, 1)
    a = skin_points_rule(pts, idx, wts, xf, "running_sum", device)
    b = skin_points_rule(pts, idx2, wts2, xf, "running_sum", device)
    np.testing.assert_allclose(b, dqs_reference(pts, idx2, wts2, xf, "running_sum"), atol=2e-5)
    assert differ_fraction(a, b) > 0.02  # the order matters ...
    la = skin_points_rule(pts, idx, wts, xf, "largest_weight", device)
    lb = skin_points_rule(pts, idx2, wts2, xf, "largest_weight", device)
    np.testing.assert_allclose(la, lb, atol=2e-5)  # ... only for the running sum


def test_two_influences_agree(device):
    """With two influences the rules differ only by the sign of the whole blend, which
    normalization removes."""
    pts, idx, wts, xf = random_rig(np.random.default_rng(9), K=2, zero=0.0)
    a, b = (skin_points_rule(pts, idx, wts, xf, rule, device) for rule in RULES)
    np.testing.assert_allclose(a, b, atol=2e-5)


def skin_points_rule(pts, idx, wts, xf, rule, device):
    return dqskin.skin_points(pts, idx, wts, xf, "dqs", sign_reference=rule, device=device)


def test_normals_both_rules(device):
    pts, idx, wts, xf = random_rig(np.random.default_rng(3), K=4)
    normals = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    for rule in RULES:
        got = dqskin.skin_normals(normals, idx, wts, xf, "dqs", sign_reference=rule,
                                  device=device)
        r, _ = rotation_blend(xf, idx, wts, rule)
        np.testing.assert_allclose(got, rotate(r, normals[None]), atol=2e-5, err_msg=rule)


def test_blend_method_uses_the_rule(device):
    pts, idx, wts, xf = random_rig(np.random.default_rng(4), K=4)
    b = np.random.default_rng(5).random(len(pts))
    sk = Skinner(pts, idx, wts, blend_weights=b, device=device)
    lbs = np.einsum("vk,fvkij,vj->fvi", wts, xf[:, idx, :3, :], np.c_[pts, np.ones(len(pts))])
    for rule in RULES:
        want = (1 - b[None, :, None]) * lbs + b[None, :, None] * dqs_reference(pts, idx, wts, xf,
                                                                               rule)
        np.testing.assert_allclose(sk.skin(xf, "blend", sign_reference=rule), want, atol=3e-5)


def motion(rng, J, F=2):
    """Rigid transforms ``A(t) = [exp(t·ωⱼ)·R₀ⱼ | t₀ⱼ + t·vⱼ]`` at t = 0 and their central
    differences of the float64 reference positions."""
    r0 = Rotation.random(J, random_state=rng)
    omega, t0, vel = rng.normal(size=(J, 3)), rng.normal(size=(J, 3)), rng.normal(size=(J, 3))

    def at(t):
        x = np.tile(np.eye(4), (F, J, 1, 1))
        for f in range(F):
            x[f, :, :3, :3] = (Rotation.from_rotvec((t + 0.3 * f) * omega) * r0).as_matrix()
            x[f, :, :3, 3] = t0 + (t + 0.3 * f) * vel
        return x
    return at


def test_velocities_both_rules(device):
    rng = np.random.default_rng(11)
    pts, idx, wts, _ = random_rig(rng, V=300, K=4)
    at = motion(rng, 6)
    h = 1e-5
    x, x_dot = at(0.0), (at(h) - at(-h)) / (2 * h)
    for rule in RULES:
        got = skinned_velocities(pts, idx, wts, x, x_dot, "dqs", sign_reference=rule,
                                 device=device)
        want = (dqs_reference(pts, idx, wts, at(h), rule)
                - dqs_reference(pts, idx, wts, at(-h), rule)) / (2 * h)
        np.testing.assert_allclose(got, want, atol=2e-3 * np.abs(want).max(), err_msg=rule)


def test_bad_sign_reference():
    pts, idx, wts, xf = random_rig(np.random.default_rng(0), V=10)
    with pytest.raises(ValueError, match="sign_reference must be one of"):
        dqskin.skin_points(pts, idx, wts, xf, "dqs", sign_reference="blender")


# ---------------------------------------------------------------------------------------------
# Scene.skin and the CLI, on a generated UsdSkel asset with three influences per vertex


def write_usd_rig(path, rng, *, J=4, K=3, frames=3, faces=None, points=None, idx=None, wts=None):
    """A flat UsdSkel rig (every joint a child of the first) with large random rotations at
    every frame, points authored in skeleton space (identity geom bind); returns
    ``(points, idx, wts, faces)`` as authored."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

    V = 120 if points is None else len(points)
    if points is None:
        points = rng.normal(size=(V, 3)).astype(np.float32)
    if faces is None:
        faces = np.stack([rng.choice(V, 3, replace=False) for _ in range(2 * V)]).astype(np.int32)
    if idx is None:
        idx = np.stack([rng.permutation(J)[:K] for _ in range(V)]).astype(np.int32)
        wts = rng.random((V, K)).astype(np.float32)
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(frames - 1)
    root = UsdSkel.Root.Define(stage, "/Rig")
    stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, "/Rig/Skel")
    names = ["j0"] + [f"j0/j{j}" for j in range(1, J)]
    skel.CreateJointsAttr(names)
    eye = Vt.Matrix4dArray([Gf.Matrix4d(1)] * J)
    skel.CreateBindTransformsAttr(eye)
    skel.CreateRestTransformsAttr(eye)
    anim = UsdSkel.Animation.Define(stage, "/Rig/Skel/Anim")
    anim.CreateJointsAttr(names)
    rot, tra, sca = (anim.CreateRotationsAttr(), anim.CreateTranslationsAttr(),
                     anim.CreateScalesAttr())
    for f in range(frames):
        q = Rotation.random(J, random_state=rng).as_quat()
        rot.Set(Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z))
                               for x, y, z, w in q]), f)
        tra.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, v)) for v in rng.normal(size=(J, 3))]), f)
        sca.Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * J), f)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    mesh = UsdGeom.Mesh.Define(stage, "/Rig/Mesh")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.asarray(points, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(np.asarray(faces).reshape(-1).tolist()))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, idx.shape[1]).Set(
        Vt.IntArray(idx.reshape(-1).tolist()))
    binding.CreateJointWeightsPrimvar(False, idx.shape[1]).Set(
        Vt.FloatArray(wts.reshape(-1).astype(float).tolist()))
    binding.CreateSkinningMethodAttr().Set("dualQuaternion")
    mesh.GetPrim().CreateAttribute("primvars:skel:geomBindTransform",
                                   Sdf.ValueTypeNames.Matrix4d).Set(Gf.Matrix4d(1))
    stage.GetRootLayer().Save()
    return (np.asarray(points, np.float64), idx.astype(np.int64), wts.astype(np.float64),
            np.asarray(faces))


def usdskel_transforms(path, frames):
    """(F, J, 4, 4) skinning transforms from UsdSkel itself (column-vector convention)."""
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(str(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetPrimAtPath("/Rig"))
    cache.Populate(root, Usd.TraverseInstanceProxies())
    query = cache.GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Rig/Skel")))
    return np.stack([np.array(query.ComputeSkinningTransforms(f)).transpose(0, 2, 1)
                     for f in frames])


def run_cli(*args, process=False):
    """``dqskin ARGS``: in this process (``dqskin.cli.main(argv)``), or as a subprocess."""
    argv = [str(a) for a in args]
    if process:
        proc = subprocess.run([sys.executable, "-m", "dqskin.cli", *argv], capture_output=True,
                              text=True, timeout=300)
        return proc.returncode, proc.stdout + proc.stderr
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse
            rc = exc.code
    return rc, out.getvalue()


def test_scene_and_cli_both_rules(tmp_path):
    path = tmp_path / "rig.usda"
    pts, idx, wts, _ = write_usd_rig(path, np.random.default_rng(21))
    xf = usdskel_transforms(path, [0, 1, 2])
    scene = dqskin.load(path)
    ref = {rule: dqs_reference(pts, idx, wts, xf, rule) for rule in RULES}
    assert differ_fraction(ref["largest_weight"], ref["running_sum"]) > 0.1
    for rule in RULES:
        got = scene.skin(method="dqs", sign_reference=rule).points["/Rig/Mesh"]
        np.testing.assert_allclose(got, ref[rule], atol=5e-5, err_msg=rule)
        out = tmp_path / f"{rule}.npz"
        rc, text = run_cli("skin", path, "--out", out, "--method", "dqs", "--sign-reference", rule,
                           process=rule == "running_sum")  # (one run as its own process)
        assert rc == 0, text
        np.testing.assert_allclose(np.load(out)["points_0"], ref[rule], atol=5e-5, err_msg=rule)
    rc, text = run_cli("skin", path, "--out", tmp_path / "x.npz", "--sign-reference", "blender",
                       process=True)
    assert rc == 2 and "invalid choice" in text and "Traceback" not in text


# ---------------------------------------------------------------------------------------------
# Blender itself (optional oracle): its Armature modifier with Preserve Volume


BLENDER_SCRIPT = """\
import sys
import bpy
import numpy as np

data = np.load(sys.argv[1])
points, idx, wts, xf = data["points"], data["idx"], data["wts"], data["xforms"]
bpy.ops.wm.read_factory_settings(use_empty=True)
arm = bpy.data.armatures.new("Arm")
rig = bpy.data.objects.new("Rig", arm)
bpy.context.scene.collection.objects.link(rig)
bpy.context.view_layer.objects.active = rig
bpy.ops.object.mode_set(mode="EDIT")
J = xf.shape[1]
for j in range(J):
    b = arm.edit_bones.new(f"j{j}")
    b.head, b.tail, b.roll = (0, 0, 0), (0, 1, 0), 0.0
bpy.ops.object.mode_set(mode="OBJECT")
me = bpy.data.meshes.new("M")
me.from_pydata(points.tolist(), [], [])
ob = bpy.data.objects.new("M", me)
bpy.context.scene.collection.objects.link(ob)
groups = [ob.vertex_groups.new(name=f"j{j}") for j in range(J)]
for v in range(len(points)):
    for k in range(idx.shape[1]):  # dvert order = input slot order
        if wts[v, k] > 0:
            groups[idx[v, k]].add([v], float(wts[v, k]), "REPLACE")
mod = ob.modifiers.new("Armature", "ARMATURE")
mod.object = rig
mod.use_deform_preserve_volume = True
from mathutils import Matrix
out = []
for f in range(xf.shape[0]):
    for j in range(J):
        rig.pose.bones[f"j{j}"].matrix_basis = Matrix(xf[f, j].tolist())
    bpy.context.view_layer.update()
    dg = bpy.context.evaluated_depsgraph_get()
    ev = ob.evaluated_get(dg)
    m = ev.to_mesh()
    co = np.empty(len(m.vertices) * 3)
    m.vertices.foreach_get("co", co)
    out.append(co.reshape(-1, 3))
    ev.to_mesh_clear()
np.save(sys.argv[2], np.array(out))
"""


def bpy_python():
    """A Python that imports ``bpy`` (Blender as a module; bpy 5.x needs Python 3.11): the one in
    ``$DQSKIN_BPY_PYTHON``, or this one if it has bpy; None otherwise."""
    if os.environ.get("DQSKIN_BPY_PYTHON"):
        return os.environ["DQSKIN_BPY_PYTHON"]
    try:
        import bpy  # noqa: F401
    except ImportError:
        return None
    return sys.executable


def test_running_sum_matches_blender(tmp_path):
    py = bpy_python()
    if py is None:
        pytest.skip("bpy not installed: set DQSKIN_BPY_PYTHON to a Python 3.11 with `pip install "
                    "bpy` (Blender 5.x) to compare against Blender's Preserve Volume")
    pts, idx, wts, xf = random_rig(np.random.default_rng(1), V=300, K=4, F=2)
    np.savez(tmp_path / "in.npz", points=pts, idx=idx, wts=wts, xforms=xf)
    (tmp_path / "blender.py").write_text(BLENDER_SCRIPT)
    proc = subprocess.run([py, str(tmp_path / "blender.py"), str(tmp_path / "in.npz"),
                           str(tmp_path / "out.npy")], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    blender = np.load(tmp_path / "out.npy")
    ours = {rule: dqskin.skin_points(pts, idx, wts, xf, "dqs", sign_reference=rule)
            for rule in RULES}
    np.testing.assert_allclose(ours["running_sum"], blender, atol=2e-5)
    assert differ_fraction(ours["largest_weight"], blender) > 0.2  # UsdSkel's rule is not it


def test_rigid_prims_both_rules(tmp_path):
    """A Cube bound with constant influences (three joints) moves as the affine map DQS makes of
    its frame: from Python (dqskin.pipeline.rigid_transforms) and in a baked USD cache."""
    from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

    from dqskin.pipeline import rigid_transforms
    from dqskin.readers.usd import load_rigid_prims

    path = tmp_path / "rig.usda"
    write_usd_rig(path, np.random.default_rng(31))
    stage = Usd.Stage.Open(str(path))
    cube = UsdGeom.Cube.Define(stage, "/Rig/Cube")
    binding = UsdSkel.BindingAPI.Apply(cube.GetPrim())
    binding.CreateSkeletonRel().SetTargets([Sdf.Path("/Rig/Skel")])
    idx, wts = np.array([3, 1, 2]), np.array([0.3, 0.25, 0.45])
    binding.CreateJointIndicesPrimvar(True, 3).Set(Vt.IntArray(idx.tolist()))
    binding.CreateJointWeightsPrimvar(True, 3).Set(Vt.FloatArray(wts.tolist()))
    binding.CreateSkinningMethodAttr().Set("dualQuaternion")
    stage.GetRootLayer().Save()
    xf = usdskel_transforms(path, [0, 1, 2])
    frame = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    want = {}
    for rule in RULES:
        q = dqs_reference(frame, np.tile(idx, (4, 1)), np.tile(wts, (4, 1)), xf, rule)
        m = np.tile(np.eye(4), (3, 1, 1))
        m[:, :3, 3] = q[:, 0]
        m[:, :3, :3] = (q[:, 1:] - q[:, :1]).transpose(0, 2, 1)
        want[rule] = m
    assert np.abs(want["largest_weight"] - want["running_sum"]).max() > 0.1
    scene = dqskin.load(path)
    (rigid,) = load_rigid_prims(scene)
    for rule in RULES:
        got = rigid_transforms(scene, rigid, scene.times,
                               dqskin.SkinOptions(method="dqs", sign_reference=rule))
        np.testing.assert_allclose(got, want[rule], atol=5e-5, err_msg=rule)
        out = tmp_path / f"{rule}.usda"
        rc, text = run_cli("skin", path, "--out", out, "--method", "dqs", "--sign-reference", rule)
        assert rc == 0, text
        baked_stage = Usd.Stage.Open(str(out))
        attr = baked_stage.GetPrimAtPath("/Rig/Cube").GetAttribute("xformOp:transform")
        baked = np.stack([np.array(attr.Get(t)).T for t in scene.times])
        np.testing.assert_allclose(baked, want[rule], atol=5e-5, err_msg=rule)
