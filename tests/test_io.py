"""Plain-mesh input through trimesh, and atomic outputs."""

import numpy as np
import pytest
import trimesh

from dqskin.files.atomic import atomic_path
from dqskin.readers.mesh import load_mesh


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


def test_atomic_path_leaves_the_file_to_its_writer(tmp_path):
    """The temporary file does not exist until the writer creates it, in a private folder beside
    the target. USD's Export saves through its own temporary file and a rename; renamed onto an
    existing (empty) file, ext4 writes the whole new file to disk before the rename returns. Its
    own temporary files land in the private folder, which commit and discard remove."""
    from pxr import Sdf
    claim = atomic_path(tmp_path / "out.usdc")
    tmp = claim.open()
    assert not tmp.exists() and tmp.name == "out.usdc" and tmp.parent.parent == tmp_path
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    Sdf.CreatePrimInLayer(layer, "/a")
    assert layer.Export(str(tmp))
    assert claim.commit() == tmp_path / "out.usdc"
    assert [p.name for p in tmp_path.iterdir()] == ["out.usdc"]
    assert Sdf.Layer.OpenAsAnonymous(str(tmp_path / "out.usdc")).GetPrimAtPath("/a")
    claim = atomic_path(tmp_path / "b.usdc")
    tmp = claim.open()
    tmp.write_text("half")
    (tmp.parent / ".b.usdc.tmp123").write_text("a writer's own temporary file")
    claim.discard()
    assert [p.name for p in tmp_path.iterdir()] == ["out.usdc"]
    with pytest.raises(OSError, match=r"c.usdc: cannot write \(the writer created no file\)"):
        with atomic_path(tmp_path / "c.usdc"):
            pass
    assert [p.name for p in tmp_path.iterdir()] == ["out.usdc"]


def test_atomic_path_exclusive_claim(tmp_path):
    """overwrite=False: of two writers of one new file, the one committing second fails and
    leaves the first one's file; its temporary file is removed."""
    target = tmp_path / "out.txt"
    first, second = atomic_path(target, overwrite=False), atomic_path(target, overwrite=False)
    first.open().write_text("first")
    second.open().write_text("second")
    first.commit()
    with pytest.raises(FileExistsError, match="out.txt: exists"):
        second.commit()
    assert target.read_text() == "first"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with atomic_path(target) as tmp:  # overwrite=True (default): the last writer wins
        tmp.write_text("third")
    assert target.read_text() == "third"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_atomic_group_is_all_or_nothing(tmp_path):
    from dqskin.files.atomic import atomic_group
    (tmp_path / "b.txt").write_text("other run")
    group = atomic_group(overwrite=False)
    for name in ("a.txt", "b.txt", "c.txt"):
        group.add(tmp_path / name).write_text(name)
    with pytest.raises(FileExistsError, match="b.txt"):
        group.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]  # a.txt taken back
    assert (tmp_path / "b.txt").read_text() == "other run"
    with pytest.raises(RuntimeError):
        with atomic_group() as group:
            group.add(tmp_path / "d.txt").write_text("d")
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]


def test_atomic_folder_appears_whole(tmp_path):
    """A folder is renamed into place complete: an error leaves nothing; exclusive, it fails if
    another run put a folder there meanwhile (an empty folder is replaced); with overwrite the
    earlier folder is replaced whole (nothing of it stays) and only on commit."""
    import os

    from dqskin.files.atomic import atomic_folder
    out = tmp_path / "report"
    with pytest.raises(RuntimeError):
        with atomic_folder(out) as folder:
            (folder.tmp / "a.txt").write_text("a")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    out.mkdir()  # empty: claimed
    with atomic_folder(out) as folder:
        (folder.tmp / "a.txt").write_text("first")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]
    assert oct(out.stat().st_mode & 0o777) == oct(0o777 & ~_umask())
    folder = atomic_folder(out)
    (folder.open() / "b.txt").write_text("second")
    with pytest.raises(FileExistsError, match="report: exists"):
        folder.commit()
    assert (out / "a.txt").read_text() == "first" and [p.name for p in tmp_path.iterdir()] == [
        "report"]
    folder = atomic_folder(out, overwrite=True)
    (folder.open() / "b.txt").write_text("second")
    assert (out / "a.txt").read_text() == "first"  # not before commit
    folder.commit()
    assert sorted(p.name for p in out.iterdir()) == ["b.txt"]
    assert sorted(os.listdir(tmp_path)) == ["report"]


def _umask():
    import os
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_atomic_errors_name_the_target(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(NotADirectoryError, match="file is not a directory"):
        with atomic_path(blocker / "sub" / "out.txt"):
            pass
    long_name = tmp_path / ("n" * 250)  # legal; its temporary folder is 10 characters longer
    with pytest.raises(OSError) as info:
        with atomic_path(long_name):
            pass
    assert str(info.value).startswith(f"{long_name}: cannot write")
    target = tmp_path / "out.bin"
    with pytest.raises(OSError) as info:
        with atomic_path(target) as tmp:
            raise OSError(28, "No space left on device", str(tmp))
    assert str(info.value) == f"{target}: cannot write (No space left on device)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_interrupt_waits_for_the_critical_step(tmp_path):
    """An interrupt during a commit is raised after it; then nothing commits any more."""
    from dqskin.files import atomic

    class Stop(KeyboardInterrupt):
        pass

    try:
        with pytest.raises(Stop):
            with atomic.critical():
                atomic.interrupt(Stop())  # as a signal handler would, mid-step
                (tmp_path / "a.txt").write_text("a")  # the step still runs to its end
        assert (tmp_path / "a.txt").read_text() == "a"
        with pytest.raises(Stop):
            with atomic.atomic_path(tmp_path / "b.txt") as tmp:
                tmp.write_text("b")
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
    finally:
        atomic.reset_interrupt()


def test_frame_writer_rules(tmp_path):
    from dqskin.writers.mesh_files import FrameWriter, frame_paths, write_frames
    with pytest.raises(ValueError, match=r"3 frames but 1 file"):
        frame_paths(str(tmp_path / "x.obj"), [0, 1, 2])
    assert frame_paths(str(tmp_path / "x.obj"), [7]) == [tmp_path / "x.obj"]
    pts = np.zeros((2, 3, 3))
    pts[:, 1, 0] = pts[:, 2, 1] = 1
    tri = [[0, 1, 2]]
    with pytest.raises(ValueError, match="cannot hold UVs"):
        FrameWriter(str(tmp_path / "f_{}.stl"), tri, uvs=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="no faces"):
        write_frames(str(tmp_path / "f_{}.stl"), [0, 1], pts, np.zeros((0, 3), int))
    paths = write_frames(str(tmp_path / "f_{}.obj"), [0, 1], pts, tri,
                         normals=np.tile([0.0, 0.0, 1.0], (2, 3, 1)), uvs=np.eye(3)[:, :2])
    text = paths[1].read_text()
    assert text.count("\nvn ") == 3 and text.count("\nvt ") == 3 and "mtllib" not in text
    with pytest.raises(FileExistsError):
        write_frames(str(tmp_path / "f_{}.obj"), [0, 1], pts, tri)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f_0.obj", "f_1.obj"]


def test_mesh_layout_mixes_meshes_with_and_without_normals_and_uvs():
    """One file for two meshes: the one without rest normals gets area-weighted normals of its
    skinned triangles, the one without UVs gets (0, 0); glTF UVs are flipped to bottom-left."""
    from dqskin import Mesh
    from dqskin.writers.mesh_files import MeshLayout
    quad = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    one = np.ones((4, 1), np.float32)
    a = Mesh("a", quad, faces, np.zeros((4, 1), np.int32), one,
             normals=np.tile(np.float32([0, 2, 0]), (4, 1)),
             uvs=np.float32([[0, 0], [1, 0], [1, 0.25], [0, 1]]))
    b = Mesh("b", quad + 5, faces, np.zeros((4, 1), np.int32), one)
    layout = MeshLayout([a, b], ".ply", uv_top_left=True)
    assert layout.normals and layout.faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]
    np.testing.assert_allclose(layout.uvs, [[0, 1], [1, 1], [1, 0.75], [0, 0]] + [[0, 0]] * 4)
    pts = {"a": quad[None], "b": (quad + 5)[None]}
    pos, nrm = layout.frames(pts, {"a": np.tile(np.float32([0, 2, 0]), (1, 4, 1))})
    assert pos.shape == nrm.shape == (1, 8, 3)
    np.testing.assert_allclose(nrm[0, :4], [[0, 1, 0]] * 4)  # skinned, normalized
    np.testing.assert_allclose(nrm[0, 4:], [[0, 0, 1]] * 4)  # from b's triangles
    assert MeshLayout([a, b], ".stl").uvs is None and not MeshLayout([a, b], ".off").normals
    assert not MeshLayout([a, b], ".obj", normals=False).normals
