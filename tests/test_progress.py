"""Progress bars are drawn only on a terminal: every bar in dqskin comes from
:func:`dqskin.progress.progress_bar`, which writes nothing when stderr is a file or a pipe."""

import io
import re
from pathlib import Path

import pytest

from dqskin.progress import NoBar, progress_bar

ROOT = Path(__file__).resolve().parents[1]


class _Stream(io.StringIO):
    def __init__(self, tty):
        super().__init__()
        self.tty = tty

    def isatty(self):
        return self.tty


@pytest.mark.parametrize("tty", [False, True])
def test_bar_only_on_a_terminal(monkeypatch, tty):
    err = _Stream(tty)
    monkeypatch.setattr("sys.stderr", err)
    with progress_bar(total=3, desc="skinning", unit="frame") as bar:
        for _ in range(3):
            bar.update()
    assert isinstance(bar, NoBar) is not tty
    assert ("skinning" in err.getvalue()) is tty and (err.getvalue() == "") is not tty
    # asked not to draw: nothing, on a terminal too; iterating still yields every item
    quiet = progress_bar(range(4), enabled=False, desc="render")
    assert list(quiet) == [0, 1, 2, 3]
    assert ("render" in err.getvalue()) is False


def test_every_bar_goes_through_progress_bar():
    """tqdm is named nowhere else in the package (outside docstrings): no bar can skip the
    terminal check."""
    offenders = []
    for path in sorted((ROOT / "dqskin").rglob("*.py")):
        if path.name == "progress.py":
            continue
        code = path.read_text(encoding="utf-8")
        if re.search(r"^\s*(from tqdm|import tqdm)|\btqdm\(", code, re.M):
            offenders.append(path.relative_to(ROOT).as_posix())
    assert offenders == []
