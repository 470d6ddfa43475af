"""The README's Python example runs as written and prints what it claims."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_python_example_runs():
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "README has no python example"
    proc = subprocess.run([sys.executable, "-c", blocks[0]], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    def number(line):
        try:
            return float(line)
        except ValueError:
            return None
    # Warp prints its own banner and module-load lines too; the example prints two numbers
    printed = [v for v in map(number, proc.stdout.splitlines()) if v is not None]
    assert len(printed) == 2, proc.stdout
    dqs_min, lbs_max = printed
    assert abs(dqs_min - 1.0) < 1e-5 and lbs_max < 1e-5
