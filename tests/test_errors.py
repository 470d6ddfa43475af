"""dqskin.errors: the classes callers can tell apart, messages that name what the caller typed
(``force=True`` from Python, ``--force`` on the command line), and the command line's exit
status: 2 for a DqskinError, 70 with a traceback file for anything else (a bug)."""

import ast
import concurrent.futures
import multiprocessing
import pickle
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import dqskin
from dqskin import cli
from dqskin.errors import (
    DqskinError,
    InputError,
    Interrupted,
    LimitError,
    OutputExistsError,
    Param,
    UnknownNameError,
    output_exists,
)

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "assets" / "humanoid.usda"
BUG_LINE = re.compile(r"^dqskin: internal error \(a bug\): (\w+): (.*); traceback written to "
                      r"(\S+)$")


# -- the classes -----------------------------------------------------------------------------

def test_each_kind_is_also_the_builtin_callers_already_catch():
    assert issubclass(InputError, ValueError) and issubclass(InputError, DqskinError)
    assert issubclass(LimitError, InputError)
    assert issubclass(OutputExistsError, FileExistsError)
    assert issubclass(OutputExistsError, DqskinError)
    assert issubclass(UnknownNameError, KeyError) and issubclass(UnknownNameError, InputError)
    assert issubclass(Interrupted, KeyboardInterrupt) and not issubclass(Interrupted, Exception)
    assert cli.Interrupted is Interrupted
    from dqskin.files.crate import UnsupportedCrate
    assert issubclass(UnsupportedCrate, InputError)
    # the package exports them (lazily) and the module
    assert dqskin.DqskinError is DqskinError and dqskin.LimitError is LimitError
    assert dqskin.errors.OutputExistsError is OutputExistsError
    assert {"DqskinError", "InputError", "LimitError", "OutputExistsError",
            "UnknownNameError", "errors"} <= set(dqskin.__all__)


def test_an_unknown_name_reads_as_its_message_not_a_quoted_key():
    """KeyError's own str() quotes its argument; a lookup error is a message like the others."""
    exc = UnknownNameError("a.usda: no mesh 'x'; meshes: ['body']")
    assert str(exc) == "a.usda: no mesh 'x'; meshes: ['body']"
    with pytest.raises(UnknownNameError, match="no mesh 'x'") as info:
        dqskin.load(HUMANOID).mesh("x")
    assert isinstance(info.value, KeyError)  # what Scene.mesh raised before


def test_messages_name_api_parameters_and_the_cli_spells_them_as_flags():
    exc = LimitError("the clip selects 9 frames; raise ", Param("max_frames"), " to allow more")
    assert str(exc) == "the clip selects 9 frames; raise max_frames to allow more"
    assert exc.message(cli.flag) == "the clip selects 9 frames; raise --max-frames to allow more"
    cases = {Param("force", True): ("force=True", "--force"),
             Param("overwrite", True): ("overwrite=True", "--force"),  # flatten(overwrite=)
             Param("clips", False): ("clips=False", "--no-clips"),
             Param("chunk", 0): ("chunk=0", "--chunk 0"),
             Param("out", Path("a b.usd")): ("out='a b.usd'", "--out 'a b.usd'"),
             Param("fps", 24.0): ("fps=24.0", "--fps 24")}
    for param, (api, flag) in cases.items():
        assert (str(param), cli.flag(param)) == (api, flag)


def _raise_limit():
    raise LimitError("--x is not named here; ", Param("max_rays"), " is")


def test_errors_cross_process_boundaries_with_their_type_and_parameters():
    """Pickled as Dask pickles a task's error: the class, the message and the parameters (so
    the CLI still spells them as flags) survive."""
    exc = OutputExistsError("a: exists (use ", Param("force", True), " to overwrite)")
    back = pickle.loads(pickle.dumps(exc))
    assert type(back) is OutputExistsError and str(back) == str(exc)
    assert back.message(cli.flag) == "a: exists (use --force to overwrite)"
    assert pickle.loads(pickle.dumps(Param("chunk"))).has_value is False
    with concurrent.futures.ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("fork")) as pool:
        with pytest.raises(LimitError) as info:
            pool.submit(_raise_limit).result()
    assert info.value.message(cli.flag) == "--x is not named here; --max-rays is"


# -- the same refusal from Python and from the command line -----------------------------------

def test_bake_over_an_existing_file_names_force_in_python_and_the_flag_on_the_command_line(
        tmp_path, capsys):
    out = tmp_path / "cache.npz"
    out.write_bytes(b"not ours to replace")
    with pytest.raises(OutputExistsError) as info:
        dqskin.bake(dqskin.load(HUMANOID), out, method="lbs", device="cpu")
    assert str(info.value) == f"{out}: exists (use force=True to overwrite)"
    assert cli.main(["skin", str(HUMANOID), "--out", str(out), "--device", "cpu"]) == 2
    assert capsys.readouterr().err == (f"dqskin: error: {out}: exists (use --force to "
                                       "overwrite)\n")
    assert out.read_bytes() == b"not ours to replace"


def test_flatten_names_its_own_parameter(tmp_path):
    from dqskin.writers.usd_clips import flatten
    out = tmp_path / "flat.usdc"
    out.write_bytes(b"")
    with pytest.raises(FileExistsError, match=r"use overwrite=True to overwrite"):
        flatten(HUMANOID, out)
    assert output_exists(out, "overwrite").message(cli.flag).endswith("(use --force to overwrite)")


def test_a_frame_limit_names_max_frames_in_python_and_on_the_command_line(tmp_path, capsys):
    from dqskin.times import select_times
    with pytest.raises(LimitError, match=r"^frames='0:50'.*limit of 10; raise max_frames"):
        select_times(range(60), 24.0, frames="0:50", max_frames=10)
    out = tmp_path / "c.npz"
    code = cli.main(["skin", str(HUMANOID), "--out", str(out), "--frames", "0:50",
                     "--max-frames", "10", "--device", "cpu"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("dqskin: error: --frames 0:50 selects 51 frames"), err
    assert "raise --max-frames to allow more" in err and not out.exists()


def test_an_unknown_device_names_the_device_parameter():
    from dqskin._warp import resolve_device
    with pytest.raises(InputError) as info:
        resolve_device("bogus")
    assert str(info.value).startswith("device='bogus': ")
    assert info.value.message(cli.flag).startswith("--device bogus: ")


def test_one_file_for_many_frames_names_bakes_times_parameter(tmp_path):
    """bake selects frames with ``times`` (the CLI's ``--frames``)."""
    with pytest.raises(InputError) as info:
        dqskin.bake(dqskin.load(HUMANOID), tmp_path / "one.obj", [0.0, 1.0], device="cpu")
    assert str(info.value).endswith("or select one frame with times")
    assert info.value.message(cli.flag).endswith("or select one frame with --frames")


def test_each_negated_flag_sets_its_api_parameter_to_false():
    """``NEGATED`` holds the ``--no-...`` flags that set an API parameter (a SkinOptions or
    BakeSettings field) to False, and every such flag of the parser."""
    import argparse
    import dataclasses

    from dqskin.baking import BakeSettings
    from dqskin.options import SkinOptions
    api = {f.name for c in (SkinOptions, BakeSettings) for f in dataclasses.fields(c)}
    negated = {}
    parser = cli.build_parser()
    subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    for sub in [parser, *(p for a in subparsers for p in a.choices.values())]:
        for action in sub._actions:
            for option in action.option_strings:
                if option.startswith("--no-") and action.dest in api and (
                        isinstance(action, argparse._StoreFalseAction)
                        or isinstance(action, argparse.BooleanOptionalAction)):
                    negated[action.dest] = option
    assert cli.NEGATED == negated
    for name, option in negated.items():
        assert cli.flag(Param(name, False)) == option


def test_library_text_names_no_command_line_flag():
    """Flags are the CLI's spelling (:func:`dqskin.cli.flag`); messages and report text made by
    the library name API parameters (:class:`Param`) or none. Docstrings may show commands."""
    flag_text = re.compile(r"(?<![\w-])--[a-z]")
    found = []
    for path in sorted([*ROOT.glob("dqskin/**/*.py"), *ROOT.glob("kernels/**/*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        if rel == "dqskin/cli.py":
            continue
        tree = ast.parse(path.read_text(), rel)
        docstrings = {id(n.value) for n in ast.walk(tree)
                      if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
        found += [f"{rel}:{n.lineno}: {n.value!r}" for n in ast.walk(tree)
                  if isinstance(n, ast.Constant) and isinstance(n.value, str)
                  and id(n) not in docstrings and flag_text.search(n.value)]
    assert not found, "\n".join(found)


# -- a bug exits 70 with a traceback file; bad input exits 2 without one ----------------------

@pytest.mark.parametrize("kind", [ValueError, KeyError, TypeError, RuntimeError, OSError])
def test_a_bug_exits_70_naming_the_traceback_file(kind, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))

    def buggy_command(args):
        raise kind("injected")

    monkeypatch.setattr(cli, "cmd_info", buggy_command)
    assert cli.main(["info", str(HUMANOID)]) == cli.EXIT_INTERNAL == 70
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    m = BUG_LINE.match(err.strip())
    assert m and m[1] == kind.__name__ and "injected" in m[2], err
    report = Path(m[3])
    assert report.parent == tmp_path and report.is_file()
    text = report.read_text()
    assert "Traceback (most recent call last)" in text and "buggy_command" in text
    assert f"{kind.__name__}: " in text and "injected" in text


def test_verbose_prints_the_traceback_too(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(cli, "cmd_info", lambda args: {}["missing"])
    assert cli.main(["--verbose", "info", str(HUMANOID)]) == 70
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and BUG_LINE.match(err.splitlines()[-1])


@pytest.mark.parametrize("kind", ["ValueError", "RuntimeError"])
def test_a_bug_in_the_process_exits_70_with_one_line(kind, tmp_path):
    """As the console script runs: ``main()`` ends the process itself."""
    code = ("import sys\nfrom dqskin import cli\n"
            f"def buggy_command(args):\n    raise {kind}('injected bug')\n"
            "cli.cmd_info = buggy_command\nsys.argv = ['dqskin', 'info', sys.argv[1]]\n"
            "cli.main()\n")
    proc = subprocess.run([sys.executable, "-c", code, str(HUMANOID)], capture_output=True,
                          text=True, timeout=300, env={**_env(), "TMPDIR": str(tmp_path)})
    assert proc.returncode == 70, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    m = BUG_LINE.match(lines[0])
    assert m and m[1] == kind and m[2] == "injected bug", lines[0]
    text = Path(m[3]).read_text()
    assert Path(m[3]).parent == tmp_path
    assert "buggy_command" in text and f"{kind}: injected bug" in text


def test_bad_input_still_exits_2_without_a_traceback(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\n(\n  this is not USD\n")
    assert cli.main(["info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"dqskin: error: {bad}") and len(err.splitlines()) == 1, err
    assert "Traceback" not in err and not any((tmp_path / "tmp").iterdir())
    proc = subprocess.run([sys.executable, "-m", "dqskin.cli", "info", str(bad)],
                          capture_output=True, text=True, timeout=300,
                          env={**_env(), "TMPDIR": str(tmp_path / "tmp")})
    assert proc.returncode == 2 and proc.stderr.startswith("dqskin: error: "), proc.stderr
    assert len(proc.stderr.splitlines()) == 1 and not any((tmp_path / "tmp").iterdir())


def _env():
    import os
    return dict(os.environ)


# -- no bare built-in error raised for bad input is left --------------------------------------

BARE = {"ValueError", "FileExistsError", "KeyError"}
ALLOWED: dict[tuple[str, str], str] = {
    # (file, exception name) → why a plain built-in is right there. None at present.
}


def test_no_bare_value_file_exists_or_key_error_is_raised():
    """Bad input raises an InputError (a ValueError), an existing output an OutputExistsError
    (a FileExistsError), an unknown name an UnknownNameError (a KeyError): a bare built-in that
    reaches the command line reads as a bug (exit 70)."""
    found = []
    for path in sorted([*ROOT.glob("dqskin/**/*.py"), *ROOT.glob("kernels/**/*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        for node in ast.walk(ast.parse(path.read_text(), rel)):
            if isinstance(node, ast.Raise):
                exc = node.exc
            elif isinstance(node, ast.Return) and isinstance(node.value, ast.Call):
                exc = node.value  # an error made for the caller to raise (a reader's error())
            else:
                continue
            target = exc.func if isinstance(exc, ast.Call) else exc
            if isinstance(target, ast.Name) and target.id in BARE \
                    and (rel, target.id) not in ALLOWED:
                found.append(f"{rel}:{node.lineno}: {target.id}")
    assert not found, "\n".join(found)
