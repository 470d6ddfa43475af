"""Shared fixtures: the real-asset folder and the Warp devices.

Every device-agnostic test runs on those devices.
"""

import os
from pathlib import Path

import pytest
import warp as wp

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def shared_assets():
    """``../shared/assets``: required in CI (``CI=true``), skipped with a reason elsewhere."""
    path = SHARED / "assets"
    if not path.is_dir():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"../shared/assets is missing at {path} (required in CI)")
        pytest.skip(f"../shared/assets not found at {path}")
    return path


def _devices():
    wp.config.quiet = True
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Every available Warp device: ``cpu``, and ``cuda:0`` when present."""
    return request.param
