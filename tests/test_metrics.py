"""Artifact metrics against closed forms: a twisted and a bent capped cylinder skinned with LBS
and DQS (radius factor, volume ratio, ring section ratio k and √k), a synthetic bulge, the
bend/twist split, icosphere volume, closedness, scaled and moved meshes for strain and
distances."""

import numpy as np
import pytest
import trimesh

import dqskin
from dqskin import metrics as M

RADIUS, LENGTH, RINGS, SEGMENTS = 0.25, 2.0, 201, 64
FRACTION = 0.5  # share of the cylinder's length covered by the weight ramp


def _cylinder():
    """Closed capped cylinder along +x, outward winding: RINGS rings of SEGMENTS vertices, then
    the two cap centres."""
    x = np.linspace(0.0, LENGTH, RINGS)
    phi = 2 * np.pi * np.arange(SEGMENTS) / SEGMENTS
    ring = np.stack([np.zeros(SEGMENTS), RADIUS * np.cos(phi), RADIUS * np.sin(phi)], 1)
    points = np.concatenate([ring + [xi, 0, 0] for xi in x] + [[[0, 0, 0], [LENGTH, 0, 0]]])
    faces = []
    for j in range(RINGS - 1):
        for i in range(SEGMENTS):
            a, b = j * SEGMENTS + i, j * SEGMENTS + (i + 1) % SEGMENTS
            faces += [[a, b, b + SEGMENTS], [a, b + SEGMENTS, a + SEGMENTS]]
    c0, last = RINGS * SEGMENTS, (RINGS - 1) * SEGMENTS
    for i in range(SEGMENTS):
        faces += [[c0, (i + 1) % SEGMENTS, i], [c0 + 1, last + i, last + (i + 1) % SEGMENTS]]
    return points, np.array(faces)


def _twist_setup(theta):
    """Two joints on the x axis (root at 0, child at L/2), weights (1 − w, w) with w a linear ramp
    over FRACTION·L centred on the child; the child twists by θ about the bone (x) axis."""
    points, faces = _cylinder()
    start = LENGTH / 2 - FRACTION * LENGTH / 2
    w = np.clip((points[:, 0] - start) / (FRACTION * LENGTH), 0.0, 1.0)
    indices = np.tile([0, 1], (len(points), 1))
    weights = np.stack([1 - w, w], 1)
    twist = np.eye(4)
    c, s = np.cos(theta), np.sin(theta)
    twist[1:3, 1:3] = [[c, -s], [s, c]]  # rotation about x through the child joint (on x)
    xforms = np.stack([np.eye(4), twist])
    return points, faces, indices, weights, w, xforms


def _lbs_radius_factor(w, theta):
    """|(1 − w) + w·e^{iθ}|: LBS scales a ring of weight w about the twist axis by this."""
    return np.sqrt(1 - 2 * w * (1 - w) * (1 - np.cos(theta)))


def _twist_angle(w, theta, method):
    """Angle by which the ring of weight w turns: the argument of the blended rotation."""
    if method == "lbs":
        return np.arctan2(w * np.sin(theta), 1 - w + w * np.cos(theta))
    return 2 * np.arctan2(w * np.sin(theta / 2), 1 - w + w * np.cos(theta / 2))


def _max_ring_turn(theta, method):
    """Largest angle between consecutive rings of the ramp, max|dφ/dw|·Δw (Δw = ring spacing)."""
    w = np.linspace(0, 1, 20001)
    dw = (LENGTH / (RINGS - 1)) / (FRACTION * LENGTH)
    return np.abs(np.gradient(np.unwrap(_twist_angle(w, theta, method)), w)).max() * dw, dw


THETAS = [np.pi / 2, np.pi]


@pytest.mark.parametrize("theta", THETAS, ids=["90deg", "180deg"])
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_twisted_cylinder(method, theta, device):
    points, faces, idx, wts, w, xforms = _twist_setup(theta)
    posed = dqskin.skin_points(points, idx, wts, xforms, method, device=device).astype(np.float64)
    on_ring = np.arange(len(points)) < RINGS * SEGMENTS

    # Radius of each ring about the twist axis: LBS shrinks it by √(1 − 2w(1−w)(1−cos θ)),
    # DQS keeps it.
    factor = _lbs_radius_factor(w, theta) if method == "lbs" else np.ones_like(w)
    radius = np.linalg.norm(posed[:, 1:], axis=1)
    np.testing.assert_allclose(radius[on_ring], RADIUS * factor[on_ring], atol=1e-6)
    np.testing.assert_allclose(posed[:, 0], points[:, 0], atol=1e-6)

    # Volume ratio. Continuum: mean of factor² over the length, 1 − f(1 − cos θ)/3 for LBS, 1 for
    # DQS. Discretization (exact for each ring, whose polygon area scales by factor²): the
    # triangulated band between rings turned by Δφ loses ~Δφ²/2 of its volume (prismatoid
    # mid-section), and integrating factor² ring by ring costs ≤ Δw²·max|d²(factor²)/dw²|/12.
    turn, dw = _max_ring_turn(theta, method)
    closed = 1 - FRACTION * (1 - np.cos(theta)) / 3 if method == "lbs" else 1.0
    tol = FRACTION * (turn ** 2 + (1 - np.cos(theta)) * dw ** 2) + 1e-5
    ratio, reason = M.volume_ratio(posed, points, faces, device=device)
    assert reason is None
    assert ratio == pytest.approx(closed, abs=tol)
    # The same polyhedra measured independently (trimesh mass properties, float64).
    exact = (trimesh.Trimesh(posed, faces, process=False).volume
             / trimesh.Trimesh(points, faces, process=False).volume)
    assert ratio == pytest.approx(exact, rel=2e-6)

    # Candy wrapper: the ring of weight share w is a circle shrunk by k(w) under LBS (both axes
    # of its section), kept by DQS. One ring of the mesh per ring width (0.01 here).
    rings, share = M.joint_rings(idx, wts, [-1, 0], ring_width=0.01, min_weight=1e-9)
    members = (w > 0) & (w < 1)
    np.testing.assert_array_equal(rings >= 0, members)
    np.testing.assert_allclose(share[rings[members] - len(share)], w[members], atol=1e-9)
    sec = M.ring_sections(points, posed, rings, 2 * len(share))
    inner = share[(share > 0) & (share < 1)]
    expected = _lbs_radius_factor(inner, theta) if method == "lbs" else np.ones_like(inner)
    got = sec.section_ratio[0, len(share):][(share > 0) & (share < 1)]
    np.testing.assert_allclose(got, expected, atol=2e-5)
    assert np.all(np.isnan(sec.section_ratio[0, :len(share)]))  # the root has no members
    # Closed form of the minimum: |cos(θ/2)| at w = ½ (0.7071 at 90°, 0 at 180°).
    assert np.nanmin(got) == pytest.approx(
        abs(np.cos(theta / 2)) if method == "lbs" else 1.0, abs=2e-5)
    # LBS only shrinks rings about their centre: every vertex ratio is its ring's factor.
    np.testing.assert_allclose(sec.vertex_ratio[0, members],
                               expected[np.searchsorted(inner, w[members] - 1e-9)], atol=2e-5)
    assert np.nanmax(sec.bulge_ratio) <= 1 + 2e-5


def _lbs_bend_oracle(points, w, rotation, pivot):
    """Float64 LBS of a two-joint bend from its equation: (1 − w)p + w(R(p − c) + c)."""
    return (1 - w)[:, None] * points + w[:, None] * ((points - pivot) @ rotation.T + pivot)


@pytest.mark.parametrize("degrees", [45, 90, 150])
def test_ring_sections_in_a_bend(degrees):
    # Bend about z through the joint. A circular ring of share w: LBS shrinks its section along the
    # bend plane by k = √(1 − 2w(1−w)(1 − cos θ)) and keeps it along z: section ratio √k; DQS
    # turns each ring rigidly: 1 — at any angle, which is what slicing along a bone could not give.
    theta = np.radians(degrees)
    points, faces, idx, wts, w, _ = _twist_setup(theta)
    joint = np.array([LENGTH / 2, 0.0, 0.0])
    bend = trimesh.transformations.rotation_matrix(theta, [0, 0, 1], point=joint)
    xforms = np.stack([np.eye(4), bend])
    rings, share = M.joint_rings(idx, wts, [-1, 0], ring_width=0.01, min_weight=1e-9)
    inner = (share > 0) & (share < 1)
    k = _lbs_radius_factor(share[inner], theta)
    lbs = _lbs_bend_oracle(points, w, bend[:3, :3], joint)
    for method, expected in (("lbs", np.sqrt(k)), ("dqs", np.ones_like(k))):
        posed = dqskin.skin_points(points, idx, wts, xforms, method, device="cpu")
        if method == "lbs":
            np.testing.assert_allclose(posed, lbs, atol=1e-5)
        sec = M.ring_sections(points, posed, rings, 2 * len(share))
        np.testing.assert_allclose(sec.section_ratio[0, len(share):][inner], expected, atol=2e-5)
        # Bulge: LBS keeps the ring's extent along z (ratio 1 there) and shrinks it elsewhere.
        assert np.nanmax(sec.bulge_ratio) == pytest.approx(1.0, abs=2e-5)
    bend_deg, twist_deg = M.joint_bend_twist(xforms, np.array([[0.0, 0, 0], joint]), [-1, 0])
    assert np.isnan(bend_deg[0]) and bend_deg[1] == pytest.approx(degrees, abs=1e-6)
    assert twist_deg[1] == pytest.approx(0.0, abs=1e-6)


def test_ring_bulge_closed_form():
    # Synthetic bulge: scale one ring about its centre by 1.3 along y only; the section ratio is
    # √1.3 (one axis of the ellipse), the bulge 1.3 (the vertices on the y axis), rigid motions of
    # the whole set change nothing.
    points, _ = _cylinder()
    on = np.arange(len(points)) < SEGMENTS
    rings = np.where(on, 0, -1)
    posed = points.copy()
    posed[on, 1] *= 1.3
    rot = trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3))
    moved = posed @ rot[:3, :3].T + [4.0, -2.0, 1.0]
    for p in (posed, moved):
        sec = M.ring_sections(points, np.stack([points, p]), rings, 1)
        np.testing.assert_allclose(sec.section_ratio[:, 0], [1.0, np.sqrt(1.3)], atol=1e-6)
        np.testing.assert_allclose(sec.bulge_ratio[:, 0], [1.0, 1.3], atol=1e-6)
        phi = 2 * np.pi * np.arange(SEGMENTS) / SEGMENTS
        np.testing.assert_allclose(sec.vertex_ratio[1, on],
                                   np.hypot(1.3 * np.cos(phi), np.sin(phi)), atol=1e-6)
        assert np.all(np.isnan(sec.vertex_ratio[:, ~on]))
    # Too few vertices or a degenerate (collinear) rest ring: undefined, not a number.
    few = M.ring_sections(points, points, np.where(np.arange(len(points)) < 3, 0, -1), 1)
    assert np.isnan(few.section_ratio[0, 0]) and np.isnan(few.bulge_ratio[0, 0])
    line = np.zeros((6, 3))
    line[:, 0] = np.arange(6)
    assert np.isnan(M.ring_sections(line, line, np.zeros(6, int), 1).section_ratio[0, 0])


def test_bend_twist_split():
    # Joint 2 turned by R = swing · twist about its bone (+y, toward joint 3): angles recovered
    # independently of how the parent chain moves.
    pos = np.array([[0.0, 0, 0], [0, 1, 0], [0, 2, 0], [0, 3, 0]])
    parents = [-1, 0, 1, 2]
    tw = trimesh.transformations.rotation_matrix(np.radians(70), [0, 1, 0], point=pos[2])
    sw = trimesh.transformations.rotation_matrix(np.radians(40), [1, 0, 1], point=pos[2])
    carry = trimesh.transformations.rotation_matrix(1.1, [0.3, -0.2, 0.9], point=[1, 2, 3])
    x = np.stack([carry, carry, carry @ sw @ tw, carry @ sw @ tw])
    bend, twist = M.joint_bend_twist(np.stack([x, np.tile(np.eye(4), (4, 1, 1))]), pos, parents)
    np.testing.assert_allclose(bend[0, 1:], [0, 40, 0], atol=1e-6)
    np.testing.assert_allclose(twist[0, 1:], [0, 70, 0], atol=1e-6)
    np.testing.assert_allclose(bend[1, 1:], 0, atol=1e-6)
    np.testing.assert_allclose(M.bone_directions(pos, parents), np.tile([0, 1.0, 0], (4, 1)))


def test_icosphere_volume(device):
    r = 1.3
    s = trimesh.creation.icosphere(subdivisions=4, radius=r)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    vol = M.volume(v, f, device=device)
    assert vol == pytest.approx(s.volume, rel=1e-5)  # exact polyhedron, trimesh mass properties
    # Inscribed polyhedron: contains the ball touching its nearest face plane, inside the sphere.
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inner = np.min(np.abs(np.sum(n * v[f[:, 0]], 1)) / np.linalg.norm(n, axis=1))
    assert 4 / 3 * np.pi * inner ** 3 < vol < 4 / 3 * np.pi * r ** 3
    # Translation-invariant, sign follows the winding, frames batch.
    moved = M.volume(np.stack([v + [5.0, -3.0, 2.0], 0.5 * v]), f, device=device)
    np.testing.assert_allclose(moved, [s.volume, s.volume / 8], rtol=1e-5)
    assert M.volume(v, f[:, ::-1], device=device) == pytest.approx(-s.volume, rel=1e-5)


def test_closedness_and_reasons():
    s = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    ratio, reason = M.volume_ratio(v * 1.1, v, f)
    assert reason is None and ratio == pytest.approx(1.1 ** 3, rel=1e-5)
    ratio, reason = M.volume_ratio(v, v, f[1:])
    assert ratio is None and "open" in reason and "3 boundary edges" in reason
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]
    assert "winding" in M.volume_ratio(v, v, flipped)[1]
    assert "non-manifold" in M.volume_ratio(v, v, np.concatenate([f, f[:1], f[:1, ::-1]]))[1]
    # A seam: faces touching vertex 0 use a duplicate of it. Closed once welded at bit-identical
    # rest positions, open when the duplicate is moved off vertex 0.
    dup = np.concatenate([v, v[:1]])
    seam = f.copy()
    touch = np.flatnonzero(np.any(f == 0, axis=1))[:2]
    seam[touch] = np.where(seam[touch] == 0, len(v), seam[touch])
    assert M.volume_ratio(dup, dup, seam) == (pytest.approx(1.0), None)
    apart = np.concatenate([v, v[:1] * (1 + 1e-6)])
    assert "open" in M.volume_ratio(apart, apart, seam)[1]
    flat = v * [1.0, 1.0, 1e-12]  # closed, but no volume
    assert M.volume_ratio(flat, flat, f)[1].startswith("rest volume")


def test_edge_strain_and_distance(device):
    s = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    scale = np.array([1.5, 0.8, 1.0])
    posed = v * scale
    edges = M.mesh_edges(f)
    assert len(edges) == len(s.edges_unique) and np.all(edges[:, 0] < edges[:, 1])
    d0 = v[edges[:, 0]] - v[edges[:, 1]]
    expected = np.linalg.norm(d0 * scale, axis=1) / np.linalg.norm(d0, axis=1) - 1
    np.testing.assert_allclose(M.edge_strain(posed, v, edges, device=device), expected, atol=1e-5)
    uniform = M.edge_strain(np.stack([v * 1.2, v]), v, edges, device=device)
    np.testing.assert_allclose(uniform, np.stack([np.full(len(edges), 0.2),
                                                  np.zeros(len(edges))]), atol=1e-5)

    t = np.array([0.3, -0.4, 1.2])
    dist = M.vertex_distance(np.stack([v + t, v]), v, device=device)
    np.testing.assert_allclose(dist, np.stack([np.full(len(v), np.linalg.norm(t)),
                                               np.zeros(len(v))]), atol=1e-5)


def test_helpers_and_validation():
    parents = [-1, 0, 1, 1]
    pos = np.array([[0.0, 0, 0], [0, 1, 0], [0, 2, 0], [1, 1, 0]])
    idx = np.array([[1, 2, 0], [2, 1, 0], [0, 3, 1], [1, 0, 3], [2, 3, 0]])
    wts = np.array([[0.6, 0.4, 0], [0.9, 0.02, 0.08], [0.1, 0.5, 0.4], [0.5, 0.3, 0.2],
                    [0.5, 0.5, 0]])
    # rows: (1,2) pair → 2; 2-vs-1 too weak; (3,1) → 3; (1,0) → 1 but holds only 0.8 of the
    # weight (below the default 0.9); (2,3) siblings → -1
    regions, share = M.dominant_pair_regions(idx, wts, parents)
    np.testing.assert_array_equal(regions, [2, -1, 3, -1, -1])
    regions, share = M.dominant_pair_regions(idx, wts, parents, min_pair=0.8)
    np.testing.assert_array_equal(regions, [2, -1, 3, 1, -1])
    np.testing.assert_allclose(share, [0.4, np.nan, 0.5 / 0.9, 0.5 / 0.8, np.nan])
    rings, centres = M.joint_rings(idx, wts, parents, ring_width=0.25, min_pair=0.8)
    np.testing.assert_array_equal(centres, [0, 0.25, 0.5, 0.75, 1])
    np.testing.assert_array_equal(rings, [2 * 5 + 2, -1, 3 * 5 + 2, 1 * 5 + 3, -1])
    with pytest.raises(ValueError, match="parents"):
        M.joint_bend_twist(np.tile(np.eye(4), (4, 1, 1)), pos, [-1, 2, 0, 1])
    with pytest.raises(ValueError, match="ring_width"):
        M.joint_rings(idx, wts, parents, ring_width=0)
    with pytest.raises(ValueError, match="faces"):
        M.volume(pos, np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="rest_points"):
        M.edge_strain(np.zeros((2, 4, 3)), np.zeros((3, 4, 3)), [[0, 1]])
    with pytest.raises(ValueError, match="rings"):
        M.ring_sections(pos, pos, np.zeros(3, int), 1)
    with pytest.raises(ValueError, match="rings"):
        M.ring_sections(pos, pos, np.full(4, 2), 1)
