"""Count dqskin's public functions and how many are fully annotated.

Public: every function reachable from ``dqskin.__all__`` and from the ``__all__`` of each public
module (no name part starting with ``_``; a module without ``__all__`` contributes the public
functions and classes it defines), and the public methods (plus ``__init__`` and ``__call__``)
of every public class, properties included. Fully annotated: every parameter but a method's
``self``/``cls`` has an annotation, and so does the return (``__init__`` excepted). Each
function counts once, under the module that defines it.

Warp kernels and functions (``@wp.kernel``, ``@wp.func``: ``warp`` ``Kernel`` and ``Function``
objects, counted by the Python function they wrap) count as fully annotated when every
parameter carries a type (the Warp type Warp's code generator requires); their return is
exempt, as ``__init__``'s is: a kernel returns nothing, and a Warp function's return type is
the one Warp infers from its body, not a Python return a caller could annotate against.

Also printed: every function of ``dqskin/`` (private ones included, ``kernels/`` counted apart)
that takes ten or more parameters (``self``/``cls`` not counted, ``*args``/``**kwargs`` one
each), read from the source with :mod:`ast`.

Usage: ``python tools/api_metrics.py [ROOT] [--list]`` where ROOT is a source tree holding
``dqskin/`` and ``kernels/`` (default: this checkout). The tree is imported in a subprocess of
its own, ``dqskin.kernels`` mapped to ``ROOT/kernels`` as the installed package does.
"""

import argparse
import importlib.abc
import importlib.machinery
import importlib.util
import inspect
import json
import os
import pkgutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path


class _TreeFinder(importlib.abc.MetaPathFinder):
    """Import ``dqskin`` from ``root/dqskin`` and ``dqskin.kernels`` from ``root/kernels``."""

    def __init__(self, root):
        self.places = {"dqskin": root / "dqskin", "dqskin.kernels": root / "kernels"}

    def find_spec(self, name, path=None, target=None):
        folder = self.places.get(name)
        if folder is None:
            return None
        return importlib.util.spec_from_file_location(
            name, folder / "__init__.py", submodule_search_locations=[str(folder)])


def _public(name):
    return not name.startswith("_")


def _fully_annotated(fn, bound, warp=False):
    """True when every parameter (but a bound first one) and the return (not for ``warp``: a
    Warp kernel or function) are annotated."""
    fn = inspect.unwrap(fn)
    try:
        sig = inspect.signature(fn, follow_wrapped=False, eval_str=False)
    except (TypeError, ValueError):
        return False
    params = list(sig.parameters.values())[1 if bound else 0:]
    if any(p.annotation is inspect.Parameter.empty for p in params):
        return False
    return (warp or fn.__name__ == "__init__"
            or sig.return_annotation is not inspect.Signature.empty)


def _collect(root):
    """{function qualname: (module, annotated)} of the public API of the tree at ``root``."""
    sys.meta_path.insert(0, _TreeFinder(root))
    import dqskin

    found = {}
    tree = str(root.resolve())

    def ours(fn):
        code = getattr(inspect.unwrap(fn), "__code__", None)  # (generated code: "<string>")
        return (code is not None and os.path.isabs(code.co_filename)
                and str(Path(code.co_filename).resolve()).startswith(tree))

    def add(fn, bound):
        if ours(fn):
            fn0 = inspect.unwrap(fn)
            warp = type(fn).__module__.split(".")[0] == "warp"  # a wp.Kernel or wp.Function
            found[f"{fn0.__module__}.{fn0.__qualname__}"] = (fn0.__module__,
                                                            _fully_annotated(fn0, bound, warp))

    def add_class(cls):
        for name, member in vars(cls).items():
            if not (_public(name) or name in ("__init__", "__call__")):
                continue
            if isinstance(member, staticmethod):
                add(member.__func__, False)
            elif isinstance(member, classmethod):
                add(member.__func__, True)
            elif isinstance(member, property):
                for accessor in (member.fget, member.fset):
                    if accessor is not None:
                        add(accessor, True)
            elif inspect.isfunction(member):
                add(member, True)

    def add_object(obj):
        if inspect.isclass(obj):
            if obj.__module__.startswith("dqskin"):
                add_class(obj)
        elif inspect.isfunction(obj) or callable(getattr(obj, "__wrapped__", None)):
            add(obj, False)

    modules = [dqskin] + [importlib.import_module(info.name) for info in
                          pkgutil.walk_packages(dqskin.__path__, "dqskin.")
                          if all(_public(part) for part in info.name.split("."))]
    if "dqskin.kernels" not in {m.__name__ for m in modules}:
        kernels = importlib.import_module("dqskin.kernels")
        modules += [kernels] + [importlib.import_module(info.name) for info in
                                pkgutil.walk_packages(kernels.__path__, "dqskin.kernels.")
                                if all(_public(p) for p in info.name.split("."))]
    for module in modules:
        names = getattr(module, "__all__", None)
        if names is None:
            names = [n for n, v in vars(module).items() if _public(n)
                     and getattr(v, "__module__", None) == module.__name__]
        for name in names:
            add_object(getattr(module, name))
    return found


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", nargs="?", type=Path, default=Path(__file__).parents[1])
    parser.add_argument("--list", action="store_true", help="list the functions not annotated")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    root = args.root.resolve()
    if args.json:
        json.dump(_collect(root), sys.stdout)
        return
    out = subprocess.run([sys.executable, __file__, str(root), "--json"], check=True,
                         capture_output=True, text=True).stdout
    found = json.loads(out)
    per_module = defaultdict(lambda: [0, 0])
    for module, annotated in found.values():
        per_module[module][0] += annotated
        per_module[module][1] += 1
    for module, (a, n) in sorted(per_module.items()):
        print(f"{module:32s} {a:4d}/{n:<4d}")
    groups = (("dqskin/ (kernels/ excluded)", lambda m: not m.startswith("dqskin.kernels")),
              ("dqskin.kernels", lambda m: m.startswith("dqskin.kernels")),
              ("total", lambda m: True))
    for label, keep in groups:
        done = sum(a for m, (a, _) in per_module.items() if keep(m))
        total = sum(n for m, (_, n) in per_module.items() if keep(m))
        print(f"{label:32s} {done:4d}/{total:<4d} fully annotated "
              f"({100 * done / max(total, 1):.0f}%)")
    if args.list:
        for name, (_, annotated) in sorted(found.items()):
            if not annotated:
                print("  not annotated:", name)
    long = _long_parameter_lists(root)
    for folder in ("dqskin", "kernels"):
        rows = [(n, where) for n, where in long if where.startswith(folder + "/")]
        print(f"functions in {folder}/ with >= {LONG} parameters: {len(rows)}")
        for n, where in rows:
            print(f"  {n:3d}  {where}")


LONG = 10
"""A parameter list this long or longer is counted."""


def _long_parameter_lists(root: Path) -> list[tuple[int, str]]:
    """``(parameter count, "path:function")`` of every function with at least :data:`LONG`
    parameters under ``root/dqskin`` and ``root/kernels``, longest first."""
    import ast
    rows = []
    for path in sorted([*(root / "dqskin").rglob("*.py"), *(root / "kernels").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs)
                         if x.arg not in ("self", "cls")]
                count = len(names) + (a.vararg is not None) + (a.kwarg is not None)
                if count >= LONG:
                    rows.append((count, f"{path.relative_to(root)}:{node.name}"))
    return sorted(rows, key=lambda r: (-r[0], r[1]))


if __name__ == "__main__":
    main()
