"""The documentation builds without a broken link or reference, its CLI reference is the parser's,
the Python examples of the README, Getting started, the concept pages and the how-to guides run
as written, and so do the README's ``dqskin`` commands.

A ```python block that cannot run is marked in the Markdown by ``<!-- no-run: why -->`` on the
line above it; :data:`MAX_NO_RUN` keeps them few.
"""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
PAGES = [ROOT / "README.md", ROOT / "docs" / "getting-started.md",
         *sorted((ROOT / "docs" / "concepts").glob("*.md")),
         *sorted((ROOT / "docs" / "guides").glob("*.md"))]
MAX_NO_RUN = 2
README_MAX_LINES = 300
_BLOCK = re.compile(r"^(<!-- no-run: (?P<why>[^>]*?) -->\n)?```python\n(?P<code>.*?)^```",
                    re.M | re.S)


def python_blocks(text):
    """``(code, why)`` for every ```python block, ``why`` the no-run reason or None."""
    return [(m["code"], m["why"]) for m in _BLOCK.finditer(text)]


def dqskin_commands(text):
    """The ``dqskin ...`` command lines of the ```bash blocks (continuations joined, comments
    dropped), as argument lists."""
    commands = []
    for block in re.findall(r"^```bash\n(.*?)^```", text, re.M | re.S):
        for line in block.replace("\\\n", " ").splitlines():
            args = shlex.split(line, comments=True)
            if args[:1] == ["dqskin"]:
                commands.append(args[1:])
    return commands


def test_python_blocks_parser():
    text = ("a\n```python\nx = 1\n```\n<!-- no-run: later -->\n```python\ny = 2\n```\n"
            "```bash\nz\n```\n")
    assert python_blocks(text) == [("x = 1\n", None), ("y = 2\n", "later")]


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines <= README_MAX_LINES, f"README.md: {lines} lines, at most {README_MAX_LINES}"


def test_no_run_blocks_are_few_and_explained():
    marks = []
    for page in PAGES:
        text = page.read_text()
        found = [why for _, why in python_blocks(text) if why is not None]
        assert text.count("<!-- no-run:") == len(found), \
            f"{page.name}: a no-run marker not directly above a ```python block"
        marks += [(page.name, why) for why in found]
    assert all(why.strip() for _, why in marks), marks
    assert len(marks) <= MAX_NO_RUN, f"too many no-run blocks: {marks}"


@pytest.fixture
def workdir(tmp_path):
    """A working folder where ``assets/`` is the repository's and ``../shared`` the shared one's,
    as from the repository root."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "assets").symlink_to(ROOT / "assets")
    if SHARED.is_dir():
        (tmp_path / "shared").symlink_to(SHARED)
    return work


def run_page(page, workdir, request):
    code = "\n".join(c for c, why in python_blocks(page.read_text()) if why is None)
    assert code, f"{page.name}: no runnable python block"
    if "../shared/" in code:
        request.getfixturevalue("shared_assets")  # skipped with its reason without ../shared
    script = workdir.parent / "page_example.py"  # not named after a module the code imports
    script.write_text(code)
    proc = subprocess.run([sys.executable, str(script)], cwd=workdir, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, f"{page.name}:\n{proc.stderr[-4000:]}"
    return proc.stdout


def numbers(stdout):
    out = []
    for line in stdout.splitlines():
        try:
            out.append(float(line))
        except ValueError:
            pass  # Warp's banner and the examples' other lines
    return out


def test_readme_examples_run(workdir, request):
    stdout = run_page(ROOT / "README.md", workdir, request)
    # the ring example: DQS keeps the radius 1 (a rigid half turn), LBS collapses it to 0
    dqs_radius, lbs_radius = numbers(stdout)
    assert abs(dqs_radius - 1.0) < 1e-5 and lbs_radius < 1e-5
    assert "(49, 1202, 3)" in stdout  # the humanoid's body over its 49 time codes
    assert (workdir / "out" / "walk_api.usdc").is_file()


def test_readme_commands_run(workdir, request):
    commands = dqskin_commands((ROOT / "README.md").read_text())
    assert len(commands) >= 5, commands
    for args in commands:
        if any("../shared/" in a for a in args):
            request.getfixturevalue("shared_assets")
        proc = subprocess.run([sys.executable, "-m", "dqskin.cli", *args], cwd=workdir,
                              capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, f"dqskin {shlex.join(args)}:\n{proc.stderr[-4000:]}"
    assert (workdir / "out" / "report" / "report.html").is_file()
    # frames 12, 24 and 36 at 24 fps: 0.5, 1 and 1.5 s, with their material beside them
    assert len(list((workdir / "out" / "cesium").glob("f_*.obj"))) == 3
    assert (workdir / "out" / "cesium" / "f.mtl").is_file()
    assert (workdir / "out" / "cesium.usdc").is_file()


@pytest.mark.parametrize("page", [p for p in PAGES if p.name != "README.md"
                                  and python_blocks(p.read_text())], ids=lambda p: p.stem)
def test_page_examples_run(page, workdir, request):
    run_page(page, workdir, request)


def test_mkdocs_build_strict(tmp_path):
    """``mkdocs build --strict``: a broken link, anchor or API reference fails the build."""
    site = tmp_path / "site"
    # (not -q: it hides the warnings that --strict counts, and the build then passes)
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(site)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    problems = [ln for ln in (proc.stdout + proc.stderr).splitlines()
                if ln.startswith(("WARNING", "ERROR", "Aborted"))]
    assert proc.returncode == 0, "\n".join(problems) or proc.stderr[-4000:]
    # the CLI reference lists every subcommand and option of the parser it was generated from
    from dqskin.cli import build_parser
    cli = (site / "reference" / "cli" / "index.html").read_text()
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command")
    for name, sub in subparsers.choices.items():
        assert f"dqskin {name}" in cli, name
        for action in sub._actions:
            for flag in action.option_strings:
                if action.dest in ("help", "verbose"):
                    continue  # every subcommand's, said once on the page
                assert f"<code>{flag}</code>" in cli, f"dqskin {name} {flag}"
    api = (site / "reference" / "api" / "index.html").read_text()
    for name in ("load", "Scene", "Scene.skin", "SkinnedFrames", "Skinner", "skin_points",
                 "Skeleton", "bake", "Crowd", "rig_mesh", "errors.InputError", "SkinOptions",
                 "CorOptions", "BakeSettings", "options.DEFAULT_SIGN_REFERENCE", "spaces.SPACES",
                 "errors.OutputExistsError", "errors.UnknownNameError",
                 "report.compare.run_compare"):
        assert f'id="dqskin.{name}"' in api, name


def test_docstring_rewrite_for_the_api_reference():
    """The griffe extension's rewrite: closing prose gets a Notes heading, a ``{..}`` type is not
    read as choices, Sphinx roles become inline code; nothing else changes."""
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        from griffe_docstrings import rewrite
    finally:
        sys.path.pop(0)
    text = ("Skin it (:func:`dqskin.load`, :meth:`~.scene.Scene.skin`).\n\nParameters\n"
            "----------\nmethod : {\"lbs\", \"dqs\"} or None\n    None: the asset's.\n\n"
            "Closing prose.\n")
    assert rewrite(text) == (
        "Skin it (``dqskin.load``, ``skin``).\n\nParameters\n----------\n"
        "method : one of {\"lbs\", \"dqs\"} or None\n    None: the asset's.\n\nNotes\n-----\n"
        "Closing prose.\n")
    plain = "Summary.\n\nReturns\n-------\n(F, V, 3) float32\n    Points.\n"
    assert rewrite(plain) == plain
