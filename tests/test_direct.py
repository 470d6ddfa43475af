"""Files written past the page cache (:mod:`dqskin.files.direct`): the bytes are exactly those
appended (and rewritten at an offset), direct or buffered, and a file system that refuses
``O_DIRECT`` gets buffered writes instead."""

import errno
import os

import numpy as np
import pytest

from dqskin.files import direct
from dqskin.files.direct import AppendFile

RNG = np.random.default_rng(7)


def _takes_direct(path):
    """Whether the file system of ``path`` (an existing file) opens it with O_DIRECT (asked of
    the kernel, not of the code under test)."""
    try:
        os.close(os.open(path, os.O_RDONLY | getattr(os, "O_DIRECT", 0)))
    except OSError:
        return False
    return hasattr(os, "O_DIRECT")


@pytest.fixture(autouse=True)
def _direct_io_on(monkeypatch):
    monkeypatch.delenv("DQSKIN_DIRECT_IO", raising=False)


def _pieces():
    """Appends of every kind and size: bytes, float32 and uint8 arrays, empty ones, pieces
    smaller and larger than a block and than the stage (patched to 3 blocks), in an order
    that leaves the stage at every offset."""
    sizes = [88, 0, 5, 4096, 4095, 1, 12_289, 3 * 4096, 7, 40_000, 4096 * 2 + 3, 100]
    out = []
    for k, n in enumerate(sizes):
        if k % 3 == 0:
            out.append(RNG.bytes(n))
        elif k % 3 == 1:
            out.append(RNG.integers(0, 256, n, dtype=np.uint8))
        else:
            out.append(RNG.normal(size=(n // 12 + 1, 3)).astype(np.float32))
    return out


def _expected(pieces, header):
    data = bytearray(b"".join(memoryview(p).cast("B").tobytes() for p in pieces))
    data[:len(header)] = header
    return bytes(data)


def _write(path, pieces, header, **kwargs):
    """Write ``pieces`` then ``header`` at 0; returns whether every whole block went past the
    page cache (still direct after the appends, and some written)."""
    f = AppendFile(path, **kwargs)
    for a in range(0, len(pieces), 3):
        assert f.append(pieces[a:a + 3]) == sum(direct.nbytes(p) for p in pieces[a:a + 3])
    used = f.direct and f._written > 0
    f.pwrite(header, 0)
    f.close()
    return used


@pytest.mark.parametrize("mode", ["direct", "buffered", "switched off"])
def test_appended_bytes_and_a_header_written_last_are_the_file(tmp_path, monkeypatch, mode):
    """The file holds what was appended, in order, with the header written over its start,
    whether the bytes went past the page cache (a small stage: every piece crosses blocks and
    stages), through it (``direct=False``), or through it because ``DQSKIN_DIRECT_IO=0``."""
    monkeypatch.setattr(direct, "STAGE", 3 * direct.BLOCK)
    if mode == "switched off":
        monkeypatch.setenv("DQSKIN_DIRECT_IO", "0")
    pieces, header = _pieces(), RNG.bytes(88)
    (tmp_path / "f.bin").touch()
    takes = _takes_direct(tmp_path / "f.bin")
    used = _write(tmp_path / "f.bin", pieces, header, direct=mode != "buffered")
    assert (tmp_path / "f.bin").read_bytes() == _expected(pieces, header)
    assert used == (mode == "direct" and takes)


def test_a_file_system_refusing_o_direct_gets_buffered_writes(tmp_path, monkeypatch):
    import fcntl
    real = fcntl.fcntl

    def no_direct(fd, cmd, arg=0):
        if cmd == fcntl.F_SETFL and arg & direct._O_DIRECT:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(fd, cmd, arg)

    monkeypatch.setattr(fcntl, "fcntl", no_direct)
    pieces, header = _pieces(), b"head"
    assert not _write(tmp_path / "f.bin", pieces, header)
    assert (tmp_path / "f.bin").read_bytes() == _expected(pieces, header)


@pytest.mark.parametrize("failure", ["EINVAL first", "EINVAL later", "short later",
                                     "ENOSPC later"])
def test_a_refused_or_short_direct_write_goes_buffered_and_a_full_disk_is_raised(
        tmp_path, monkeypatch, failure):
    """A direct write refused (EINVAL: an alignment this file system does not take), at the
    first one or after some went through, or short: what was staged and the rest go through
    the page cache, the same bytes. A full disk (ENOSPC) is the caller's error."""
    monkeypatch.setattr(direct, "STAGE", 2 * direct.BLOCK)
    (tmp_path / "f.bin").touch()
    if not _takes_direct(tmp_path / "f.bin"):
        pytest.skip("this file system refuses O_DIRECT")
    real, calls = os.pwrite, []
    f = AppendFile(tmp_path / "f.bin")

    def fail(fd, data, offset):
        if f.direct:
            calls.append(offset)
            if failure == "EINVAL first" or len(calls) > 1:
                if failure == "short later":
                    return real(fd, memoryview(data)[:512], offset)
                raise OSError(errno.EINVAL if "EINVAL" in failure else errno.ENOSPC, "refused")
        return real(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", fail)
    pieces = [RNG.bytes(5000), RNG.bytes(20_000), RNG.bytes(3)]
    if failure == "ENOSPC later":
        with pytest.raises(OSError, match="refused"):
            f.append(pieces)
        f.close(flush=False)
        return
    f.append(pieces)
    assert not f.direct
    f.pwrite(b"xy", 0)
    f.close()
    assert (tmp_path / "f.bin").read_bytes() == _expected(pieces, b"xy")


def test_pwrite_refuses_bytes_past_the_appended_ones(tmp_path):
    f = AppendFile(tmp_path / "f.bin")
    f.append([b"abc"])
    with pytest.raises(ValueError, match="past the 3 bytes"):
        f.pwrite(b"abcd", 0)
    f.close()
    assert (tmp_path / "f.bin").read_bytes() == b"abc"


def test_a_crate_layer_written_past_the_cache_is_the_buffered_one(tmp_path, monkeypatch):
    """:class:`~dqskin.files.crate.CrateSamples` past the page cache (a stage of 3 blocks:
    its sample blocks cross many) writes the bytes it writes through the cache, and usd-core
    reads its samples back."""
    from pxr import Sdf

    from dqskin.files.crate import CrateSamples
    monkeypatch.setattr(direct, "STAGE", 3 * direct.BLOCK)
    points = RNG.normal(size=(7, 500, 3)).astype(np.float32)
    points[3] = points[2]  # a held frame: stored once
    xf = RNG.normal(size=(7, 4, 4))
    files = {}
    for mode in (True, False):
        crate = CrateSamples(tmp_path / f"{mode}.usdc", 24.0, direct=mode)
        if mode:
            assert crate._file.direct == _takes_direct(tmp_path / f"{mode}.usdc")
        crate.add("/A/B.points", "point3f[]", np.arange(7.0), points)
        crate.add("/A.xformOp:transform", "matrix4d", np.arange(7.0), xf)
        files[mode] = crate.close(0, 6).read_bytes()
    assert files[True] == files[False]
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "True.usdc"))
    for k in range(7):
        np.testing.assert_array_equal(
            np.asarray(layer.QueryTimeSample("/A/B.points", float(k))), points[k])


@pytest.mark.parametrize("mode", ["direct", "buffered", "observed"])
@pytest.mark.parametrize("width", [12, 36, 3 * 4096 + 20])  # the last: a record over the stage
def test_records_are_head_row_and_padding(tmp_path, monkeypatch, mode, width):
    """``append_records``: per row of each group (all, or the selected ones in their order),
    the head, the row's bytes and the zero padding, the groups of one call one after the other
    (heads, widths and padding of their own; a group's records after another's in one block,
    or record by record), after bytes already appended and before more, the stage (3 blocks)
    crossed at every offset; records wider than the stage too. Observed: every byte seen, in
    file order."""
    monkeypatch.setattr(direct, "STAGE", 3 * direct.BLOCK)
    rows = RNG.integers(0, 256, (700, width), dtype=np.uint8)
    other = RNG.integers(0, 256, (300, 2 * width + 1), dtype=np.uint8)[:, 1:]  # strided rows
    select = np.array([5, 3, 3, 699, 0] + list(range(10, 400, 7)))
    head = RNG.bytes(8)
    f = AppendFile(tmp_path / "f.bin", direct=mode == "direct")
    seen: list[bytes] = []
    if mode == "observed":
        f.observe = lambda b: seen.append(memoryview(b).cast("B").tobytes())
    assert f.append([b"\x01" * 100]) == 100
    assert f.append_records([(head, rows, 4, None)]) == 700 * (8 + width + 4)
    groups = [(head, rows, 0, select), (b"abc", other[::3], 5, None), (b"", rows[:0], 3, None),
              (b"", other, 0, [7, 2]), (b"z", rows[:3], 1, None)]
    assert f.append_records(groups) == len(select) * (8 + width) + 100 * (3 + 2 * width + 5) \
        + 2 * 2 * width + 3 * (1 + width + 1)
    f.append([b"\x02" * 5])
    f.close()
    want = b"\x01" * 100 + b"".join(head + r.tobytes() + bytes(4) for r in rows) \
        + b"".join(head + rows[i].tobytes() for i in select) \
        + b"".join(b"abc" + r.tobytes() + bytes(5) for r in other[::3]) \
        + other[7].tobytes() + other[2].tobytes() \
        + b"".join(b"z" + r.tobytes() + b"\0" for r in rows[:3]) + b"\x02" * 5
    assert (tmp_path / "f.bin").read_bytes() == want
    assert f.size == len(want)
    if mode == "observed":
        assert b"".join(seen) == want


def test_records_refused_midway_go_buffered(tmp_path, monkeypatch):
    """The first direct write refused while records are staged: those and the rest go through
    the page cache, the same bytes."""
    monkeypatch.setattr(direct, "STAGE", 2 * direct.BLOCK)
    f = AppendFile(tmp_path / "f.bin")
    if not f.direct:
        f.close()
        pytest.skip("this file system refuses O_DIRECT")
    real = os.pwrite

    def refuse(fd, data, offset):
        if f.direct:
            raise OSError(errno.EINVAL, "refused")
        return real(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", refuse)
    rows = RNG.integers(0, 256, (300, 40), dtype=np.uint8)
    f.append_records([(b"h", rows, 3, None)])
    assert not f.direct
    f.close()
    assert (tmp_path / "f.bin").read_bytes() == b"".join(b"h" + r.tobytes() + bytes(3)
                                                         for r in rows)


def test_a_failed_write_of_the_tail_keeps_it_staged(tmp_path, monkeypatch):
    """The page-cache write of the staged tail fails once (a full disk): the error is raised and
    the bytes stay staged, so a later flush (the disk freed) still writes the whole file."""
    (tmp_path / "f.bin").touch()
    if not _takes_direct(tmp_path / "f.bin"):
        pytest.skip("this file system refuses O_DIRECT")
    monkeypatch.setattr(direct, "STAGE", 2 * direct.BLOCK)
    f = AppendFile(tmp_path / "f.bin")
    pieces = [RNG.bytes(9000), RNG.bytes(77)]
    f.append(pieces)
    real, failed = os.pwrite, []

    def full_once(fd, data, offset):
        if not f.direct and not failed:
            failed.append(offset)
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", full_once)
    with pytest.raises(OSError, match="No space"):
        f.flush()
    f.append([b"more"])
    f.close()
    assert failed and (tmp_path / "f.bin").read_bytes() == b"".join(pieces) + b"more"


def test_records_must_be_rows_of_bytes(tmp_path):
    f = AppendFile(tmp_path / "f.bin")
    with pytest.raises(ValueError, match="uint8 rows"):
        f.append_records([(b"h", np.zeros((2, 3), np.float32), 0, None)])
    assert f.append_records([(b"", np.zeros((5, 0), np.uint8), 0, None)]) == 0
    f.close()
    assert (tmp_path / "f.bin").read_bytes() == b""


@pytest.mark.parametrize("mode", ["direct", "buffered", "refused midway"])
def test_a_crate_layer_hashed_as_written_matches_its_bytes(tmp_path, monkeypatch, mode):
    """``CrateSamples(hasher=)`` sees every byte after the bootstrap in file order, then the
    bootstrap: its digest equals XXH3-128 of the finished file's bytes 88.. and 0..88 read back
    here (records copied into a 3-block stage, held frames, matrices; direct, buffered, and
    direct writes refused after some went through)."""
    import xxhash

    from dqskin.files.crate import CrateSamples
    monkeypatch.setattr(direct, "STAGE", 3 * direct.BLOCK)
    if mode == "refused midway":
        real, calls = os.pwrite, []

        def refuse(fd, data, offset):
            if direct.nbytes(data) % direct.BLOCK == 0 and offset % direct.BLOCK == 0:
                calls.append(offset)
                if len(calls) > 2:
                    raise OSError(errno.EINVAL, "refused")
            return real(fd, data, offset)
        monkeypatch.setattr(os, "pwrite", refuse)
    points = RNG.normal(size=(9, 400, 3)).astype(np.float32)
    points[4] = points[3]
    hasher = xxhash.xxh3_128()
    crate = CrateSamples(tmp_path / "c.usdc", 24.0, direct=mode != "buffered", hasher=hasher)
    assert crate._file.direct == (mode != "buffered" and _takes_direct(tmp_path / "c.usdc"))
    crate.add("/A/B.points", "point3f[]", np.arange(5.0), points[:5])
    crate.add("/A.xformOp:transform", "matrix4d", np.arange(9.0), RNG.normal(size=(9, 4, 4)))
    crate.add("/A/B.points", "point3f[]", np.arange(5.0, 9.0), points[5:])
    data = crate.close(0, 8).read_bytes()
    assert hasher.hexdigest() == xxhash.xxh3_128(data[88:] + data[:88]).hexdigest()
    from dqskin.writers.usd_clips import file_checksum
    assert file_checksum(tmp_path / "c.usdc") == hasher.hexdigest()


def test_without_pwrite_the_buffered_path_writes_the_same(tmp_path, monkeypatch):
    """Where ``os.pwrite`` does not exist (Windows), the buffered path seeks and writes."""
    monkeypatch.delattr(os, "pwrite")
    pieces, header = _pieces(), RNG.bytes(88)
    assert not _write(tmp_path / "f.bin", pieces, header, direct=False)
    assert (tmp_path / "f.bin").read_bytes() == _expected(pieces, header)


@pytest.mark.parametrize("clips", [False, True])
def test_a_bake_past_the_page_cache_writes_the_bytes_a_buffered_one_does(tmp_path, monkeypatch,
                                                                         clips):
    """``dqskin.bake`` of the bundled humanoid (points, normals, velocities), single layer and
    value clips: every file the same bytes with ``DQSKIN_DIRECT_IO=0`` as past the page cache
    (a 3-block stage, so the direct path runs on these small files)."""
    from pathlib import Path

    from dqskin.baking import bake
    humanoid = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"
    monkeypatch.setattr(direct, "STAGE", 3 * direct.BLOCK)
    out = {}
    for mode in ("1", "0"):
        monkeypatch.setenv("DQSKIN_DIRECT_IO", mode)
        folder = tmp_path / mode
        folder.mkdir()
        bake(str(humanoid), folder / "shot.usd", clips=clips,
             **({"chunk": 16} if clips else {}))
        out[mode] = {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*"))
                     if p.is_file()}
    assert len(out["1"]) >= (3 if clips else 1)
    assert out["1"] == out["0"]
