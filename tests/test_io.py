"""Plain-mesh input through trimesh, and atomic outputs."""

import numpy as np
import pytest
import trimesh

from dqskin.formats import atomic_path, load_mesh


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".off"])
def test_load_mesh_reads_geometry(tmp_path, suffix):
    box = trimesh.creation.box(extents=(1, 2, 3))
    path = tmp_path / f"box{suffix}"
    box.export(path)
    points, faces = load_mesh(path)
    assert points.dtype == np.float32 and faces.dtype == np.int32
    # the same surface: equal volume and bounds (STL re-indexes vertices)
    mesh = trimesh.Trimesh(points, faces)
    np.testing.assert_allclose(mesh.volume, 6.0, rtol=1e-6)
    np.testing.assert_allclose(points.min(0), [-0.5, -1, -1.5], atol=1e-6)


def test_load_mesh_errors(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)


def test_atomic_path_keeps_old_file_on_error(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with atomic_path(tmp_path / "sub" / "new.txt") as tmp:
        tmp.write_text("new")
    assert (tmp_path / "sub" / "new.txt").read_text() == "new"
