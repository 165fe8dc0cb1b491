"""The package's import graph, read from the source with ``ast``: no cycles, and the engine on top.

Every ``import`` and ``from ... import`` statement counts, at module level or inside a function:
a function-level import only postpones a cycle to the first call, where a half-initialised
module then fails with an AttributeError or ImportError far from its cause. Edges to the
importing module's own ancestor packages are left out: Python imports those before the module
itself, whatever it says, and a package ``__init__`` re-exporting its submodules would otherwise
close a cycle with each of them. Imports of computed names (``importlib.import_module(name)``)
cannot be read from the source and are not counted.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

import rtctl

PACKAGE_DIR = Path(rtctl.__file__).parent

#: The engine composes everything else; only the command line may import it.
ENGINE = "rtctl.engine"
ENGINE_IMPORTERS = {"rtctl.cli", "rtctl.__main__"}


def module_files(package_dir: Path, package: str) -> dict[str, Path]:
    """Dotted module name -> source file, for every ``.py`` file under ``package_dir``."""
    out = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = [package, *path.relative_to(package_dir).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _known(name: str, modules) -> str | None:
    """The longest prefix of ``name`` that is a module of the graph (``pkg.mod.Class`` ->
    ``pkg.mod``), or None when ``name`` lies outside it."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, modules) -> dict[str, int]:
    """Modules of the graph that module ``name`` imports -> line of the first such import.

    ``import a.b.c`` and ``from a.b import c`` import ``a`` and ``a.b`` too (Python runs each
    package's ``__init__`` on the way), and ``c`` when it is a module.
    """
    is_package = path.name == "__init__.py"
    here = name if is_package else name.rpartition(".")[0]
    own_ancestors = set(_ancestors(name))
    found: dict[str, int] = {}

    def add(target: str, line: int):
        for m in [*_ancestors(target), target]:
            k = _known(m, modules)
            if k and k != name and k not in own_ancestors:
                found.setdefault(k, line)

    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = here.split(".")
                if node.level - 1 >= len(parts):
                    raise ValueError(f"{path}:{node.lineno}: relative import beyond the top package")
                base = ".".join(parts[:len(parts) - (node.level - 1)])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module
            add(base, node.lineno)
            for alias in node.names:
                if f"{base}.{alias.name}" in modules:
                    add(f"{base}.{alias.name}", node.lineno)
    return found


def import_graph(package_dir: Path, package: str) -> dict[str, dict[str, int]]:
    """Module -> {imported module of the same package -> line}."""
    modules = module_files(package_dir, package)
    return {m: imports_of(m, p, modules) for m, p in modules.items()}


def cycles(graph) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    for root in sorted(graph):
        if root in index:
            continue
        # iterative depth-first search: (node, iterator over its successors)
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        work = [(root, iter(sorted(graph[root])))]
        while work:
            v, succ = work[-1]
            w = next(succ, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return sorted(out)


def describe(graph, comp) -> str:
    """One cycle and the imports that close it, ``a:line -> b``."""
    inside = set(comp)
    edges = [f"    {a}:{line} -> {b}" for a in comp for b, line in sorted(graph[a].items()) if b in inside]
    return " <-> ".join(comp) + "\n" + "\n".join(edges)


def in_engine(name: str) -> bool:
    return name == ENGINE or name.startswith(ENGINE + ".")


def engine_importers(graph) -> list[str]:
    """Imports of the engine from outside it (``module:line -> engine module``), the command
    line excepted."""
    return sorted(f"{m}:{line} -> {t}" for m, targets in graph.items()
                  if not in_engine(m) and m not in ENGINE_IMPORTERS
                  for t, line in targets.items() if in_engine(t))


# -- the reader itself, on a package written for the purpose -----------------------------------


def _write(root: Path, files: dict):
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text))


def test_reader_resolves_every_import_form_and_finds_the_cycle(tmp_path):
    pkg = tmp_path / "pkg"
    _write(pkg, {
        "__init__.py": "from pkg.sub import leaf  # a package re-exporting its submodule\n",
        "a.py": "import os\nfrom . import b\n",
        "b.py": "def f():\n    from .c import thing\n    return thing\n",
        "c.py": "import pkg.a as again\nthing = 1\n",
        "sub/__init__.py": "",
        "sub/leaf.py": "from ..a import f\nfrom .. import c\nfrom pkg import sub\n",
        "sub/deep.py": "from . import leaf\nfrom .leaf import f\nimport json, pkg.c\n",
    })
    g = import_graph(pkg, "pkg")
    assert set(g) == {"pkg", "pkg.a", "pkg.b", "pkg.c", "pkg.sub", "pkg.sub.leaf", "pkg.sub.deep"}
    assert g["pkg"] == {"pkg.sub": 1, "pkg.sub.leaf": 1}
    assert g["pkg.a"] == {"pkg.b": 2}                     # `from . import b`; os is not ours
    assert g["pkg.b"] == {"pkg.c": 2}                     # function-level, relative
    assert g["pkg.c"] == {"pkg.a": 1}
    # `from ..a import f` -> pkg.a (f is a name in it); `from .. import c` -> pkg.c;
    # `from pkg import sub` names leaf's own package: left out
    assert g["pkg.sub.leaf"] == {"pkg.a": 1, "pkg.c": 2}
    assert g["pkg.sub.deep"] == {"pkg.sub.leaf": 1, "pkg.c": 3}
    assert cycles(g) == [["pkg.a", "pkg.b", "pkg.c"]]
    assert "pkg.b:2 -> pkg.c" in describe(g, cycles(g)[0])


def test_reader_counts_the_packages_on_the_way_and_rejects_too_many_dots(tmp_path):
    pkg = tmp_path / "pkg"
    _write(pkg, {
        "__init__.py": "",
        "x/__init__.py": "from pkg.y.z import thing\n",   # runs y/__init__ before y.z
        "y/__init__.py": "import pkg.x\n",
        "y/z.py": "thing = 1\n",
    })
    g = import_graph(pkg, "pkg")
    assert g["pkg.x"] == {"pkg.y": 1, "pkg.y.z": 1}
    assert g["pkg.y"] == {"pkg.x": 1}
    assert g["pkg.y.z"] == {}
    assert cycles(g) == [["pkg.x", "pkg.y"]]
    (pkg / "bad.py").write_text("from ... import q\n")
    with pytest.raises(ValueError, match="beyond the top package"):
        import_graph(pkg, "pkg")


def test_cycles_of_a_graph_without_and_with_loops():
    assert cycles({"a": {"b": 1}, "b": {"c": 1}, "c": {}}) == []
    g = {"a": {"b": 1}, "b": {"a": 1, "c": 1}, "c": {"d": 1}, "d": {"c": 1, "e": 1}, "e": {}}
    assert cycles(g) == [["a", "b"], ["c", "d"]]


def test_engine_rule_on_a_graph():
    # the engine imports anything, the command line imports it, a name merely starting with
    # "rtctl.engine" is not it; rtctl.io.sim importing an engine module is the one breach
    g = {"rtctl.cli": {"rtctl.engine.run": 3}, "rtctl.engine.run": {"rtctl.engine": 1, "rtctl.dsp": 2},
         "rtctl.engine": {}, "rtctl.dsp": {"rtctl.engineering": 4}, "rtctl.engineering": {},
         "rtctl.io.sim": {"rtctl.engine.stage": 7}, "rtctl.engine.stage": {}}
    assert engine_importers(g) == ["rtctl.io.sim:7 -> rtctl.engine.stage"]


# -- the package -------------------------------------------------------------------------------


def test_no_import_cycles_in_rtctl():
    g = import_graph(PACKAGE_DIR, "rtctl")
    assert len(g) > 50 and "rtctl.render.hia" in g    # the reader saw the package
    found = cycles(g)
    text = "\n".join(describe(g, c) for c in found)
    print(text)
    assert not found, f"import cycles among rtctl modules:\n{text}"


def test_only_the_command_line_imports_the_engine():
    g = import_graph(PACKAGE_DIR, "rtctl")
    assert ENGINE in g
    bad = engine_importers(g)
    print("\n".join(bad))
    assert not bad, "modules outside rtctl.engine that import it:\n" + "\n".join(bad)
