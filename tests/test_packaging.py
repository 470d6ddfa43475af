"""A non-editable install ships the kernels as ``dqskin.kernels``.

It also imports from outside the repo.
"""

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
    for module in ("dqmath", "fk", "skin", "velocity", "metrics", "render"):
        assert f"dqskin/kernels/{module}.py" in names
    assert not any(n.startswith(("kernels/", "tests/", "tools/")) for n in names)
    site = tmp_path / "site"
    install = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q",
                              "--target", str(site), str(wheel)], capture_output=True, text=True,
                             timeout=600)
    assert install.returncode == 0, install.stderr
    deps = sysconfig.get_paths()["purelib"]
    code = ("import dqskin, dqskin.kernels.skin, numpy as np; print(dqskin.__file__); "
            "print(dqskin.skin_points(np.zeros((2, 3)), [[0], [0]], [[1.0], [1.0]], "
            "np.eye(4)[None], device='cpu').shape)")
    run = subprocess.run([sys.executable, "-I", "-c", f"import sys; sys.path[:0] = "
                          f"[{str(site)!r}, {deps!r}]; {code}"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.split()
    assert lines[0].startswith(str(site)) and "(2, 3)" in run.stdout
