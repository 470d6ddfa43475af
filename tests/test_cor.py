"""``method="cor"``: optimized centers of rotation (Le & Hodgins 2016).

The centers are checked against a brute-force float64 evaluation of the paper's formula (every
vertex against every triangle, the similarity summed over all joint pairs), and the skinned points
against ``R·(v − p*) + Σ wⱼ·Aⱼ·[p*, 1]`` with ``R`` from SciPy quaternions, on a chain of four
joints (bent at every joint: a twist alone cannot tell a wrong center on the axis from the right
one). Both sign rules give the same result on that chain, so the rules are checked on a random
rig (4 random influences, random joint rotations, random triangles) where their references differ
on more than 10% of the vertices (asserted first). Then the exact merging on the bundled rigs, the
clustering error bound, the procedural rigs (candy wrapper, bend), one-hot and near-one-hot
vertices, a geomBindTransform, velocities (central differences of the reference), normals, the
disk cache, Scene.skin, the CLI and compare.
"""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_sign_reference import (
    RULES,
    differ_fraction,
    dqs_reference,
    hamilton,
    motion,
    random_rig,
    rotate,
    rotation_blend,
    run_cli,
    usdskel_transforms,
    write_usd_rig,
)

import dqskin
from dqskin import CorOptions, cor
from dqskin.motion import skinned_velocities
from dqskin.skinning import Skinner

ASSETS = Path(__file__).resolve().parents[1] / "assets"


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    """Every test gets its own center cache (also the CLI it runs)."""
    path = tmp_path / "cache"
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(path))
    return path


# ---------------------------------------------------------------------------------------------
# float64 reference, from the paper


def dense(idx, wts, J):
    W = np.zeros((len(idx), J))
    np.add.at(W, (np.arange(len(idx))[:, None], idx), wts)
    return W


def subdivided(tri, corner_w, eps, max_levels=8):
    """The paper's refinement, one triangle at a time: split 1→4 at the edge midpoints until the
    weights at both ends of every edge are within ``eps`` (Euclidean distance). The cap of
    ``max_levels`` = 8 splits and stopping per piece as soon as its own edges pass are our choices
    (the paper gives ε = 0.1 but neither a cap nor the exact stop rule); this oracle checks that
    the engine does what we chose, not that it is the paper's exact refinement."""
    out_p, out_w = [], []

    def split(p, w, level):
        gap = max(np.linalg.norm(w[a] - w[b]) for a, b in ((0, 1), (1, 2), (2, 0)))
        if gap <= eps or level == max_levels:
            out_p.append(p)
            out_w.append(w)
            return
        mp = [(p[a] + p[b]) / 2 for a, b in ((0, 1), (1, 2), (2, 0))]
        mw = [(w[a] + w[b]) / 2 for a, b in ((0, 1), (1, 2), (2, 0))]
        for c in ((0, 3, 5), (3, 1, 4), (5, 4, 2), (3, 4, 5)):
            split(np.stack([[*p, *mp][i] for i in c]), np.stack([[*w, *mw][i] for i in c]),
                  level + 1)
    for p, w in zip(tri, corner_w):
        split(p, w, 0)
    return np.array(out_p), np.array(out_w)


def centers_reference(points, faces, idx, wts, sigma=0.1, subdivide=None, vertices=None):
    """``p*ᵢ = Σₜ s(wᵢ, wₜ)·aₜ·cₜ / Σₜ s(wᵢ, wₜ)·aₜ``, brute force; NaN where the sum is 0.
    ``vertices``: only these rows (every triangle still counts)."""
    J = int(idx.max()) + 1
    W = dense(idx, np.asarray(wts, np.float64), J)
    tri, corner_w = points[faces], W[faces]
    if vertices is not None:
        W = W[vertices]
    if subdivide is not None:
        tri, corner_w = subdivided(tri, corner_w, subdivide)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    Wt = corner_w.mean(axis=1)
    wv = W[:, None, :, None] * W[:, None, None, :]
    wt = Wt[None, :, :, None] * Wt[None, :, None, :]
    diff = W[:, None, :, None] * Wt[None, :, None, :] - W[:, None, None, :] * Wt[None, :, :, None]
    terms = wv * wt * np.exp(-diff ** 2 / sigma ** 2)
    terms[..., np.arange(J), np.arange(J)] = 0.0  # j ≠ k
    s = terms.sum(axis=(2, 3)) * area[None]
    den = s.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = (s @ tri.mean(axis=1)) / den[:, None]
    c[den <= 0] = np.nan
    return c


def cor_reference(points, idx, wts, xforms, centers, rule="largest_weight"):
    """(F, V, 3): ``R·(v − p*) + Σ wⱼ·Aⱼ·[p*, 1]``; DQS where there is no center."""
    r, _ = rotation_blend(xforms, idx, wts, rule)
    c = np.where(np.isnan(centers), 0.0, centers)
    ch = np.c_[c, np.ones(len(c))]
    lbs_c = np.einsum("vk,fvkij,vj->fvi", wts, xforms[:, idx, :3, :], ch)
    out = rotate(r, (points - c)[None]) + lbs_c
    none = np.isnan(centers[:, 0])
    out[:, none] = dqs_reference(points, idx, wts, xforms, rule)[:, none]
    return out


def cor_residual_reference(points, idx, wts, xforms, centers):
    """:func:`cor_reference` of transforms with scale/shear: each ``A = R·S`` (polar), the blended
    residual ``Σ wⱼ·Sⱼ`` on ``v − p*`` (and, for DQS without a center, on ``v``). The paper has
    rigid joints only: applying ``Σ wⱼ·Sⱼ`` to ``v − p*`` before the rotation is our design choice
    for scale and shear (as UsdSkel's DQS does to ``v``), checked here as chosen."""
    lin = xforms[..., :3, :3]
    rot = Rotation.from_matrix(lin.reshape(-1, 3, 3)).as_matrix().reshape(lin.shape)
    res = np.einsum("fjki,fjkl->fjil", rot, lin)  # Rᵀ·A
    s_blend = np.einsum("vk,fvkij->fvij", wts, res[:, idx])
    rigid = xforms.copy()
    rigid[..., :3, :3] = rot
    r, d = rotation_blend(rigid, idx, wts, "largest_weight")
    c = np.where(np.isnan(centers), 0.0, centers)
    lbs_c = np.einsum("vk,fvkij,vj->fvi", wts, xforms[:, idx, :3, :], np.c_[c, np.ones(len(c))])
    out = rotate(r, np.einsum("fvij,vj->fvi", s_blend, points - c)) + lbs_c
    none = np.isnan(centers[:, 0])
    t = 2.0 * hamilton(d, r * np.array([1, -1, -1, -1]))[..., 1:] / np.sum(r * r, -1,
                                                                           keepdims=True)
    dqs = rotate(r, np.einsum("fvij,vj->fvi", s_blend, points)) + t
    out[:, none] = dqs[:, none]
    return out


# ---------------------------------------------------------------------------------------------
# a chain of four joints along x


JOINT_X = np.array([0.0, 1.5, 3.0, 4.5])
BONE_MID = np.array([0.75, 2.25, 3.75, 5.25])


def chain_mesh(around=12, rings=31, length=6.0, radius=0.5, seed=0):
    """Open tube along +x; weights ``max(0, 1 − |x − mⱼ|/1.6)`` around each bone's middle, with
    ±10% per-vertex noise: one-hot near both ends, three joints around x = 2.2, two elsewhere."""
    x = np.linspace(0, length, rings)
    a = np.linspace(0, 2 * np.pi, around, endpoint=False)
    X, A = np.meshgrid(x, a, indexing="ij")
    pts = np.stack([X, radius * np.cos(A), radius * np.sin(A)], -1).reshape(-1, 3)
    faces = []
    for i in range(rings - 1):
        for j in range(around):
            p, q = i * around + j, i * around + (j + 1) % around
            faces += [[p, q, q + around], [p, q + around, p + around]]
    w = np.maximum(0.0, 1.0 - np.abs(pts[:, :1] - BONE_MID[None]) / 1.6)
    w *= 1 + 0.1 * np.random.default_rng(seed).random(w.shape) * (w > 0)
    w = (w / w.sum(1, keepdims=True)).astype(np.float32).astype(np.float64)
    idx = np.tile(np.arange(4), (len(pts), 1))
    return pts, np.array(faces), idx, w


def chain_pose(rng, frames=3, max_angle=np.radians(110)):
    """(F, 4, 4, 4) skinning transforms of random bends/twists at every joint of the chain."""
    out = np.zeros((frames, 4, 4, 4))
    for f in range(frames):
        world = np.eye(4)
        for j in range(4):
            local = np.eye(4)
            axis = rng.normal(size=3)
            local[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(
                0.3, 1.0) * max_angle).as_matrix()
            local[0, 3] = JOINT_X[j] - (JOINT_X[j - 1] if j else 0.0)
            world = world @ local
            inv_bind = np.eye(4)
            inv_bind[0, 3] = -JOINT_X[j]
            out[f, j] = world @ inv_bind
    return out


def test_centers_match_reference_on_a_chain():
    pts, faces, idx, w = chain_mesh()
    want = centers_reference(pts, faces, idx, w)
    got = cor.rotation_centers(pts, faces, idx, w, cache=False)
    np.testing.assert_array_equal(np.isnan(got[:, 0]), np.isnan(want[:, 0]))
    np.testing.assert_allclose(got, want, atol=1e-9)
    # one-hot vertices have none; the rest have a center near the bone axis, not at themselves
    one_hot = (w > 0).sum(1) == 1
    assert np.all(np.isnan(got[one_hot, 0])) and not np.any(np.isnan(got[~one_hot, 0]))
    assert np.abs(got[~one_hot, 1:]).max() < 0.05
    assert ((w > 0).sum(1) == 3).any()


def test_centers_match_reference_on_a_random_soup():
    rng = np.random.default_rng(1)
    V, J, K = 80, 6, 4
    pts = rng.normal(size=(V, 3))
    faces = np.stack([rng.choice(V, 3, replace=False) for _ in range(200)])
    idx = np.stack([rng.permutation(J)[:K] for _ in range(V)])
    idx[:5, 1] = idx[:5, 0]  # a repeated joint sums
    w = rng.random((V, K)).astype(np.float32)
    w[rng.random((V, K)) < 0.3] = 0
    for sigma in (0.1, 0.3):
        want = centers_reference(pts, faces, idx, w.astype(np.float64), sigma)
        got = cor.rotation_centers(pts, faces, idx, w, sigma=sigma, cache=False)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
        np.testing.assert_allclose(got, want, atol=1e-9)


@pytest.mark.parametrize("asset", ["twist_cylinder.usda", "bending_arm.usda"])
def test_exact_merging_on_rigs_with_repeated_weights(asset):
    """Rings of equal weights: the exact path merges equal triangle entries and computes each
    distinct weight vector once; centers against the brute force on a sample of vertices."""
    mesh = dqskin.load(ASSETS / asset).meshes[0]
    pts = np.asarray(mesh.points, np.float64)
    idx, w = mesh.joint_indices, mesh.joint_weights.astype(np.float64)
    distinct = np.unique(np.c_[idx, w], axis=0, return_index=True)[1]
    assert len(distinct) < len(pts) / 50  # (many repeats)
    rows = np.union1d(distinct, np.random.default_rng(0).choice(len(pts), 150, replace=False))
    want = centers_reference(pts, mesh.faces, idx, w, vertices=rows)
    got = cor.rotation_centers(mesh.points, mesh.faces, idx, mesh.joint_weights, cluster=None,
                               cache=False)[rows]
    np.testing.assert_array_equal(np.isnan(got[:, 0]), np.isnan(want[:, 0]))
    assert np.sum(~np.isnan(want[:, 0])) > 20
    np.testing.assert_allclose(got, want, atol=1e-9)


def test_clustering_within_the_documented_bound(monkeypatch, caplog):
    """Clustered centers and the points skinned with them against the exact oracle, within the
    bound rotation_centers documents: grid step × falloff width (1 / the steepest weight
    gradient: ℓ = 1.5 here), for centers and skinned points alike."""
    pts, faces, idx, w = chain_mesh()
    exact = centers_reference(pts, faces, idx, w)
    np.testing.assert_allclose(cor.rotation_centers(pts, faces, idx, w, cluster=None, cache=False),
                               exact, atol=1e-9)
    xf = chain_pose(np.random.default_rng(2))
    want = cor_reference(pts, idx, w, xf, exact)
    err = {}
    for g in (1 / 32, 1 / 256):
        c = cor.rotation_centers(pts, faces, idx, w, cluster=g, cache=False)
        np.testing.assert_array_equal(np.isnan(c[:, 0]), np.isnan(exact[:, 0]))
        got = Skinner(pts, idx, w, faces=faces, cor=CorOptions(cluster=g)).skin(xf, "cor")
        err[g] = (np.nanmax(np.linalg.norm(c - exact, axis=1)),
                  np.linalg.norm(got - want, axis=-1).max())
        assert 1e-6 < err[g][0] <= g * 1.5 and err[g][1] <= g * 1.5, (g, err[g])
    assert err[1 / 256][0] < err[1 / 32][0], err
    # "auto": exact on this small mesh (logged at DEBUG), the CLUSTER grid once the work exceeds
    # AUTO_TERMS (logged at INFO)
    with caplog.at_level("DEBUG", logger="dqskin.cor"):
        np.testing.assert_array_equal(cor.rotation_centers(pts, faces, idx, w, cache=False),
                                      cor.rotation_centers(pts, faces, idx, w, cluster=None,
                                                           cache=False))
    assert [r.levelname for r in caplog.records] == ["DEBUG", "DEBUG"]
    caplog.clear()
    monkeypatch.setattr(cor, "AUTO_TERMS", 0)
    with caplog.at_level("INFO", logger="dqskin.cor"):
        np.testing.assert_array_equal(cor.rotation_centers(pts, faces, idx, w, cache=False),
                                      cor.rotation_centers(pts, faces, idx, w,
                                                           cluster=cor.CLUSTER, cache=False))
    assert len(caplog.records) == 1 and "clustered on a 1/256 grid" in caplog.records[0].message


def test_subdivision_matches_reference_and_refines():
    pts, faces, idx, w = chain_mesh(around=6, rings=11)  # rings 0.6 apart: weights jump ~0.5
    coarse = cor.rotation_centers(pts, faces, idx, w, cache=False)
    got = cor.rotation_centers(pts, faces, idx, w, subdivide=0.1, cache=False)
    np.testing.assert_allclose(got, centers_reference(pts, faces, idx, w, subdivide=0.1),
                               atol=1e-9)
    fine = cor.rotation_centers(pts, faces, idx, w, subdivide=0.04, cache=False)
    err = {name: np.nanmax(np.abs(c - fine)) for name, c in (("coarse", coarse), ("0.1", got))}
    assert err["0.1"] < 0.5 * err["coarse"], err  # the refinement converges
    sk = Skinner(pts, idx, w, faces=faces, cor=CorOptions(subdivide=0.1))
    np.testing.assert_array_equal(sk.rotation_centers(), got)


def test_points_match_reference_on_a_chain(device):
    """(Both sign rules give the same result on this chain -- adjacent joints' quaternions stay in
    one hemisphere -- so the rules are tested on :func:`random_cor_rig` below.)"""
    pts, faces, idx, w = chain_mesh()
    xf = chain_pose(np.random.default_rng(2))
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    rule = "largest_weight"
    got = sk.skin(xf, "cor", sign_reference=rule)
    want = cor_reference(pts, idx, w, xf, centers_reference(pts, faces, idx, w), rule)
    np.testing.assert_allclose(got, want, atol=5e-5)
    # the centers matter: the result is neither DQS nor LBS, nor CoR about the vertex itself
    dqs = dqs_reference(pts, idx, w, xf, rule)
    assert np.abs(got - dqs).max() > 0.05
    wrong = cor_reference(pts, idx, w, xf, pts.copy(), rule)  # p* = v: LBS
    assert np.abs(got - wrong).max() > 0.05


def random_cor_rig(seed, V=200, T=400, J=6, K=4, F=3):
    """``random_rig`` (K random influences of J joints with random world rotations) with T random
    triangles and normalized weights: the sign rules differ on many vertices here."""
    rng = np.random.default_rng(seed)
    pts, idx, w, xf = random_rig(rng, V=V, J=J, K=K, F=F)
    w[np.arange(V), np.argmax(w, 1)] += 0.1  # none all zero
    w = (w / w.sum(1, keepdims=True)).astype(np.float32).astype(np.float64)
    faces = np.stack([rng.choice(V, 3, replace=False) for _ in range(T)])
    return pts, faces, idx, w, xf


def test_points_match_both_rules_on_a_random_rig(device):
    pts, faces, idx, w, xf = random_cor_rig(12)
    centers = centers_reference(pts, faces, idx, w)
    assert np.mean(np.isnan(centers[:, 0])) < 0.05  # nearly all take the COR path
    want = {rule: cor_reference(pts, idx, w, xf, centers, rule) for rule in RULES}
    # the rules really differ here (so the comparison below can fail)
    assert differ_fraction(want["largest_weight"], want["running_sum"]) > 0.1
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    for rule in RULES:
        np.testing.assert_allclose(sk.skin(xf, "cor", sign_reference=rule), want[rule],
                                   atol=5e-5, err_msg=rule)
    np.testing.assert_array_equal(sk.skin(xf, "cor"), sk.skin(xf, "cor",
                                                              sign_reference="largest_weight"))


def test_one_hot_vertices_move_rigidly(device):
    pts, faces, idx, w = chain_mesh()
    xf = chain_pose(np.random.default_rng(3))
    got = dqskin.skin_points(pts, idx, w, xf, "cor", faces=faces, device=device)
    one_hot = (w > 0).sum(1) == 1
    j = np.argmax(w, axis=1)
    rigid = np.einsum("fvij,vj->fvi", xf[:, j, :3, :], np.c_[pts, np.ones(len(pts))])
    np.testing.assert_allclose(got[:, one_hot], rigid[:, one_hot], atol=2e-5)


def test_near_one_hot_vertices_get_a_center(device):
    """Vertices whose weights are one-hot but for 10⁻³ on the neighbouring joint share triangles
    with two-joint pairs: they get a center (the oracle's) and the COR formula, nearly rigid."""
    pts, faces, idx, w = chain_mesh(rings=16)
    one_hot = (w > 0).sum(1) == 1
    j = np.argmax(w, axis=1)
    w = w.copy()
    w[one_hot, j[one_hot]] = 1 - 1e-3
    w[one_hot, np.where(j[one_hot] == 0, 1, j[one_hot] - 1)] = 1e-3
    centers = centers_reference(pts, faces, idx, w)
    assert not np.any(np.isnan(centers[:, 0]))
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    np.testing.assert_allclose(sk.rotation_centers(), centers, atol=1e-9)
    xf = chain_pose(np.random.default_rng(3))
    got = sk.skin(xf, "cor")
    np.testing.assert_allclose(got, cor_reference(pts, idx, w, xf, centers), atol=5e-5)
    rigid = np.einsum("fvij,vj->fvi", xf[:, j, :3, :], np.c_[pts, np.ones(len(pts))])
    off = np.linalg.norm(got - rigid, axis=-1)[:, one_hot]
    assert 1e-5 < off.max() < 0.02, off.max()


def test_one_hot_vertices_with_a_center_move_rigidly(device, monkeypatch):
    """The formula itself: for one-hot weights ``R·(v − p*) + Aⱼ·[p*, 1] = Aⱼ·[v, 1]`` whatever
    the center (the engine gives them none; here every vertex gets a planted one)."""
    from dqskin import skinning

    pts, faces, idx, w = chain_mesh(rings=16)
    planted = pts + np.random.default_rng(7).normal(size=pts.shape)
    monkeypatch.setattr(skinning, "rotation_centers", lambda *a, **k: planted.copy())
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    np.testing.assert_array_equal(sk.rotation_centers(), planted)
    xf = chain_pose(np.random.default_rng(3))
    got = sk.skin(xf, "cor")
    one_hot = (w > 0).sum(1) == 1
    j = np.argmax(w, axis=1)
    rigid = np.einsum("fvij,vj->fvi", xf[:, j, :3, :], np.c_[pts, np.ones(len(pts))])
    np.testing.assert_allclose(got[:, one_hot], rigid[:, one_hot], atol=5e-5)
    np.testing.assert_allclose(got, cor_reference(pts, idx, w, xf, planted), atol=5e-5)


def test_geom_bind_transform(device):
    """Centers are computed in bind space: from ``G·v`` (G rotates, scales unevenly and
    translates, so mesh-space centers mapped by G differ), and points are skinned from there."""
    pts, faces, idx, w, xf = random_cor_rig(15, V=150, T=300, F=2)
    g = np.eye(4)
    g[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix() @ np.diag([2.0, 0.5, 1.2])
    g[:3, 3] = [0.5, -1.0, 2.0]
    bind = pts @ g[:3, :3].T + g[:3, 3]
    centers = centers_reference(bind, faces, idx, w)
    mapped = centers_reference(pts, faces, idx, w) @ g[:3, :3].T + g[:3, 3]
    assert np.nanmax(np.abs(mapped - centers)) > 0.05
    sk = Skinner(pts, idx, w, faces=faces, geom_bind_transform=g, device=device)
    np.testing.assert_allclose(sk.rotation_centers(), centers, atol=1e-9)
    np.testing.assert_allclose(sk.skin(xf, "cor"), cor_reference(bind, idx, w, xf, centers),
                               atol=1e-4)


def test_normals_and_uniform_scale(device):
    pts, faces, idx, w, xf = random_cor_rig(4, F=2)
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    # normals turn by the normalized rotation blend R (of either rule), centers or not
    n = np.random.default_rng(5).normal(size=pts.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    for rule in RULES:
        r, _ = rotation_blend(xf, idx, w, rule)
        np.testing.assert_allclose(sk.skin_vectors(xf, n, "cor", sign_reference=rule),
                                   rotate(r, n[None]), atol=2e-5, err_msg=rule)
    # a uniform scale about the origin on every joint: the float64 residual reference
    centers = centers_reference(pts, faces, idx, w)
    scaled = xf.copy()
    scaled[:, :, :3, :] *= 1.5
    want = cor_residual_reference(pts, idx, w, scaled, centers)
    np.testing.assert_allclose(sk.skin(scaled, "cor"), want, atol=1e-4)
    assert np.abs(want - cor_reference(pts, idx, w, xf, centers)).max() > 0.1  # (it scaled)


def test_scale_and_shear(device):
    """Non-uniform scale and shear on every joint (changing over time): points against the
    residual reference, velocities against its central differences."""
    pts, faces, idx, w = chain_mesh(rings=16)
    rng = np.random.default_rng(8)
    poses = chain_pose(rng, frames=2)
    s0, s1 = rng.uniform(0.7, 1.3, size=(2, 4, 3)), rng.normal(size=(2, 4, 3)) * 0.2
    shear = np.eye(3) + 0.2 * np.triu(rng.normal(size=(3, 3)), 1)

    def at(t):
        x = poses.copy()
        x[..., :3, :3] = np.einsum("fjab,fjbc,cd->fjad", poses[..., :3, :3],
                                   np.eye(3) * (s0 + t * s1)[..., None, :], shear)
        return x
    centers = centers_reference(pts, faces, idx, w)
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    np.testing.assert_allclose(sk.skin(at(0.0), "cor"),
                               cor_residual_reference(pts, idx, w, at(0.0), centers), atol=1e-4)
    h = 1e-5
    got = sk.skin_velocities(at(0.0), (at(h) - at(-h)) / (2 * h), "cor")
    want = (cor_residual_reference(pts, idx, w, at(h), centers)
            - cor_residual_reference(pts, idx, w, at(-h), centers)) / (2 * h)
    np.testing.assert_allclose(got, want, atol=2e-3 * np.abs(want).max())


def test_velocities_match_central_differences(device):
    """Both sign rules, on a random rig where they differ (random joint rotations moving)."""
    pts, faces, idx, w, _ = random_cor_rig(13, V=150, T=300)
    at = motion(np.random.default_rng(14), 6)
    centers = centers_reference(pts, faces, idx, w)
    h = 1e-5
    want = {rule: (cor_reference(pts, idx, w, at(h), centers, rule)
                   - cor_reference(pts, idx, w, at(-h), centers, rule)) / (2 * h)
            for rule in RULES}
    pos = {rule: cor_reference(pts, idx, w, at(0.0), centers, rule) for rule in RULES}
    assert differ_fraction(pos["largest_weight"], pos["running_sum"]) > 0.1
    assert differ_fraction(want["largest_weight"], want["running_sum"]) > 0.1
    for rule in RULES:
        got = skinned_velocities(pts, idx, w, at(0.0), (at(h) - at(-h)) / (2 * h), "cor",
                                 faces=faces, sign_reference=rule, device=device)
        np.testing.assert_allclose(got, want[rule], atol=2e-3 * np.abs(want[rule]).max(),
                                   err_msg=rule)


def test_velocities_of_per_frame_points_use_rest_centers(device):
    """With per-frame points (blend shapes), centers come from the rest points, as Skinner.skin
    and Scene.skin take them: the velocities are the derivatives of those positions."""
    pts, faces, idx, w, _ = random_cor_rig(16, V=150, T=300)
    rng = np.random.default_rng(17)
    at = motion(rng, 6)
    offset, rate = 0.6 * rng.normal(size=(2,) + pts.shape), rng.normal(size=(2,) + pts.shape)

    def points(t):
        return pts + offset + t * rate
    rest_centers = centers_reference(pts, faces, idx, w)
    h = 1e-5
    want = (cor_reference(points(h)[0], idx, w, at(h)[:1], rest_centers)[0]
            - cor_reference(points(-h)[0], idx, w, at(-h)[:1], rest_centers)[0]) / (2 * h)
    wrong_centers = centers_reference(points(0.0)[0], faces, idx, w)
    wrong = (cor_reference(points(h)[0], idx, w, at(h)[:1], wrong_centers)[0]
             - cor_reference(points(-h)[0], idx, w, at(-h)[:1], wrong_centers)[0]) / (2 * h)
    assert np.abs(wrong - want).max() > 10 * 2e-3 * np.abs(want).max()  # the centers matter
    got = skinned_velocities(points(0.0), idx, w, at(0.0), (at(h) - at(-h)) / (2 * h), "cor",
                             faces=faces, point_velocities=rate, rest_points=pts, device=device)
    np.testing.assert_allclose(got[0], want, atol=2e-3 * np.abs(want).max())
    # the positions they differentiate: Skinner.skin (as Scene.skin) of per-frame points
    sk = Skinner(pts, idx, w, faces=faces, device=device)
    np.testing.assert_allclose(sk.skin(at(0.0), "cor", points=points(0.0))[0],
                               cor_reference(points(0.0)[0], idx, w, at(0.0)[:1], rest_centers)[0],
                               atol=1e-4)
    with pytest.raises(ValueError, match="needs rest_points"):
        skinned_velocities(points(0.0), idx, w, at(0.0), at(0.0), "cor", faces=faces)


# ---------------------------------------------------------------------------------------------
# the procedural rigs


def side_rings(mesh, lo=1.0, hi=3.0):
    """Vertex masks of the side rings with ``lo <= x <= hi`` (both rigs run along +x)."""
    p = np.asarray(mesh.points, np.float64)
    r = np.linalg.norm(p[:, 1:], axis=1)
    side = np.abs(r - r.max()) < 1e-4
    xs = np.unique(np.round(p[side, 0], 5))
    return [side & (np.abs(p[:, 0] - x) < 1e-5) for x in xs[(xs >= lo) & (xs <= hi)]]


def ring_area(q):
    """Area of a closed ring of points (in order around), projected on its best-fit plane."""
    c = q - q.mean(0)
    basis = np.linalg.svd(c)[2][:2]
    u = c @ basis.T
    u = u[np.argsort(np.arctan2(u[:, 1], u[:, 0]))]
    return 0.5 * abs(np.sum(u[:, 0] * np.roll(u[:, 1], -1) - np.roll(u[:, 0], -1) * u[:, 1]))


def distance_to_bones(x, joint, forearm):
    """Distance from ``x`` to the bent skeleton: 0 ≤ s ≤ 2 on +x, and from ``joint`` along
    ``forearm`` for 2 units."""
    def seg(a, d):
        s = np.clip((x - a) @ d, 0, 2.0)
        return np.linalg.norm(x - a - s * d)
    return min(seg(np.zeros(3), np.array([1.0, 0, 0])), seg(joint, forearm))


def test_twist_180_keeps_sections():
    scene = dqskin.load(ASSETS / "twist_cylinder.usda")
    mesh = scene.meshes[0]
    t = scene.times[-1:]  # 180°
    rings = side_rings(mesh)
    rest = [ring_area(np.asarray(mesh.points, np.float64)[r]) for r in rings]
    ratio = {}
    for meth in ("lbs", "cor"):
        q = scene.skin(t, meth, space="skeleton").points[mesh.name][0].astype(np.float64)
        ratio[meth] = min(ring_area(q[r]) / a for r, a in zip(rings, rest))
    assert ratio["lbs"] < 0.05  # the candy wrapper ...
    assert ratio["cor"] >= 0.95  # ... is gone


def test_bend_neither_collapses_nor_swings_off_axis():
    scene = dqskin.load(ASSETS / "bending_arm.usda")
    mesh = scene.meshes[0]
    frames = scene.times[[18, 22, 27]]  # 90°, 110°, 135°
    xf = scene.skinning_transforms(frames)
    rings = side_rings(mesh)
    pts = np.asarray(mesh.points, np.float64)
    rest = [ring_area(pts[r]) for r in rings]
    res = {m: scene.skin(frames, m, space="skeleton").points[mesh.name].astype(np.float64)
           for m in ("lbs", "dqs", "cor")}
    for f in range(len(frames)):
        a = xf[f, 1].astype(np.float64)
        joint, forearm = a[:3, :3] @ [2.0, 0, 0] + a[:3, 3], a[:3, :3] @ [1.0, 0, 0]
        section, off = {}, {}
        for m, q in res.items():
            section[m] = min(ring_area(q[f, r]) / s for r, s in zip(rings, rest))
            off[m] = max(distance_to_bones(q[f, r].mean(0), joint, forearm) for r in rings)
        assert section["lbs"] < 0.75 and section["cor"] >= 0.95, section  # LBS collapses
        assert off["dqs"] > 1.3 * off["lbs"], off  # DQS swings its sections off the bones
        assert off["cor"] <= 1.1 * off["lbs"] + 1e-3, off  # CoR keeps them on


# ---------------------------------------------------------------------------------------------
# cache, errors, scene, CLI, compare


def test_cache_reused_and_invalidated(cache_dir):
    pts, faces, idx, w = chain_mesh(rings=11)
    first = cor.rotation_centers(pts, faces, idx, w)
    files = list((cache_dir / "cor").glob("*.npz"))
    assert len(files) == 1
    # a second run reads the file (planted values come back) ...
    planted = np.full_like(first, 7.0)
    np.savez(files[0], centers=planted)
    np.testing.assert_array_equal(cor.rotation_centers(pts, faces, idx, w), planted)
    # ... and anything that changes the centers is another key
    moved = pts + [0.0, 0.0, 1e-3]
    np.testing.assert_allclose(cor.rotation_centers(moved, faces, idx, w),
                               first + [0.0, 0.0, 1e-3], atol=1e-9)
    cor.rotation_centers(pts, faces[:-2], idx, w)
    cor.rotation_centers(pts, faces, idx, w, sigma=0.2)
    cor.rotation_centers(pts, faces, idx, w, subdivide=0.1)
    w2 = w.copy()
    w2[5] = w2[5][::-1]
    cor.rotation_centers(pts, faces, idx, w2)
    assert len(list((cache_dir / "cor").glob("*.npz"))) == 6
    # a corrupt, empty or truncated file is recomputed and replaced
    whole = files[0].read_bytes()
    for junk in (b"not a numpy file", b"", whole[:100], whole[:-30]):
        files[0].write_bytes(junk)
        np.testing.assert_array_equal(np.isnan(cor.rotation_centers(pts, faces, idx, w)),
                                      np.isnan(first))
    np.savez(files[0], centers=first.astype(np.float32))  # another dtype: recomputed too
    assert cor.rotation_centers(pts, faces, idx, w).dtype == np.float64
    assert not list((cache_dir / "cor").glob(".*"))  # no temporary file left


def test_errors():
    pts, faces, idx, w = chain_mesh(rings=5)
    xf = chain_pose(np.random.default_rng(0), frames=1)
    with pytest.raises(ValueError, match='"cor" needs faces'):
        dqskin.skin_points(pts, idx, w, xf, "cor")
    with pytest.raises(ValueError, match="faces: vertex index out of range"):
        Skinner(pts, idx, w, faces=faces + len(pts))
    with pytest.raises(ValueError, match=r"faces: expected \(T, 3\)"):
        Skinner(pts, idx, w, faces=faces[:, :2])
    with pytest.raises(ValueError, match="sigma"):
        cor.rotation_centers(pts, faces, idx, w, sigma=0.0)
    with pytest.raises(ValueError, match="subdivide"):
        cor.rotation_centers(pts, faces, idx, w, subdivide=-1)
    with pytest.raises(ValueError, match="cluster"):
        cor.rotation_centers(pts, faces, idx, w, cluster="fast")


def test_scene_cli_and_compare(tmp_path, monkeypatch):
    pts, faces, idx, w = chain_mesh(rings=16)
    path = tmp_path / "chain.usda"
    write_usd_rig(path, np.random.default_rng(6), J=4, frames=2, points=pts, faces=faces,
                  idx=idx.astype(np.int32), wts=w.astype(np.float32))
    xf = usdskel_transforms(path, [0, 1])
    want = cor_reference(pts, idx, w, xf, centers_reference(pts, faces, idx, w))
    scene = dqskin.load(path)
    np.testing.assert_allclose(scene.skin(method="cor").points["/Rig/Mesh"], want, atol=5e-5)
    out = tmp_path / "cor.npz"
    rc, text = run_cli("skin", path, "--out", out, "--method", "cor")
    assert rc == 0, text
    np.testing.assert_allclose(np.load(out)["points_0"], want, atol=5e-5)
    rules = []  # what compare asks the skinning path for
    from dqskin import pipeline
    real = pipeline.skin_scene  # (the scene calls it from there)
    monkeypatch.setattr(pipeline, "skin_scene", lambda scene, t, options, cache: (
        rules.append(options.sign_reference), real(scene, t, options, cache))[1])
    rc, text = run_cli("compare", path, "--out", tmp_path / "report", "--methods", "lbs,cor",
                       "--frames", "1", "--views", "front", "--width", "32", "--supersample",
                       "1", "--no-sweeps", "--quiet", "--sign-reference", "running_sum")
    assert rc == 0, text
    metrics = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert metrics["methods"] == ["lbs", "cor"]
    assert rules and set(rules) == {"running_sum"}


def test_cor_options_through_scene_and_cli(tmp_path, monkeypatch):
    """SkinOptions.cor and ``dqskin skin --cor-exact`` reach the centers, in this process and in
    a clip bake's workers: with every mesh above AUTO_TERMS the default clusters, the option
    gives the exact oracle's points."""
    pts, faces, idx, w = chain_mesh(rings=16)
    path = tmp_path / "chain.usda"
    write_usd_rig(path, np.random.default_rng(6), J=4, frames=2, points=pts, faces=faces,
                  idx=idx.astype(np.int32), wts=w.astype(np.float32))
    want = cor_reference(pts, idx, w, usdskel_transforms(path, [0, 1]),
                         centers_reference(pts, faces, idx, w))
    monkeypatch.setattr(cor, "AUTO_TERMS", 0)
    scene = dqskin.load(path)
    clustered = scene.skin(method="cor").points["/Rig/Mesh"]
    assert np.abs(clustered - want).max() > 2e-4  # (the default clusters here)
    exact = dqskin.SkinOptions(method="cor", cor=dqskin.CorOptions(cluster=None))
    np.testing.assert_allclose(scene.skin(options=exact).points["/Rig/Mesh"], want, atol=5e-5)
    np.testing.assert_allclose(scene.skin(method="cor", cor=CorOptions(cluster=None))
                               .points["/Rig/Mesh"], want, atol=5e-5)
    for flags, exact in (([], False), (["--cor-exact"], True)):
        out = tmp_path / f"cor{len(flags)}.npz"
        rc, text = run_cli("skin", path, "--out", out, "--method", "cor", *flags)
        assert rc == 0, text
        err = np.abs(np.load(out)["points_0"] - want).max()
        assert (err < 5e-5) if exact else (err > 2e-4), (flags, err)
    from pxr import Usd
    for flags, exact in (([], False), (["--cor-exact"], True)):  # clip layers (the workers' path)
        out = tmp_path / f"clips{len(flags)}.usda"
        rc, text = run_cli("skin", path, "--out", out, "--method", "cor", "--clips", *flags)
        assert rc == 0, text
        stage = Usd.Stage.Open(str(out))
        attr = stage.GetPrimAtPath("/Rig/Mesh").GetAttribute("points")
        got = np.stack([np.array(attr.Get(t)) for t in (0, 1)])
        err = np.abs(got - want).max()
        assert (err < 5e-5) if exact else (err > 2e-4), (flags, err)


def test_usd_bake_with_rigid_prims(shared_assets, tmp_path):
    """A USD cache baked with --method cor: meshes get COR, rigid prims (no triangles) DQS."""
    from pxr import Usd

    from dqskin.pipeline import rigid_transforms
    from dqskin.readers.usd import load_rigid_prims

    src = shared_assets / "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning/dqs.usda"
    scene = dqskin.load(src)
    for r in load_rigid_prims(scene):
        np.testing.assert_array_equal(
            rigid_transforms(scene, r, scene.times, dqskin.SkinOptions(method="cor")),
            rigid_transforms(scene, r, scene.times, dqskin.SkinOptions(method="dqs")))
    out = tmp_path / "cor.usda"
    rc, text = run_cli("skin", src, "--out", out, "--method", "cor", "--no-velocities")
    assert rc == 0, text
    stage = Usd.Stage.Open(str(out))
    m = next(m for m in scene.meshes if len(m.faces))
    t = scene.times[-1]
    got = np.array(stage.GetPrimAtPath(m.name).GetAttribute("points").Get(t))
    want = scene.skin([t], "cor").points[m.name][0]
    np.testing.assert_allclose(got, want, atol=1e-5)
