"""Output buffers (:mod:`dqskin.kernels.buffers`): large CPU buffers ask for huge pages."""

import sys

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


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="madvise and smaps are Linux's")
def test_large_cpu_buffers_ask_for_huge_pages():
    init_warp()
    n = 3 * KB.HUGE_PAGE // 12  # vec3: 3 huge pages
    big = KB.empty((2, n), wp.vec3, "cpu")
    assert big.shape == (2, n) and big.dtype == wp.vec3
    assert "hg" in _vm_flags(big.ptr + big.capacity // 2)  # MADV_HUGEPAGE on its interior
    plain = wp.empty((2, n), dtype=wp.vec3, device="cpu")  # what Warp alone does
    assert "hg" not in _vm_flags(plain.ptr + plain.capacity // 2)
    big.numpy()[:] = 1.0  # an ordinary buffer otherwise
    assert np.all(big.numpy() == 1.0)


def test_numpy_switch_turns_huge_pages_off(monkeypatch):
    """``NUMPY_MADVISE_HUGEPAGE=0`` (NumPy's own switch) turns the advice off here too."""
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "0")
    assert KB._madvise() is None
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE")
    assert (KB._madvise() is None) == (not sys.platform.startswith("linux"))
