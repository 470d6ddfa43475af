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


@pytest.fixture(scope="session", autouse=True)
def _private_cache(tmp_path_factory):
    """Every test (and the CLI it runs, and its subprocesses) caches in a temporary folder, never
    in the user's ``~/.cache/dqskin``: tests neither read stale entries nor leave files there."""
    old = os.environ.get("DQSKIN_CACHE_DIR")
    os.environ["DQSKIN_CACHE_DIR"] = str(tmp_path_factory.mktemp("dqskin-cache"))
    yield
    if old is None:
        os.environ.pop("DQSKIN_CACHE_DIR", None)
    else:
        os.environ["DQSKIN_CACHE_DIR"] = old


def _devices():
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    return ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


DEVICES = _devices()


@pytest.fixture(params=DEVICES)
def device(request):
    """Every available Warp device: ``cpu``, and ``cuda:0`` when present."""
    return request.param


@pytest.fixture(autouse=True)
def _workers_always(monkeypatch):
    """``workers=N`` bakes start their workers whatever the shot's length (tests of the
    workers' behaviour use short shots); tests of the choice itself delete the variable."""
    monkeypatch.setenv("DQSKIN_WORKERS_PAY_SECONDS", "0")
