"""Output buffers (:mod:`dqskin.kernels.buffers`): large CPU buffers ask for huge pages."""

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
wp.config.quiet = True
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
