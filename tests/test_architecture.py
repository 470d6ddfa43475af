"""Structure rules of the package, checked on the source: no import cycles between modules
(counting the package ``__init__`` each import runs), no ``wp.launch`` outside ``kernels/``
(launchers live beside their kernels), and small modules that import nothing heavy."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _modules():
    """Module name → file for ``dqskin`` (with ``kernels/`` as ``dqskin.kernels``)."""
    mods = {}
    roots = ((ROOT / "dqskin", ["dqskin"]), (ROOT / "kernels", ["dqskin", "kernels"]))
    for folder, prefix in roots:
        for path in folder.rglob("*.py"):
            parts = prefix + list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


def _runtime_nodes(node):
    """Every node under ``node`` but those in ``if TYPE_CHECKING:`` blocks (imports for
    annotations only, never executed)."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.If) and ast.unparse(child.test) in ("TYPE_CHECKING",
                                                                    "typing.TYPE_CHECKING"):
            yield from (n for part in child.orelse for n in [part, *_runtime_nodes(part)])
            continue
        yield child
        yield from _runtime_nodes(child)


def _ancestors(module):
    """``module`` and the packages above it: ``a.b.c`` → ``a``, ``a.b``, ``a.b.c``."""
    parts = module.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts) + 1)}


def _imports(name, path, mods):
    """Modules of the package that ``name`` imports (anywhere in the file, lazy imports too;
    not those in ``if TYPE_CHECKING:`` blocks, which never run).

    Importing ``a.b.c`` runs ``a/__init__`` and ``a/b/__init__`` first, so each import counts as
    one of every package it passes through, except the packages ``name`` is inside (those are
    already running when ``name`` runs); ``from a.b import c`` imports ``a.b`` and, when ``c`` is
    a module, ``a.b.c``.
    """
    out = set()
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in _runtime_nodes(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            out |= _ancestors(target)
            out.update(f"{target}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            for a in node.names:
                out |= _ancestors(a.name)
    inside = _ancestors(".".join(package)) if package else set()
    return {m for m in out if m in mods and m != name and m not in inside}


def _cycle(graph):
    """One import cycle as a list of modules, or None (depth-first search with colours)."""
    state, stack = {}, []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_import_scanner_skips_type_checking_imports(tmp_path):
    src = tmp_path / "m.py"
    src.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import a\n"
                   "else:\n    from . import b\n\ndef f():\n    from . import c\n")
    mods = {f"p.{x}": None for x in "abcm"}
    assert _imports("p.m", src, mods) == {"p.b", "p.c"}


def test_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles():
    mods = _modules()
    assert "dqskin.kernels.skin" in mods and "dqskin.readers.usd" in mods
    graph = {name: _imports(name, path, mods) for name, path in mods.items()}
    assert graph["dqskin.scene"], "the import scanner found nothing"
    cycle = _cycle(graph)
    assert cycle is None, " → ".join(cycle)


def test_imports_count_the_packages_they_pass_through(tmp_path):
    pkg = tmp_path / "p"
    (pkg / "q").mkdir(parents=True)
    files = {"__init__.py": "from . import a\n", "a.py": "import numpy\n",
             "b.py": "from .q.r import x\n", "c.py": "from .q import r\n",
             "q/__init__.py": "", "q/r.py": "from .. import b\n"}
    for rel, text in files.items():
        (pkg / rel).write_text(text, encoding="utf-8")
    mods = {"p": pkg / "__init__.py", "p.a": pkg / "a.py", "p.b": pkg / "b.py",
            "p.c": pkg / "c.py", "p.q": pkg / "q/__init__.py", "p.q.r": pkg / "q/r.py"}
    graph = {n: _imports(n, p, mods) for n, p in mods.items()}
    assert graph == {"p": {"p.a"}, "p.a": set(), "p.b": {"p.q", "p.q.r"},
                     "p.c": {"p.q", "p.q.r"}, "p.q": set(), "p.q.r": {"p.b"}}
    assert _cycle(graph) == ["p.b", "p.q.r", "p.b"]


def test_file_roles_import_one_way():
    """``dqskin.files`` (file machinery) imports no reader or writer; readers import no writer."""
    mods = _modules()
    graph = {name: _imports(name, path, mods) for name, path in mods.items()}
    banned = {"dqskin.files": ("dqskin.readers", "dqskin.writers"),
              "dqskin.readers": ("dqskin.writers",)}
    offenders = [f"{name} → {dep}" for name, deps in graph.items() for role, bad in banned.items()
                 if name.startswith(role) for dep in sorted(deps) if dep.startswith(bad)]
    assert graph["dqskin.writers.usd_cache"] & {"dqskin.files.atomic", "dqskin.readers.usd"}
    assert not offenders, offenders


HEAVY = ("warp", "pxr", "dask", "trimesh", "pygltflib")
LOADERS = ("dqskin.readers.", "dqskin.writers.", "dqskin.scene")
SMALL = ["dqskin", "dqskin.errors", "dqskin.files", "dqskin.files.atomic", "dqskin.files.direct",
         "dqskin.readers", "dqskin.writers", "dqskin.cache", "dqskin.options", "dqskin.spaces",
         "dqskin.progress"]


@pytest.mark.parametrize("module", SMALL)
def test_small_modules_import_nothing_heavy(module):
    """A fresh interpreter importing ``module`` loads no GPU, USD or Dask library and no loader
    or writer module."""
    code = (f"import sys, {module}\n"
            "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in "
            f"{HEAVY!r} or m.startswith({LOADERS!r}))))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == [], f"import {module} loads {out[:12]}"


def test_only_kernels_launch():
    offenders = [f"{p.relative_to(ROOT)}:{i}" for p in (ROOT / "dqskin").rglob("*.py")
                 for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
                 if "wp.launch(" in line]
    assert not offenders, offenders
    assert any("wp.launch(" in p.read_text(encoding="utf-8")
               for p in (ROOT / "kernels").glob("*.py"))
