"""Output buffers (:mod:`dqskin.kernels.buffers`): large CPU buffers ask for huge pages."""

import gc
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from dqskin._warp import init_warp
from dqskin.kernels import buffers as KB


def _vm_flags(address):
    """The ``VmFlags`` of the mapping holding ``address`` (``/proc/self/smaps``)."""
    inside = False
    with open("/proc/self/smaps") as fh:
        for line in fh:
            head = line.split()[0]
            if "-" in head and not head.endswith(":"):
                lo, hi = (int(x, 16) for x in head.split("-"))
                inside = lo <= address < hi
            elif inside and head == "VmFlags:":
                return line.split()[1:]
    raise AssertionError(f"no mapping holds {address:#x}")


_FLAGS = """
import sys
import warp as wp
from dqskin._warp import init_warp
from dqskin.kernels import buffers as KB
from test_buffers import _vm_flags
wp.config.log_level = wp.LOG_ERROR
init_warp()
n = 3 * KB.HUGE_PAGE // 12  # vec3: 3 huge pages
big = KB.empty((2, n), wp.vec3, "cpu")
assert big.shape == (2, n) and big.dtype == wp.vec3
plain = wp.empty((2, n), dtype=wp.vec3, device="cpu")  # what Warp alone does
print(*("hg" in _vm_flags(a.ptr + a.capacity // 2) for a in (big, plain)))
"""


def _huge_flags(**env):
    """Whether a :func:`KB.empty` buffer and a plain ``wp.empty`` one carry MADV_HUGEPAGE, in a
    fresh process (in this one, freed memory keeps the flag of an earlier buffer)."""
    run_env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    run_env.update(env, PYTHONPATH=os.pathsep.join([str(Path(__file__).parent),
                                                    run_env.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", _FLAGS], capture_output=True, text=True,
                         env=run_env, check=True).stdout.strip().splitlines()[-1].split()
    return out[0] == "True", out[1] == "True"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="madvise and smaps are Linux's")
def test_large_cpu_buffers_ask_for_huge_pages():
    assert _huge_flags() == (True, False)
    assert _huge_flags(NUMPY_MADVISE_HUGEPAGE="0") == (False, False)  # NumPy's switch, here too


def test_cpu_buffers_are_ordinary_buffers():
    init_warp()
    big = KB.empty((2, 3 * KB.HUGE_PAGE // 12), wp.vec3, "cpu")
    big.numpy()[:] = 1.0
    assert np.all(big.numpy() == 1.0)


def test_reusing_hands_a_buffer_out_again_only_once_nothing_holds_it():
    """Inside ``KB.reusing(pool)``, a large CPU buffer comes back only once its array and every
    NumPy view of it are gone, to the next request it is the smallest fit for (a shorter array
    takes it, a longer one does not); small buffers are not the pool's, nor any outside the
    block; a buffer in use outlives its pool."""
    init_warp()
    n = KB.MIN_BYTES // 12 + 1
    pool = KB.BufferPool()
    with KB.reusing(pool):
        a = KB.empty((2, n), wp.vec3, "cpu")
        first = a.ptr
        view = a.numpy()[0, 5:]
        del a
        b = KB.empty((2, n), wp.vec3, "cpu")  # `view` still holds the first buffer
        assert b.ptr != first and len(pool) == 0
        second = b.ptr
        del view
        assert len(pool) == 1
        assert KB.empty((3, n), wp.vec3, "cpu").ptr != first  # too small for it
        c = KB.empty((1, n), wp.vec3, "cpu")  # a shorter one takes it
        assert c.ptr == first and c.shape == (1, n) and c.dtype == wp.vec3
        del b
        big = KB.empty((4, n), wp.vec3, "cpu")
        d = KB.empty((1, n), wp.vec3, "cpu")  # the smallest fit: b's (2n), not the 3n one
        assert d.ptr == second and d.shape == (1, n)
        e = KB.empty((1, n), wp.vec3, "cpu")  # the 3n one is free but over twice the size
        assert e.shape == (1, n) and len(pool) == 1
        free = len(pool)
        small = KB.empty((1, 8), wp.vec3, "cpu")
        del small
        assert len(pool) == free  # small buffers are their own
    c.numpy()[:] = 7.0
    outside = KB.empty((2, n), wp.vec3, "cpu")
    del outside
    assert len(pool) == free  # not the pool's
    with KB.reusing(pool):  # `c` still holds its buffer: never handed out
        assert all(KB.empty((1, n), wp.vec3, "cpu").ptr != first for _ in range(3))
    # the pool goes while `c` lives: its buffer stays valid until `c` goes
    del pool, big, d, e
    gc.collect()
    for _ in range(3):
        KB.empty((1, n), wp.vec3, "cpu").numpy()[:] = 1.0
    assert np.all(c.numpy() == 7.0)
