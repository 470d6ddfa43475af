"""A non-editable install ships the kernels as ``dqskin.kernels`` and the bundled rigs as
``dqskin.assets``: installed into a fresh virtual environment outside the checkout, it imports,
skins and runs ``dqskin demo`` (sweeps included)."""

import json
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_ships_kernels_and_imports_outside_the_repo(tmp_path):
    # build from a clean copy: stale files in the checkout's build/ must not hide a missing module
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "dist", "out", "*.egg-info", "__pycache__", ".pytest_cache"))
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                            str(tmp_path / "dist"), str(src)], capture_output=True, text=True,
                           timeout=600)
    assert build.returncode == 0, build.stderr
    (wheel,) = (tmp_path / "dist").glob("dqskin-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for module in ("dqmath", "fk", "grid", "skin", "velocity", "metrics", "render"):
        assert f"dqskin/kernels/{module}.py" in names
    for rig in ("humanoid", "twist_cylinder", "bending_arm"):
        assert f"dqskin/assets/{rig}.usda" in names
    for module in ("readers/usd", "readers/gltf", "report/compare", "report/html"):
        assert f"dqskin/{module}.py" in names
    assert "dqskin/py.typed" in names  # PEP 561: type checkers read the annotations
    assert not any(n.startswith(("kernels/", "assets/", "tests/", "tools/")) for n in names)
    # a fresh virtual environment outside the checkout; its dependencies (not dqskin) come from
    # the test environment's site-packages through a .pth line
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=300)
    py = venv / "bin" / "python"
    site = Path(subprocess.run([str(py), "-c", "import sysconfig; "
                                "print(sysconfig.get_paths()['purelib'])"], capture_output=True,
                               text=True, check=True).stdout.strip())
    (site / "dqskin_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install",
                              "--no-deps", "-q", str(wheel)], capture_output=True, text=True,
                             timeout=600)
    assert install.returncode == 0, install.stderr
    code = ("import dqskin, dqskin.kernels.skin, numpy as np; print(dqskin.__file__); "
            "print(dqskin.skin_points(np.zeros((2, 3)), [[0], [0]], [[1.0], [1.0]], "
            "np.eye(4)[None], device='cpu').shape)")
    run = subprocess.run([str(py), "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.split()
    assert lines[0].startswith(str(site)) and "(2, 3)" in run.stdout
    demo = subprocess.run([str(venv / "bin" / "dqskin"), "demo", "--out", "demo", "--device",
                           "cpu"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert demo.returncode == 0, demo.stderr
    metrics = json.loads((tmp_path / "demo" / "report" / "metrics.json").read_text())
    assert metrics["asset"].startswith(str(site))  # the packaged rig, not the checkout's
    assert set(metrics["sweeps"]) >= {"twist", "bend"}, metrics["sweeps"]
    assert (tmp_path / "demo" / "humanoid_dqs.usdc").stat().st_size > 0
