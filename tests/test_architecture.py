"""Structure rules of the package, checked on the source: no import cycles between modules, and no
``wp.launch`` outside ``kernels/`` (launchers live beside their kernels)."""

import ast
from pathlib import Path

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


def _imports(name, path, mods):
    """Modules of the package that ``name`` imports when it runs (anywhere in the file, lazy
    imports too; not those for type annotations only)."""
    out = set()
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in _runtime_nodes(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in mods]
            out.update(subs if len(subs) == len(node.names) else subs + [target])
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return {m for m in out if m in mods and m != name}


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
    assert "dqskin.kernels.skin" in mods and "dqskin.formats.usd" in mods
    graph = {name: _imports(name, path, mods) for name, path in mods.items()}
    assert graph["dqskin.scene"], "the import scanner found nothing"
    cycle = _cycle(graph)
    assert cycle is None, " → ".join(cycle)


def test_only_kernels_launch():
    offenders = [f"{p.relative_to(ROOT)}:{i}" for p in (ROOT / "dqskin").rglob("*.py")
                 for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
                 if "wp.launch(" in line]
    assert not offenders, offenders
    assert any("wp.launch(" in p.read_text(encoding="utf-8")
               for p in (ROOT / "kernels").glob("*.py"))
