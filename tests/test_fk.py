"""Forward kinematics against float64 matrix chains and UsdSkel's skeleton query."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

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
