"""Forward kinematics against float64 matrix chains and UsdSkel's skeleton query."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dqskin.errors import InputError
from dqskin.skeleton import Skeleton, forward_kinematics


def random_hierarchy(rng, J):
    return np.array([-1] + [int(rng.integers(0, j)) for j in range(1, J)])


def random_locals(rng, shape, J, scale=False, shear=False):
    n = int(np.prod(shape)) * J
    M = np.tile(np.eye(4), (n, 1, 1))
    M[:, :3, :3] = Rotation.random(n, random_state=rng).as_matrix()
    if scale:
        M[:, :3, :3] = M[:, :3, :3] * rng.uniform(0.5, 2.0, size=(n, 1, 3))
    if shear:
        M[:, :3, :3] = M[:, :3, :3] @ (np.eye(3) + 0.3 * np.triu(rng.normal(size=(n, 3, 3)), 1))
    M[:, :3, 3] = rng.normal(size=(n, 3))
    return M.reshape(*shape, J, 4, 4)


def chain_product(parents, local):
    """float64 reference: world[j] = world[parent[j]] @ local[j]."""
    world = np.empty_like(local)
    for j, p in enumerate(parents):
        world[..., j, :, :] = (local[..., j, :, :] if p < 0
                               else world[..., p, :, :] @ local[..., j, :, :])
    return world


@pytest.mark.parametrize("scale,shear", [(False, False), (True, False), (True, True)],
                         ids=["rigid", "scale", "shear"])
def test_fk_matches_matrix_chain(device, scale, shear):
    rng = np.random.default_rng(int(scale) + 2 * int(shear))
    J = 24
    parents = random_hierarchy(rng, J)
    local = random_locals(rng, (2, 3), J, scale, shear)
    world = forward_kinematics(parents, local, device=device)
    ref = chain_product(parents, local)
    assert world.shape == (2, 3, J, 4, 4)
    assert np.abs(world - ref).max() / np.abs(ref).max() <= 1e-5


def test_fk_dual_quaternions_are_the_rigid_part(device):
    rng = np.random.default_rng(5)
    J = 10
    parents = random_hierarchy(rng, J)
    local = random_locals(rng, (4,), J, scale=True)
    world, dq, residual = forward_kinematics(parents, local, device=device, return_dq=True)
    # rebuild world = [R(dq)·S | t(dq)] with an independent quaternion → matrix formula
    r, d = dq[..., :4].astype(np.float64), dq[..., 4:].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.sum(r * d, -1), 0.0, atol=1e-5)  # Plücker condition
    R = (Rotation.from_quat(r[..., [1, 2, 3, 0]].reshape(-1, 4)).as_matrix()
         .reshape(r.shape[:-1] + (3, 3)))
    # t = 2·d·r*  (vector part)
    rw, rv = r[..., :1], -r[..., 1:]
    dw, dv = d[..., :1], d[..., 1:]
    t = 2 * (dw * rv + rw * dv + np.cross(dv, rv))
    ref = chain_product(parents, local)
    np.testing.assert_allclose(R @ residual, ref[..., :3, :3], atol=2e-5)
    np.testing.assert_allclose(t, ref[..., :3, 3], atol=2e-5)


def test_rigid_residual_is_identity(device):
    rng = np.random.default_rng(6)
    parents = random_hierarchy(rng, 16)
    _, _, residual = forward_kinematics(parents, random_locals(rng, (3,), 16), device=device,
                                        return_dq=True)
    np.testing.assert_allclose(residual, np.broadcast_to(np.eye(3), residual.shape), atol=1e-5)


def test_skeleton_rest_pose_reproduces_bind(device):
    rng = np.random.default_rng(7)
    J = 12
    parents = random_hierarchy(rng, J)
    bind = chain_product(parents, random_locals(rng, (), J))
    skel = Skeleton([f"j{i}" for i in range(J)], parents, bind)
    np.testing.assert_allclose(skel.forward_kinematics(device=device), bind, atol=1e-5)
    xf = skel.skinning_transforms(device=device)
    np.testing.assert_allclose(xf, np.broadcast_to(np.eye(4), xf.shape), atol=1e-5)


@pytest.mark.parametrize("parents,match", [
    ([-1, 2, 1], "cycle"),
    ([-1, 2, 0], "before its parent"),
    ([-1, 5], "out of range"),
    ([-1, -3], "out of range"),
])
def test_bad_hierarchy_raises(parents, match):
    with pytest.raises(ValueError, match=match):
        Skeleton([f"j{i}" for i in range(len(parents))], parents)


def test_mismatched_counts_raise():
    with pytest.raises(ValueError, match="joint names"):
        Skeleton(["a", "b"], [-1, 0, 1])
    with pytest.raises(ValueError, match="bind_transforms"):
        Skeleton(["a", "b"], [-1, 0], np.eye(4)[None])


@pytest.mark.parametrize("scaled", [False, True], ids=["rigid", "scaled"])
def test_fk_from_trs_matches_matrices(device, scaled):
    rng = np.random.default_rng(11)
    J = 20
    parents = random_hierarchy(rng, J)
    rot = Rotation.random((3 * J), random_state=rng)
    t = rng.normal(size=(3, J, 3))
    s = rng.uniform(0.5, 2.0, size=(3, J, 3)) if scaled else None
    M = np.tile(np.eye(4), (3, J, 1, 1))
    M[..., :3, :3] = rot.as_matrix().reshape(3, J, 3, 3) * (1 if s is None else s[..., None, :])
    M[..., :3, 3] = t
    q_wxyz = rot.as_quat()[:, [3, 0, 1, 2]].reshape(3, J, 4)
    world = forward_kinematics(parents, (t, q_wxyz, s), device=device)
    ref = chain_product(parents, M)
    assert np.abs(world - ref).max() / np.abs(ref).max() <= 1e-5


def test_fk_every_quaternion_case_and_near_half_turns(device):
    """Shepperd's four cases (largest of trace, x, y, z diagonal terms) picked by selects:
    half turns and near half turns about each axis and between axes, and the identity, each
    composed under a random parent, against the float64 matrix chain."""
    rng = np.random.default_rng(21)
    axes = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1], [1, 0, 1], [1, 1, 1]]
    rots = [Rotation.identity()] + [Rotation.from_rotvec(np.pi * a * np.asarray(v) /
                                                         np.linalg.norm(v))
                                    for v in axes for a in (1.0, 0.999, -0.9999)]
    J = 2 * len(rots)
    parents = np.array([-1 if j % 2 == 0 else j - 1 for j in range(J)])
    local = np.tile(np.eye(4), (J, 1, 1))
    for i, r in enumerate(rots):
        local[2 * i, :3, :3] = Rotation.random(random_state=rng).as_matrix()
        local[2 * i + 1, :3, :3] = r.as_matrix()
    local[:, :3, 3] = rng.normal(size=(J, 3))
    world, dq, residual = forward_kinematics(parents, local, device=device, return_dq=True)
    np.testing.assert_allclose(world, chain_product(parents, local), atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(dq[:, :4], axis=-1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(residual, np.broadcast_to(np.eye(3), residual.shape))


@pytest.mark.parametrize("rotate", [False, True], ids=["identity", "rotated"])
def test_fk_translations_near_the_float32_limit(device, rotate):
    """Translations up to 3e38 (float32 max 3.4e38) whose world position fits: no overflow
    inside the dual-quaternion product (½·t·q with an unnormalized q would reach inf), from
    matrices and from TRS, against the float64 chain."""
    rng = np.random.default_rng(5)
    parents = np.array([-1, 0, 1])
    local = np.tile(np.eye(4), (3, 1, 1))
    if rotate:  # the root rotates the chain's translations: still within range
        local[0, :3, :3] = Rotation.random(random_state=rng).as_matrix()
    local[1, 1, 3] = 3e38
    local[2, :3, :3] = Rotation.from_rotvec([0.0, 0.0, np.pi]).as_matrix()  # Shepperd z case
    ref = chain_product(parents, local)
    world = forward_kinematics(parents, local.astype(np.float32), device=device)
    assert np.isfinite(world).all()
    np.testing.assert_allclose(world[:, :3, 3], ref[:, :3, 3], rtol=1e-5, atol=1e-6 * 3e38)
    q = Rotation.from_matrix(local[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
    trs = forward_kinematics(parents, (local[:, :3, 3], q, None), device=device)
    np.testing.assert_allclose(trs[:, :3, 3], ref[:, :3, 3], rtol=1e-5, atol=1e-6 * 3e38)


def test_fk_large_finite_translations_are_not_flagged(device):
    """A local matrix whose entries are finite but whose column sums pass float32 max is not
    flagged as NaN/inf (the finiteness check scales each entry by 0 before summing)."""
    local = np.eye(4)[None]
    local[0, :2, 3] = 3e38
    world = forward_kinematics([-1], local.astype(np.float32), device=device)
    np.testing.assert_allclose(world[0, :2, 3], 3e38, rtol=1e-6)


def test_fk_rigid_children_of_scaled_parents(device):
    """A rigid joint under a scaled or sheared one takes the residual path; a rigid joint under
    a rigid child of a scaled one too (the residual is inherited), checked at every depth."""
    rng = np.random.default_rng(22)
    J = 12
    parents = np.arange(-1, J - 1)  # one chain
    local = random_locals(rng, (3,), J)
    local[:, 2, :3, :3] = local[:, 2, :3, :3] @ np.diag([2.0, 0.5, 1.5])
    local[:, 7, :3, :3] = local[:, 7, :3, :3] @ (np.eye(3) + 0.4 * np.triu(np.ones((3, 3)), 1))
    world, _, residual = forward_kinematics(parents, local, device=device, return_dq=True)
    ref = chain_product(parents, local)
    assert np.abs(world - ref).max() / np.abs(ref).max() <= 1e-5
    rigid = np.all(np.abs(residual - np.eye(3)) <= 1e-6, axis=(-1, -2))
    assert rigid[:, :2].all() and not rigid[:, 2:].any()
    # a mirror (orthonormal, det −1) is not a rotation: the residual carries the reflection
    local = random_locals(rng, (3,), J)
    local[:, 1, :3, :3] = local[:, 1, :3, :3] @ np.diag([1.0, -1.0, 1.0])
    world, _, residual = forward_kinematics(parents, local, device=device, return_dq=True)
    ref = chain_product(parents, local)
    assert np.abs(world - ref).max() / np.abs(ref).max() <= 1e-5
    np.testing.assert_allclose(np.linalg.det(residual[:, 1:]), -1.0, atol=1e-5)


def test_fk_many_skeletons_in_one_launch(device):
    """The launcher over a concatenated joint axis (crowds): skeletons of different sizes, one
    rigid and one scaled, several frames, each against its own float64 chain."""
    import warp as wp

    from dqskin.kernels import fk as FK

    rng = np.random.default_rng(23)
    sizes, F = [5, 9, 1, 7], 3
    hierarchies = [random_hierarchy(rng, n) for n in sizes]
    locals_ = [random_locals(rng, (F,), n, scale=(i == 1), shear=(i == 3))
               for i, n in enumerate(sizes)]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    parents = np.concatenate([np.where(h >= 0, h + a, -1) for h, a in zip(hierarchies, starts)])
    local = np.concatenate(locals_, axis=1).astype(np.float32)
    out = FK.world_poses(int(F * starts[-1]), device)
    FK.forward_kinematics(parents=wp.array(parents.astype(np.int32), device=device),
                          skeleton_start=wp.array(starts.astype(np.int32), device=device),
                          local=wp.array(local.reshape(-1, 4, 4), dtype=wp.mat44, device=device),
                          out=out, device=device)
    world = out.matrices.numpy().reshape(F, starts[-1], 4, 4)
    for h, loc, a, n in zip(hierarchies, locals_, starts, sizes):
        ref = chain_product(h, loc)
        assert np.abs(world[:, a:a + n] - ref).max() / np.abs(ref).max() <= 1e-5


def test_fk_leaves_its_input_alone_and_returns_its_own_arrays(device):
    """On the CPU a float32 contiguous pose is read in place: never written, never aliased by
    the result; TRS rotations of any positive length are normalized."""
    rng = np.random.default_rng(24)
    parents = random_hierarchy(rng, 6)
    local = random_locals(rng, (2,), 6).astype(np.float32)
    before = local.copy()
    world = forward_kinematics(parents, local, device=device)
    np.testing.assert_array_equal(local, before)
    assert not np.shares_memory(world, local)
    rot = Rotation.random(12, random_state=rng)
    q = rot.as_quat()[:, [3, 0, 1, 2]].reshape(2, 6, 4).astype(np.float32)
    t = rng.normal(size=(2, 6, 3)).astype(np.float32)
    lengths = rng.uniform(0.01, 50.0, size=(2, 6, 1)).astype(np.float32)
    got = forward_kinematics(parents, (t, q * lengths, None), device=device)
    unit = np.tile(np.eye(4), (2, 6, 1, 1))
    unit[..., :3, :3] = rot.as_matrix().reshape(2, 6, 3, 3)
    unit[..., :3, 3] = t
    np.testing.assert_allclose(got, chain_product(parents, unit), atol=2e-5)


# -- hostile input: every fault is a one-line ValueError naming argument, frame and joint --------

NAMES = ["Hips", "Spine", "Head"]
CHAIN = [-1, 0, 1]


def _raises(call, message):
    """``call()`` raises dqskin's InputError (a ValueError; not a library's such as LinAlgError)
    on one line containing ``message``."""
    with pytest.raises(ValueError) as err:
        call()
    assert isinstance(err.value, InputError), repr(err.value)
    assert "\n" not in str(err.value) and message in str(err.value), str(err.value)


def _trs(frames=5):
    t = np.zeros((frames, 3, 3))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (frames, 3, 1))
    return t, q, np.ones((frames, 3, 3))


@pytest.mark.parametrize("what,value,message", [
    ("rotations", np.nan, "rotations: NaN at frame 3, joint 'Hips'"),
    ("translations", np.inf, "translations: infinite value at frame 3, joint 'Hips'"),
    ("scales", -np.inf, "scales: infinite value at frame 3, joint 'Hips'"),
    ("translations", 1e39, "translations: 1e+39 at frame 3, joint 'Hips' overflows float32"),
])
def test_trs_pose_non_finite_raises(what, value, message):
    """A NaN quaternion used to become the identity on the device; now the host refuses it."""
    skel = Skeleton(NAMES, CHAIN)
    t, q, s = _trs()
    {"translations": t, "rotations": q, "scales": s}[what][3, 0, 0] = value
    _raises(lambda: skel.forward_kinematics((t, q, s)), message)
    _raises(lambda: skel.skinning_transforms((t, q, s)), message)
    _raises(lambda: forward_kinematics(CHAIN, (t, q, s)), message.replace("'Hips'", "0"))


def test_zero_quaternion_raises():
    t, q, s = _trs()
    q[2, 1] = 0.0
    skel = Skeleton(NAMES, CHAIN)
    _raises(lambda: skel.forward_kinematics((t, q, None)),
            "rotations: zero quaternion at frame 2, joint 'Spine'")
    q[2, 1] = [1e-30, 0, 0, 0]  # squared norm underflows float32: the device cannot normalize
    _raises(lambda: skel.forward_kinematics((t, q, None)), "at frame 2, joint 'Spine' cannot be")
    q[2, 1] = [0, 0, 3e19, 0]  # squared norm overflows float32
    _raises(lambda: skel.forward_kinematics((t, q, None)),
            "rotations: quaternion of norm 3e+19 at frame 2, joint 'Spine' cannot be normalized")
    q[2, 1] = [0, 0, 1e19, 0]  # just inside: squared norm 1e38 < float32's 3.4e38
    assert np.isfinite(skel.forward_kinematics((t, q, None))).all()


@pytest.mark.parametrize("value,message", [
    (np.nan, "local_transforms: NaN at frame 1, joint 'Head'"),
    (np.inf, "local_transforms: infinite value at frame 1, joint 'Head'"),
    (-4e38, "local_transforms: -4e+38 at frame 1, joint 'Head' overflows float32"),
])
def test_local_matrix_non_finite_raises(value, message):
    """NaN/inf in a local matrix used to make the child's world transform the identity."""
    local = np.tile(np.eye(4), (2, 3, 1, 1))
    local[1, 2, 0, 3] = value
    skel = Skeleton(NAMES, CHAIN)
    _raises(lambda: skel.forward_kinematics(local), message)
    _raises(lambda: skel.skinning_transforms(local, as_warp=True), message)
    _raises(lambda: forward_kinematics(CHAIN, local), message.replace("'Head'", "2"))


@pytest.mark.parametrize("value,message", [
    (np.nan, "local_transforms: NaN at frame 1, joint 'Head'"),
    (-np.inf, "local_transforms: infinite value at frame 1, joint 'Head'"),
    (3e30, None),  # finite, its square beyond float32: a one-pass sum-of-squares test overflows
])
def test_float32_pose_checked(value, message):
    """float32 poses (read in place on the CPU) are checked as float64 ones: a fault is named,
    and a huge but finite value still runs (against the float64 chain)."""
    local = np.tile(np.eye(4, dtype=np.float32), (2, 3, 1, 1))
    local[1, 2, 0, 3] = value
    skel = Skeleton(NAMES, CHAIN)
    t, q, s = (a.astype(np.float32) for a in _trs(2))
    t[1, 2, 0] = value
    if message is None:
        ref = chain_product(np.array(CHAIN), local.astype(np.float64))
        np.testing.assert_allclose(skel.forward_kinematics(local), ref, rtol=1e-6)
        assert np.isfinite(skel.forward_kinematics((t, q, s))).all()
        return
    _raises(lambda: skel.forward_kinematics(local), message)
    _raises(lambda: skel.forward_kinematics((t, q, s)),
            message.replace("local_transforms", "translations"))


def test_batch_index_and_unbatched_pose_in_messages():
    local = np.tile(np.eye(4), (2, 3, 3, 1, 1))
    local[1, 2, 0, 1, 1] = np.nan
    _raises(lambda: Skeleton(NAMES, CHAIN).forward_kinematics(local),
            "local_transforms: NaN at frame (1, 2), joint 'Hips'")
    t, q, _ = _trs(1)
    q[0, 2] = np.nan
    _raises(lambda: forward_kinematics(CHAIN, (t[0], q[0], None)), "rotations: NaN at joint 2")


def test_non_numeric_local_transforms_raise():
    _raises(lambda: forward_kinematics(CHAIN, np.full((3, 4, 4), "a")),
            "local_transforms: expected real numbers")
    _raises(lambda: forward_kinematics(CHAIN, [np.zeros((3, 3))] * 2), "a TRS pose is")
    _raises(lambda: forward_kinematics(CHAIN, np.full((3, 4, 4), 1j)), "expected real numbers")
    _raises(lambda: forward_kinematics([], np.zeros((0, 4, 4))), "parents: no joints")


def test_skeleton_needs_joints():
    _raises(lambda: Skeleton([], []), "skeleton: no joints (a skeleton needs at least one joint)")
    _raises(lambda: Skeleton([], [], name="/Rig"), "/Rig: no joints")
    _raises(lambda: Skeleton(None, [-1]), "joint_names: expected a sequence")


def test_duplicate_joint_names_raise():
    _raises(lambda: Skeleton(["a", "b", "a"], [-1, 0, 1], name="/Rig"),
            "/Rig: joint_names: duplicate joint name 'a'")
    _raises(lambda: Skeleton(["a", "b", "a", "b"], [-1, 0, 1, 2]),
            "duplicate joint names 'a', 'b'")


@pytest.mark.parametrize("rest", [False, True], ids=["derived-rest", "given-rest"])
def test_singular_bind_transforms_raise(rest):
    """np.linalg.inv used to raise a bare LinAlgError ('Singular matrix')."""
    bind = np.tile(np.eye(4), (3, 1, 1))
    bind[1, :3, :3] = 0.0
    bind[2, :3, :3] = np.diag([1.0, 1e-20, 1.0])  # numerically singular
    local = np.tile(np.eye(4), (3, 1, 1)) if rest else None
    _raises(lambda: Skeleton(NAMES, CHAIN, bind, local, name="/Rig"),
            "/Rig: bind_transforms: singular bind transform at joints 'Spine', 'Head'")


def test_non_finite_bind_rest_and_world_raise():
    bad = np.tile(np.eye(4), (3, 1, 1))
    bad[2, 1, 1] = np.nan
    _raises(lambda: Skeleton(NAMES, CHAIN, bad), "bind_transforms: NaN or infinite entries at "
                                                 "joint 'Head'")
    _raises(lambda: Skeleton(NAMES, CHAIN, None, bad), "rest_transforms: NaN or infinite entries "
                                                       "at joint 'Head'")
    bad[2, 1, 1] = 1e39
    _raises(lambda: Skeleton(NAMES, CHAIN, bad), "beyond float32 range")
    _raises(lambda: Skeleton(NAMES, CHAIN, world_transform=np.full((4, 4), np.inf)),
            "world_transform: NaN or infinite entries")
    _raises(lambda: Skeleton(NAMES, CHAIN, {"not": "matrices"}), "bind_transforms")


def test_native_fk_steps_both_branches_against_float64():
    """kernels/fk_native.py: the CPU (vector) branch and the CUDA (scalar) branch, both compiled
    for the CPU, against float64 dual quaternions: the rigid step ``parent·η(R, t)``, the matrix
    of a unit DQ, and the local check (finite; rotation error of rotations, reflections,
    scales). Rotations cover every Shepperd case (trace, then each diagonal term largest)."""
    import warp as wp
    from fk_scalar_twin import both_branches  # tests/ is on the path of its tests

    from dqskin import dq
    from dqskin._warp import init_warp
    from dqskin.kernels.dqmath import vec8

    init_warp()
    rng = np.random.default_rng(7)
    n = 400
    rot = Rotation.random(n, random_state=rng)
    half_turns = Rotation.from_rotvec(np.pi * np.eye(3))  # x, y, z diagonal terms largest
    rot = Rotation.concatenate([rot, half_turns, Rotation.identity()])
    n = len(rot)
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = rot.as_matrix()
    m[:, :3, 3] = rng.normal(scale=5.0, size=(n, 3))
    q_par = Rotation.random(n, random_state=rng).as_quat()[:, [3, 0, 1, 2]]
    parent = dq.from_rt(q_par, rng.normal(size=(n, 3)))
    has = (np.arange(n) % 3 != 0).astype(np.int32)  # every third joint a root
    step, matrix, check = (wp.empty((2, n), dtype=t, device="cpu")
                           for t in (vec8, wp.mat44, wp.vec2))
    wp.launch(both_branches, dim=n, device="cpu", inputs=[
        wp.array(m.astype(np.float32), dtype=wp.mat44, device="cpu"),
        wp.array(parent.astype(np.float32), dtype=vec8, device="cpu"),
        wp.array(has, dtype=int, device="cpu"), step, matrix, check])
    local = dq.from_matrix(m)
    expected = np.where(has[:, None] == 1, dq.mul(parent, local), local)
    got = step.numpy()
    sign = np.sign(np.sum(got[:, :, :4] * expected[None, :, :4], -1, keepdims=True))
    for branch in (0, 1):
        np.testing.assert_allclose(got[branch] * sign[branch], expected, atol=5e-6)
        np.testing.assert_allclose(matrix.numpy()[branch], dq.to_matrix(parent), atol=5e-6)
    ck = check.numpy()
    assert np.all(ck[:, :, 0] == 0) and np.all(ck[:, :, 1] < 1e-6)  # finite rotations
    bad = m[:8].copy()
    bad[0, 1, 2] = np.nan
    bad[1, 0, 3] = np.inf
    bad[2, :3, 0] *= -1  # a reflection
    bad[3, :3, :3] *= 1.001  # a uniform scale
    bad[4, :3, 1] += 1e-3 * bad[4, :3, 0]  # a shear
    bad[5, :3, 3] = 3e38  # finite, though a sum of its entries is not
    wp.launch(both_branches, dim=8, device="cpu", inputs=[
        wp.array(bad.astype(np.float32), dtype=wp.mat44, device="cpu"),
        wp.array(parent[:8].astype(np.float32), dtype=vec8, device="cpu"),
        wp.array(has[:8], dtype=int, device="cpu"), step[:, :8], matrix[:, :8],
        check[:, :8]])
    ck = check.numpy()[:, :8]
    assert np.all(np.isnan(ck[:, :2, 0])) and np.all(ck[:, 2:, 0] == 0)
    assert np.all(ck[:, 2:5, 1] > 1e-3) and np.all(ck[:, 5:, 1] < 1e-6)


def _fk_by_path(parents, local, monkeypatch, path):
    """``forward_kinematics(..., return_dq=True)`` on the CPU through the packet kernel, the packet
    kernel over its CUDA branch (every frame left to the one-frame path: ``fk_packet_twin.py``), or
    the one-frame kernel."""
    from dqskin.kernels import fk as FK

    with monkeypatch.context() as m:
        if path == "one-frame":
            m.setattr(FK, "PACKET_MIN_FRAMES", 10**9)
        elif path == "no lane":
            from fk_packet_twin import fallback_kernel  # tests/ is on the path of its tests

            m.setattr(FK, "forward_kinematics_packet_kernel", fallback_kernel)
        return forward_kinematics(parents, local, device="cpu", return_dq=True)


def test_fk_packets_with_mixed_lanes(monkeypatch):
    """13 frames (packets of eight and five) of a 20-joint hierarchy where one joint's lanes
    split between the packet and the one-frame path: joint 3 scaled in three frames, joint 7 a
    reflection in one, a child of a scaled parent (rigid itself) in frames 8-12, joint 9's
    rotation error around the 1e-6 threshold of the rigid path. Each path against the float64
    chain; the packet kernel equals the one-frame kernel bit for bit (a bake must not depend on
    how its frames are chunked), and the packet kernel over its CUDA branch (every frame on the
    one-frame path's general code) to float32 precision."""
    rng = np.random.default_rng(11)
    J, F = 20, 13
    parents = random_hierarchy(rng, J)
    local = random_locals(rng, (F,), J)
    local[[0, 5, 9], 3, :3, :3] *= 1.3
    local[2, 7, :3, :3] = local[2, 7, :3, :3] @ np.diag([1.0, 1.0, -1.0])
    child = int(np.flatnonzero(parents > 0)[-1])
    local[8:, parents[child], :3, :3] *= np.array([1.2, 0.9, 1.1])
    local[:, 9, :3, :3] *= (1.0 + np.linspace(-8e-7, 8e-7, F))[:, None, None] ** 0.5
    ref = chain_product(parents, local)
    out = {p: _fk_by_path(parents, local, monkeypatch, p)
           for p in ("packet", "no lane", "one-frame")}
    for path, (world, _, _) in out.items():
        assert np.abs(world - ref).max() / np.abs(ref).max() <= 1e-5, path
    for a, b in zip(out["packet"], out["one-frame"]):  # bit for bit: chunking changes nothing
        np.testing.assert_array_equal(a, b)
    for a, b in zip(out["packet"][1:], out["no lane"][1:]):
        np.testing.assert_allclose(a, b, atol=1e-5)
    assert not np.allclose(out["packet"][2][:, 3], np.eye(3))  # scaled lanes kept a residual


@pytest.mark.parametrize("entry,value,message", [
    ((1, 2), np.nan, "NaN"), ((0, 3), np.nan, "NaN"), ((2, 3), np.inf, "infinite value"),
    ((3, 1), np.nan, "NaN"), ((1, 3), 1e39, "1e+39")])
def test_fk_packets_flag_a_bad_value_in_one_lane(entry, value, message):
    """A NaN, inf or beyond-float32 value in frame 9 of 12 (the second packet), in the rotation,
    the translation or the bottom row of an otherwise rigid joint, is named by frame and joint,
    as the one-frame kernel's check does (the packet's rigid test reads the 3×3 part only: the
    finiteness of all sixteen entries must send the frame back)."""
    rng = np.random.default_rng(12)
    parents = random_hierarchy(rng, 6)
    local = random_locals(rng, (12,), 6)
    local[(9, 4) + entry] = value
    import re

    with pytest.raises(ValueError, match=rf"local_transforms: {re.escape(message)} at frame 9, "
                                         r"joint 4"):
        forward_kinematics(parents, local, device="cpu")


def test_fk_packets_crowd_of_skeletons():
    """Three skeletons of 5, 11 and 1 joints, 9 frames, in one packet launch (rows of eight and
    one frames per skeleton) against the float64 chain of each."""
    import warp as wp

    from dqskin._warp import init_warp
    from dqskin.kernels import fk as FK

    init_warp()
    rng = np.random.default_rng(13)
    sizes, F = (5, 11, 1), 9
    hierarchies = [random_hierarchy(rng, n) for n in sizes]
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32)
    parents = np.concatenate([h + np.where(h >= 0, s, 0) for h, s in zip(hierarchies, starts)])
    local = random_locals(rng, (F,), int(starts[-1]), scale=False)
    out = FK.world_poses(F * int(starts[-1]), "cpu")
    FK.forward_kinematics(parents=wp.array(parents, dtype=wp.int32, device="cpu"),
                          skeleton_start=wp.array(starts, dtype=wp.int32, device="cpu"),
                          local=wp.array(local.reshape(-1, 4, 4).astype(np.float32),
                                         dtype=wp.mat44, device="cpu"),
                          out=out, device="cpu")
    world = out.matrices.numpy().reshape(F, -1, 4, 4)
    for h, a, b in zip(hierarchies, starts[:-1], starts[1:]):
        ref = chain_product(h, local[:, a:b])
        assert np.abs(world[:, a:b] - ref).max() / np.abs(ref).max() <= 1e-5
    assert out.rigid.numpy().all()
