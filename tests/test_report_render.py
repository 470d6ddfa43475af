"""The report renderer's adaptive anti-aliasing and two-layer rendering, against closed-form
geometry and full super-sampling: the silhouette area of a sphere, edge pixels resampled exactly
as full super-sampling would, interior pixels one centre sample, and a second layer identical to
a separate render of the same pose."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from dqskin.report.render import Camera, MeshRenderer, Shading


def _scene():
    """A sphere in front of a box (occlusion edges, silhouettes, a crease-free interior)."""
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    b = trimesh.creation.box(extents=(4.0, 3.0, 0.5))
    b.apply_translation((0.5, 0.0, -2.0))
    v = np.concatenate([s.vertices, b.vertices])
    f = np.concatenate([s.faces, b.faces + len(s.vertices)])
    return np.asarray(v, dtype=np.float64), np.asarray(f), len(s.vertices)


def _ortho(height):
    return Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=None,
                  ortho_height=height)


def test_adaptive_matches_full_supersampling(device):
    v, f, _ = _scene()
    r = MeshRenderer(v, f, device=device)
    cam = Camera.frame(v.min(0), v.max(0), "three_quarter")
    kw = dict(width=160, height=120, supersample=3)
    full = r.render(cam, **kw).astype(np.float64)
    adaptive = r.render(cam, adaptive=True, **kw).astype(np.float64)
    once = r.render(cam, width=160, height=120, supersample=1).astype(np.float64)
    diff = np.abs(full - adaptive).max(axis=2)
    # Edges are resampled on the same sub-pixel grid (identical pixels); elsewhere the centre
    # sample of smoothly shaded surface differs from the 3×3 mean by a shading gradient only.
    assert diff.mean() < 0.1 and (diff > 12).mean() < 0.001
    assert (diff == 0).mean() > 0.95  # background, edges and most of the interior: bit for bit
    # ... while plain one-ray-per-pixel rendering is visibly aliased at the edges.
    aliased = np.abs(full - once).max(axis=2)
    assert aliased.mean() > 0.3 and (aliased > 12).mean() > 0.005


def test_adaptive_silhouette_area(device):
    # Transparent coverage: a sphere's silhouette area in pixels, against the convex hull of its
    # projected vertices (as tests/test_render.py does for full super-sampling).
    s = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    size, h = 200, 2.5
    img = MeshRenderer(v, f, device=device).render(_ortho(h), width=size, height=size,
                                                   supersample=4, transparent=True,
                                                   adaptive=True)
    area = img[..., 3].astype(np.float64).sum() / 255
    hull = ConvexHull(v[:, :2]).volume * (size / h) ** 2
    assert area == pytest.approx(hull, rel=2e-3)


@pytest.mark.parametrize("adaptive", [False, True])
def test_second_layer_is_a_separate_render(adaptive, device):
    v, f, sphere = _scene()
    r = MeshRenderer(v, f, device=device)
    cam = Camera.frame(v.min(0), v.max(0), "front")
    heat = {"scalars": v[:, 1], "scalar_range": (-1.5, 1.5), "colormap": "magma",
            "shading": Shading(ambient=0.6, diffuse=0.4, rim=0.0)}
    kw = dict(width=90, height=70, supersample=2, adaptive=adaptive)
    plain, layered = r.render(cam, second_layer=heat, **kw)
    np.testing.assert_array_equal(plain, r.render(cam, **kw))
    alone = r.render(cam, **heat, **kw)
    if adaptive:  # edges come from the first layer's normals: identical where both agree
        assert (np.abs(layered.astype(int) - alone).max(axis=2) > 2).mean() < 0.01
    else:
        np.testing.assert_array_equal(layered, alone)
    with pytest.raises(ValueError, match="second_layer"):
        r.render(cam, second_layer={"scalar": v[:, 1]}, **kw)
    with pytest.raises(ValueError, match="second_layer: scalars"):
        r.render(cam, second_layer={"scalars": v[:sphere, 1]}, **kw)
