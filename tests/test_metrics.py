"""Artifact metrics against closed forms: a twisted capped cylinder skinned with LBS and DQS
(radius factor, volume ratio, section ratio), icosphere volume, closedness, scaled and moved
meshes for strain and distances."""

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

    # Candy wrapper: the members are the ramp's interior rings (both weights non-zero), one slice
    # per ring, so each slice ratio is that ring's radius factor.
    regions = M.dominant_pair_regions(idx, wts, [-1, 0], min_weight=1e-9)
    np.testing.assert_array_equal(regions, np.where((w > 0) & (w < 1), 1, -1))
    rest_seg = M.bone_segments(np.array([[0.0, 0, 0], [LENGTH / 2, 0, 0]]), [-1, 0])
    ring_w = np.unique(np.round(w[regions == 1], 12))
    sec = M.joint_sections(points, posed[None], rest_seg, rest_seg[None], regions,
                           slices=len(ring_w), device=device)
    expected_slices = (_lbs_radius_factor(ring_w, theta) if method == "lbs"
                       else np.ones_like(ring_w))
    np.testing.assert_allclose(sec.slice_ratio[0, 1], expected_slices, atol=1e-5)
    # Closed form of the minimum: √((1 + cos θ)/2) = |cos(θ/2)| at w = ½ (0.7071 at 90°, 0 at 180°).
    assert 0.5 in np.round(ring_w, 9)
    assert sec.min_section_ratio[0, 1] == pytest.approx(
        abs(np.cos(theta / 2)) if method == "lbs" else 1.0, abs=1e-5)
    assert np.isnan(sec.min_section_ratio[0, 0])  # the root has no members
    # LBS only shrinks rings, so the largest vertex ratio is the outermost member ring's factor.
    assert sec.max_bulge_ratio[0, 1] == pytest.approx(expected_slices.max(), abs=1e-5)
    # Slice centres, measured from the joint along the bone, sit on their rings.
    ring_x = np.unique(np.round(points[regions == 1, 0], 12)) - LENGTH / 2
    np.testing.assert_allclose(sec.slice_axial[1], ring_x, atol=0.5 * LENGTH / (RINGS - 1))


def test_section_bulge_closed_form():
    # Synthetic bulge: scale each rest ring about the axis by s(x) = 1 + 0.3·sin(π(x−a)/(b−a))
    # over the region [a, b]; slices and the vertex maximum must reproduce s.
    points, _ = _cylinder()
    a, b = 0.6, 1.4
    x = points[:, 0]
    regions = np.where((x >= a - 1e-9) & (x <= b + 1e-9) & (np.arange(len(x)) < RINGS * SEGMENTS),
                       0, -1)
    s = 1 + 0.3 * np.sin(np.pi * (x - a) / (b - a))
    posed = points.copy()
    posed[:, 1:] *= np.where(regions == 0, s, 1.0)[:, None]
    seg = np.array([[[0.0, 0, 0], [1.0, 0, 0]]])
    rings = np.unique(np.round(x[regions == 0], 9))
    sec = M.joint_sections(points, posed, seg, seg, regions, slices=len(rings), device="cpu")
    s_ring = 1 + 0.3 * np.sin(np.pi * (rings - a) / (b - a))
    np.testing.assert_allclose(sec.slice_ratio[0, 0], s_ring, atol=1e-6)
    assert sec.max_bulge_ratio[0, 0] == pytest.approx(1.3, abs=1e-6)
    assert sec.min_section_ratio[0, 0] == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(sec.vertex_ratio[0, regions == 0], s[regions == 0], atol=1e-6)
    assert np.all(np.isnan(sec.vertex_ratio[0, regions < 0]))
    # A degenerate posed axis makes the region undefined, not a number.
    bad = M.joint_sections(points, posed, seg, np.zeros((1, 2, 3)), regions, device="cpu")
    assert np.isnan(bad.min_section_ratio[0, 0]) and np.isnan(bad.max_bulge_ratio[0, 0])


def test_sections_follow_a_rigid_bend():
    # Rigid pieces (weights 0 | 1 with the step just past the joint), child bent 90° about z
    # through the joint. On each side the flesh keeps its distance to the bone carrying it.
    points, _ = _cylinder()
    joint = np.array([LENGTH / 2, 0.0, 0.0])
    on_ring = np.arange(len(points)) < RINGS * SEGMENTS
    w = (points[:, 0] > joint[0] + 1e-9).astype(float)
    bend = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1], point=joint)
    xforms = np.stack([np.eye(4), bend])
    posed = dqskin.skin_points(points, np.tile([0, 1], (len(points), 1)),
                               np.stack([1 - w, w], 1), xforms, "lbs", device="cpu")
    regions = np.where(on_ring & (np.abs(points[:, 0] - joint[0]) <= 0.3 + 1e-9), 1, -1)
    bind = np.array([[0.0, 0, 0], joint])
    rest_seg, parent_side, child_side = M.joint_axes(bind, [-1, 0], xforms)
    np.testing.assert_allclose(parent_side[1], rest_seg[1], atol=1e-12)
    np.testing.assert_allclose(child_side[1], [joint - [0, LENGTH / 2, 0], joint], atol=1e-12)
    rings = np.unique(np.round(points[regions == 1, 0], 9))
    sec = M.joint_sections(points, posed, rest_seg, parent_side, regions,
                           child_segments=child_side, slices=len(rings), device="cpu")
    np.testing.assert_allclose(sec.slice_ratio[0, 1], 1.0, atol=1e-5)
    assert sec.max_bulge_ratio[0, 1] == pytest.approx(1.0, abs=1e-5)
    # One straight axis instead: a child ring at axial distance a, turned 90° about z, lies at
    # √(a² + r² sin²φ) from the parent bone's line.
    single = M.joint_sections(points, posed, rest_seg, parent_side, regions, slices=len(rings),
                              device="cpu")
    phi = 2 * np.pi * np.arange(SEGMENTS) / SEGMENTS
    a = rings - joint[0]
    expected = np.where(a > 0, np.sqrt(a[:, None] ** 2 + (RADIUS * np.sin(phi)) ** 2).mean(1)
                        / RADIUS, 1.0)
    np.testing.assert_allclose(single.slice_ratio[0, 1], expected, rtol=1e-5)


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
    seg = M.bone_segments(pos, parents)
    np.testing.assert_array_equal(seg[2], [pos[1], pos[2]])
    np.testing.assert_array_equal(seg[0], [pos[0], pos[0]])
    assert M.bone_segments(np.stack([pos, pos]), parents).shape == (2, 4, 2, 3)
    idx = np.array([[1, 2, 0], [2, 1, 0], [0, 3, 1], [1, 0, 3], [2, 3, 0]])
    wts = np.array([[0.6, 0.4, 0], [0.9, 0.02, 0.08], [0.1, 0.5, 0.4], [0.5, 0.3, 0.2],
                    [0.5, 0.5, 0]])
    # rows: (1,2) pair → 2; 2-vs-1 too weak; (3,1) → 3; (1,0) → 1; (2,3) siblings → -1
    np.testing.assert_array_equal(M.dominant_pair_regions(idx, wts, parents), [2, -1, 3, 1, -1])
    with pytest.raises(ValueError, match="parents"):
        M.bone_segments(pos, [-1, 2, 0, 1])
    with pytest.raises(ValueError, match="faces"):
        M.volume(pos, np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="rest_points"):
        M.edge_strain(np.zeros((2, 4, 3)), np.zeros((3, 4, 3)), [[0, 1]])
    with pytest.raises(ValueError, match="regions"):
        M.joint_sections(pos, pos, seg, seg, np.zeros(3, int))
