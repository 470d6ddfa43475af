"""Offscreen renderer against closed-form geometry: silhouettes, Lambert shading, heat-map colours,
BVH refit, camera framing, and the image helpers."""

import matplotlib
import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.spatial import ConvexHull

from dqskin.report.render import (
    Camera,
    MeshRenderer,
    Shading,
    add_colorbar,
    colormap_lut,
    render,
    save_png,
    side_by_side,
)


def _sphere(radius=1.0, subdivisions=4, pole=None):
    """Icosphere; with ``pole`` the mesh is rotated so that vertex 0 points along ``pole``."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(s.vertices, dtype=np.float64)
    if pole is not None:
        a = v[0] / np.linalg.norm(v[0])
        b = np.asarray(pole, dtype=np.float64) / np.linalg.norm(pole)
        axis = np.cross(a, b)
        angle = np.arctan2(np.linalg.norm(axis), a @ b)
        r = trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]
        v = v @ r.T
    return v, np.asarray(s.faces)


def _max_edge_angle(v, f):
    e = trimesh.Trimesh(v, f, process=False).edges_unique
    a, b = v[e[:, 0]], v[e[:, 1]]
    cos = np.sum(a * b, axis=1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return float(np.arccos(np.clip(cos, -1, 1)).max())


def _ortho_front(height):
    """Orthographic camera on +Z looking at the origin; ``height`` world units tall."""
    return Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=None,
                  ortho_height=height)


def _coverage(img):
    return img[..., 3].astype(np.float64) / 255.0


def test_orthographic_silhouette_area(device):
    r, size, h = 1.0, 200, 2.5
    v, f = _sphere(r)
    img = render(v, f, _ortho_front(h), width=size, height=size, supersample=2,
                 transparent=True, device=device)
    area = _coverage(img).sum()
    px = size / h  # pixels per world unit
    # Exact polyhedron silhouette: convex hull of the projected vertices (independent oracle).
    hull = ConvexHull(v[:, :2]).volume * px ** 2
    assert area == pytest.approx(hull, rel=1e-3)
    # The inscribed polyhedron's silhouette falls short of the circle by about
    # 1 − cos²(δ/2) ≈ δ²/4 with δ ≈ 0.08 rad the largest edge angle at subdivision 4.
    delta = _max_edge_angle(v, f)
    assert area == pytest.approx(np.pi * r ** 2 * px ** 2, rel=delta ** 2 / 4 + 1e-3)
    # Centred: coverage-weighted centroid at the image centre.
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    w = _coverage(img)
    assert (xs * w).sum() / w.sum() == pytest.approx(size / 2, abs=0.05)
    assert (ys * w).sum() / w.sum() == pytest.approx(size / 2, abs=0.05)


def test_perspective_silhouette_area(device):
    r, dist, fov, size = 1.0, 4.0, 40.0, 160
    v, f = _sphere(r)
    cam = Camera(eye=(0.0, 0.0, dist), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=fov)
    img = render(v, f, cam, width=size, height=size, transparent=True, device=device)
    # The silhouette cone of a sphere has half-angle asin(r/d); on the image plane a circle of
    # radius tan(asin(r/d)) / tan(fov/2) half-heights.
    radius_px = np.tan(np.arcsin(r / dist)) / np.tan(np.radians(fov) / 2) * size / 2
    delta = _max_edge_angle(v, f)
    assert _coverage(img).sum() == pytest.approx(np.pi * radius_px ** 2, rel=delta ** 2 / 4 + 1e-3)


def test_lambert_at_centre_matches_closed_form(device):
    # Vertex 0 faces the camera, so the centre ray hits it and its (5-fold symmetric) vertex
    # normal is the view axis: n·v = 1 (no rim), n·l = l_z / |l| in camera axes.
    v, f = _sphere(1.0, pole=(0.0, 0.0, 1.0))
    shading = Shading()
    img = render(v, f, _ortho_front(2.5), width=101, height=101, supersample=1,
                 shading=shading, device=device)
    light = np.asarray(shading.light) / np.linalg.norm(shading.light)
    expected = np.asarray(shading.base_color) * (shading.ambient + shading.diffuse * light[2])
    np.testing.assert_allclose(img[50, 50], expected * 255, atol=1.0)


def test_lambert_and_rim_over_the_sphere(device):
    # Off-centre pixels against the ideal sphere normal at the ray's hit point. Interpolated
    # vertex normals of an inscribed icosphere point along the hit point of the flat triangle, so
    # they differ from the ideal normal by about sagitta / depth (tiny away from the silhouette).
    r, size, h = 1.0, 121, 2.5
    v, f = _sphere(r, subdivisions=5)
    shading = Shading()
    img = render(v, f, _ortho_front(h), width=size, height=size, supersample=1,
                 shading=shading, device=device).astype(np.float64)
    ys, xs = np.mgrid[0:size, 0:size]
    x = ((xs + 0.5) / size * 2 - 1) * h / 2
    y = (1 - (ys + 0.5) / size * 2) * h / 2
    inside = x ** 2 + y ** 2 < (0.8 * r) ** 2
    n = np.stack([x, y, np.sqrt(np.clip(r ** 2 - x ** 2 - y ** 2, 0, None))], -1) / r
    light = np.asarray(shading.light) / np.linalg.norm(shading.light)
    lambert = np.clip(n @ light, 0, None)
    rim = shading.rim * (1 - n[..., 2]) ** shading.rim_power
    expected = (np.asarray(shading.base_color) * (shading.ambient + shading.diffuse * lambert)[
        ..., None] + rim[..., None]) * 255
    err = np.abs(img - expected)[inside]
    assert err.max() <= 1.5  # 0.5 quantization + normal error
    # The key light comes from the upper left: that quadrant is brighter than the lower right.
    assert img[30, 30].mean() > img[90, 90].mean() + 40


def test_heatmap_colour_is_colormap_of_scalar(device):
    # scalars = y is linear, so barycentric interpolation reproduces it exactly on every triangle,
    # and an orthographic ray at screen height y hits a point with that y.
    r, size, h = 1.0, 101, 2.5
    v, f = _sphere(r)
    lo, hi = -1.0, 1.0
    img = render(v, f, _ortho_front(h), width=size, height=size, supersample=1,
                 scalars=v[:, 1], scalar_range=(lo, hi), colormap="viridis",
                 shading=Shading(lit=False), device=device).astype(np.float64)
    cmap = matplotlib.colormaps["viridis"]
    colours = cmap(np.linspace(0, 1, cmap.N))[:, :3]
    step = np.abs(np.diff(colours, axis=0)).max() * 255
    cols = np.arange(size)
    for row in (10, 30, 50, 70, 90):
        y = (1 - (row + 0.5) / size * 2) * h / 2
        half = np.sqrt(r ** 2 - y ** 2) * 0.9 * size / h
        sel = np.abs(cols + 0.5 - size / 2) < half
        t = (y - lo) / (hi - lo)
        # Linear interpolation between the map's N colours, in float64 ...
        smooth = np.array([np.interp(t * (cmap.N - 1), np.arange(cmap.N), colours[:, c])
                           for c in range(3)]) * 255
        np.testing.assert_allclose(img[row, sel], np.broadcast_to(smooth, (sel.sum(), 3)),
                                   atol=1.0)
        # ... and matplotlib's own lookup (nearest of N colours), within one colour step.
        nearest = np.asarray(cmap(t))[:3] * 255
        np.testing.assert_allclose(img[row, sel], np.broadcast_to(nearest, (sel.sum(), 3)),
                                   atol=step + 1)
    # Clamping: a range that ends below every value shows the top colour everywhere.
    top = render(v, f, _ortho_front(h), width=21, height=21, supersample=1, scalars=v[:, 1],
                 scalar_range=(-3.0, -2.0), shading=Shading(lit=False), device=device)
    np.testing.assert_allclose(top[10, 10], np.asarray(cmap(1.0))[:3] * 255, atol=1)
    nan = render(v, f, _ortho_front(h), width=21, height=21, supersample=1,
                 scalars=np.full(len(v), np.nan), shading=Shading(lit=False), device=device)
    np.testing.assert_allclose(nan[10, 10], np.asarray(Shading().nan_color) * 255, atol=1)


def test_refit_moves_silhouette(device):
    size, h, shift = 120, 4.0, np.array([0.5, -0.25, 0.0])
    v, f = _sphere(1.0)
    rend = MeshRenderer(v, f, device=device)
    mesh, mesh_id = rend.mesh, rend.mesh.id
    cam = _ortho_front(h)
    ys, xs = np.mgrid[0:size, 0:size] + 0.5

    def centroid(img):
        w = _coverage(img)
        return np.array([(xs * w).sum(), (ys * w).sum()]) / w.sum()

    before = centroid(rend.render(cam, width=size, height=size, transparent=True))
    rend.update(v + shift)
    moved = rend.render(cam, width=size, height=size, transparent=True)
    assert rend.mesh is mesh and rend.mesh.id == mesh_id  # refit, not rebuilt
    px = size / h
    np.testing.assert_allclose(centroid(moved) - before, [shift[0] * px, -shift[1] * px],
                               atol=0.05)
    fresh = render(v + shift, f, cam, width=size, height=size, transparent=True, device=device)
    assert np.abs(fresh.astype(int) - moved.astype(int)).max() <= 1


@pytest.mark.parametrize("view", ["front", "side", "three_quarter"])
@pytest.mark.parametrize("up_axis", ["Y", "Z"])
@pytest.mark.parametrize("fov", [30.0, None])
def test_frame_fits_bounds_tightly(view, up_axis, fov):
    box = trimesh.creation.box(extents=(0.6, 1.8, 0.3) if up_axis == "Y" else (0.6, 0.3, 1.8))
    v, f = np.asarray(box.vertices) + [0.2, 0.1, -0.3], np.asarray(box.faces)
    w, h, margin = 96, 64, 1.1
    cam = Camera.frame(v.min(0), v.max(0), view, up_axis=up_axis, fov=fov, aspect=w / h,
                       margin=margin)
    img = render(v, f, cam, width=w, height=h, supersample=2, transparent=True, device="cpu")
    rows, cols = np.nonzero(img[..., 3])
    assert rows.size and rows.min() > 0 and cols.min() > 0
    assert rows.max() < h - 1 and cols.max() < w - 1
    # Tight: in one direction the box reaches to 1/margin of the image (within two pixels).
    half_x = max(w / 2 - cols.min(), cols.max() + 1 - w / 2) / (w / 2)
    half_y = max(h / 2 - rows.min(), rows.max() + 1 - h / 2) / (h / 2)
    assert max(half_x, half_y) == pytest.approx(1 / margin, abs=2 / min(w, h) * 2)
    # The world up axis points up on screen.
    _, _, up = cam.basis()
    assert up[{"Y": 1, "Z": 2}[up_axis]] > 0


def test_frame_point_fills_image():
    center, radius, size = np.array([0.3, 1.2, -0.4]), 0.2, 80
    v, f = _sphere(radius, subdivisions=5)
    cam = Camera.frame_point(center, radius, "three_quarter", fov=35.0)
    img = render(v + center, f, cam, width=size, height=size, transparent=True, device="cpu")
    rows = np.nonzero(img[..., 3].max(axis=1))[0]
    # The sphere's silhouette cone just fits the vertical field of view.
    assert rows.min() <= 1 and rows.max() >= size - 2


def test_project_matches_pinhole_and_orthographic():
    w, h, d, fov = 160, 120, 4.0, 50.0
    cam = Camera(eye=(0.0, 0.0, d), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=fov)
    p = np.array([[0.0, 0.0, 0.0], [0.5, 0.25, 0.0], [0.5, 0.25, -1.0]])
    f = (h / 2) / np.tan(np.radians(fov) / 2)  # focal length in pixels
    depth = d - p[:, 2]
    expected = np.stack([w / 2 + f * p[:, 0] / depth, h / 2 - f * p[:, 1] / depth], 1)
    np.testing.assert_allclose(cam.project(p, w, h), expected, atol=1e-9)
    ortho = _ortho_front(3.0)
    np.testing.assert_allclose(ortho.project(p, w, h)[:, 0], w / 2 + p[:, 0] * h / 3.0)
    np.testing.assert_allclose(ortho.project(p, w, h)[:, 1], h / 2 - p[:, 1] * h / 3.0)


def test_render_frames_matches_single_renders():
    v, f = _sphere(1.0, subdivisions=2)
    frames = np.stack([v, v * 0.8 + [0.1, 0, 0], v + [0, 0.2, 0]])
    cam = _ortho_front(3.0)
    rend = MeshRenderer(v, f, device="cpu")
    out = rend.render_frames(frames, cam, width=40, height=30, scalars=frames[..., 1],
                             scalar_range=(-1, 1))
    assert out.shape == (3, 30, 40, 3) and out.dtype == np.uint8
    for i in range(3):
        single = render(frames[i], f, cam, width=40, height=30, scalars=frames[i, :, 1],
                        scalar_range=(-1, 1), device="cpu")
        np.testing.assert_array_equal(out[i], single)


def test_invalid_meshes_raise():
    v, f = _sphere(1.0, subdivisions=1)
    with pytest.raises(ValueError, match="no faces"):
        MeshRenderer(v, np.zeros((0, 3), int), device="cpu")
    with pytest.raises(ValueError, match="no points"):
        MeshRenderer(np.zeros((0, 3)), f, device="cpu")
    with pytest.raises(ValueError, match="out of range"):
        MeshRenderer(v, f + 1000, device="cpu")
    with pytest.raises(ValueError, match=r"\(T, 3\)"):
        MeshRenderer(v, f[:, :2], device="cpu")
    rend = MeshRenderer(v, f, device="cpu")
    with pytest.raises(ValueError, match="points"):
        rend.update(v[:-1])
    with pytest.raises(ValueError, match="scalars"):
        rend.render(_ortho_front(3), width=8, height=8, scalars=np.zeros(3))
    with pytest.raises(ValueError, match="colormap"):
        rend.render(_ortho_front(3), width=8, height=8, scalars=v[:, 0], colormap="nope")
    with pytest.raises(ValueError, match="ortho_height"):
        Camera(eye=(0, 0, 1), target=(0, 0, 0), fov=None)
    with pytest.raises(ValueError, match="view"):
        Camera.frame(v.min(0), v.max(0), "top")


def test_colorbar_panel_and_png(tmp_path):
    img = np.full((120, 80, 3), 200, np.uint8)
    out = add_colorbar(img, (0.0, 2.0), "magma", label="ratio")
    assert out.shape[0] == 120 and out.shape[1] > 80 and out.dtype == np.uint8
    np.testing.assert_array_equal(out[:, :80], img)
    lut = colormap_lut("magma") * 255
    panel = out[:, 80:].astype(np.float64)
    # The bar's top row is the colour map's top, the bottom row its bottom.
    def has(colour):
        return np.any(np.all(np.abs(panel - colour) <= 1.5, axis=-1))
    assert has(lut[-1]) and has(lut[0])

    rgba = np.zeros((50, 40, 4), np.uint8)
    composed = side_by_side([img, rgba], ["LBS", "DQS"], pad=4)
    assert composed.shape[2] == 3 and composed.shape[1] == 4 + 80 + 4 + 40 + 4
    assert composed.shape[0] > 120 + 8  # label row above the images

    path = save_png(tmp_path / "panel.png", composed)
    np.testing.assert_array_equal(np.asarray(Image.open(path)), composed)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["panel.png"]  # no temporary left
    with pytest.raises(ValueError, match="uint8"):
        save_png(tmp_path / "bad.png", composed.astype(np.float32))
