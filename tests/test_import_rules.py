"""The project's layout rules, checked on the source (no imports run):

- layers: a package imports only the packages below it (``scenefmt`` <- ``assets_procedural``
  <- ``generators``; ``scenefmt`` <- ``svorf``; the libraries <- ``benchmark.tools``, the
  measuring and experiment tools, which import no other ``benchmark`` module; everything <-
  the rest of ``benchmark``), the format, asset and generator packages import no torch, and
  only the Blender backend imports bpy;
- no private name (``_x``) of one module is used by another;
- no import cycle between modules (imports inside functions count too);
- no module over :data:`MAX_LINES` lines.

Every finding is printed with the module and the name, so a failure says what to move.
"""

from __future__ import annotations

import ast
import functools
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The libraries: the format, the assets, the generator and the model.
LIBRARIES = frozenset({"scenefmt", "assets_procedural", "generators", "svorf"})
#: Layer (a package, or a subpackage that is a layer of its own) -> the layers it may import
#: (besides itself). A module belongs to the longest layer name that prefixes it.
ALLOWED: dict[str, frozenset[str]] = {
    "scenefmt": frozenset(),
    "assets_procedural": frozenset({"scenefmt"}),
    "generators": frozenset({"scenefmt", "assets_procedural"}),
    "svorf": frozenset({"scenefmt"}),
    # the measuring and experiment tools (speedbench, the recipe, the generator baselines):
    # on top of the libraries, beside the benchmark; no library imports them
    "benchmark.tools": LIBRARIES,
    "benchmark": LIBRARIES | {"benchmark.tools"},
}
#: The top-level packages that are scanned.
PACKAGES = tuple(dict.fromkeys(layer.split(".")[0] for layer in ALLOWED))
#: Packages that must not import torch (they run where torch is not installed).
NO_TORCH = frozenset({"scenefmt", "assets_procedural", "generators"})
#: The only modules that may import Blender's Python modules.
BLENDER_MODULES = frozenset({"generators.blender_backend"})
BLENDER_TOPS = frozenset({"bpy", "mathutils", "bmesh"})
MAX_LINES = 800


@dataclass
class Findings:
    """What :func:`scan` found in one source tree."""

    modules: dict[str, Path]
    edges: dict[str, set[str]] = field(default_factory=lambda: defaultdict(set))
    layering: list[str] = field(default_factory=list)
    private: list[str] = field(default_factory=list)
    long: list[str] = field(default_factory=list)

    def cycles(self) -> list[list[str]]:
        """Strongly connected components of more than one module (Tarjan), except a
        package's ``__init__`` with its own submodules (a re-export, not a design cycle)."""
        index: dict[str, int] = {}
        low: dict[str, int] = {}
        stack: list[str] = []
        on: set[str] = set()
        out: list[list[str]] = []

        def visit(v: str) -> None:
            index[v] = low[v] = len(index)
            stack.append(v)
            on.add(v)
            for w in sorted(self.edges.get(v, ())):
                if w not in index:
                    visit(w)
                    low[v] = min(low[v], low[w])
                elif w in on:
                    low[v] = min(low[v], index[w])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))

        for v in sorted(self.modules):
            if v not in index:
                visit(v)
        return [c for c in out if not _init_reexport(c, self.modules)]


def _init_reexport(comp: list[str], modules: dict[str, Path]) -> bool:
    one_package = len({m.split(".")[0] for m in comp}) == 1
    return one_package and any(modules[m].name == "__init__.py" for m in comp)


def _module_files(root: Path) -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            name = ".".join(path.relative_to(root).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = path
    return mods


def _layer(name: str) -> str | None:
    """The layer of :data:`ALLOWED` a dotted module name lies in (longest prefix), or None."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        if ".".join(parts[:i]) in ALLOWED:
            return ".".join(parts[:i])
    return None


def _owner(name: str, modules: dict[str, Path]) -> str | None:
    """The project module a dotted name lies in (longest prefix), or None."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        if ".".join(parts[:i]) in modules:
            return ".".join(parts[:i])
    return None


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _dotted(node: ast.expr) -> str | None:
    """``a.b.c`` of an attribute chain on a name, else None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([node.id, *reversed(parts)])


def _resolve(module: str, path: Path, level: int, target: str | None) -> str:
    """The absolute module of ``from <level dots><target> import ...`` in ``module``."""
    if level == 0:
        return target or ""
    base = module.split(".")
    if path.name != "__init__.py":
        base = base[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


def scan(root: Path) -> Findings:
    """Read every module of the project packages under ``root`` and collect the findings."""
    mods = _module_files(root)
    f = Findings(mods)
    for mod, path in mods.items():
        src = path.read_text(encoding="utf-8")
        n_lines = src.count("\n")
        if n_lines > MAX_LINES:
            f.long.append(f"{path.relative_to(root)}: {n_lines} lines")
        pkg = mod.split(".")[0]
        own_layer = _layer(mod)
        assert own_layer is not None, mod
        aliases: dict[str, str] = {}  # local name -> the project module it is bound to
        imported: list[tuple[str, str | None, int]] = []  # (module, name or None, line)
        tree = ast.parse(src, filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    imported.append((a.name, None, node.lineno))
                    if a.asname and a.name in mods:
                        aliases[a.asname] = a.name
                    elif not a.asname and a.name.split(".")[0] in mods:
                        top = a.name.split(".")[0]
                        aliases[top] = top
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(mod, path, node.level, node.module)
                for a in node.names:
                    full = f"{base}.{a.name}" if base else a.name
                    if full in mods:  # a submodule
                        imported.append((full, None, node.lineno))
                        aliases[a.asname or a.name] = full
                    else:
                        imported.append((base, a.name, node.lineno))
        where = f"{path.relative_to(root)}"
        for name, what, line in imported:
            top = name.split(".")[0]
            layer = _layer(name)
            if layer is not None and layer != own_layer and layer not in ALLOWED[own_layer]:
                f.layering.append(f"{where}:{line}: {own_layer} may not import {name}")
            if top == "torch" and pkg in NO_TORCH:
                f.layering.append(f"{where}:{line}: {pkg} may not import torch")
            if top in BLENDER_TOPS and mod not in BLENDER_MODULES:
                f.layering.append(f"{where}:{line}: only {sorted(BLENDER_MODULES)} import {top}")
            owner = _owner(name, mods)
            if owner is None or owner == mod:
                continue
            f.edges[mod].add(owner)
            if what is not None and _private(what):
                f.private.append(f"{where}:{line}: imports {owner}.{what}")
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute) or not _private(node.attr):
                continue
            chain = _dotted(node.value)
            if chain is None:
                continue
            head, _, rest = chain.partition(".")
            if head not in aliases:
                continue
            target = aliases[head] + ("." + rest if rest else "")
            owner = _owner(target, mods)
            if owner is not None and owner == target and owner != mod:
                f.private.append(f"{where}:{node.lineno}: uses {owner}.{node.attr}")
    f.private = sorted(set(f.private))
    return f


@functools.cache
def _project() -> Findings:
    return scan(ROOT)


def test_no_import_from_a_higher_layer():
    assert _project().layering == [], "\n".join(_project().layering)


def test_no_private_name_used_across_modules():
    assert _project().private == [], "\n".join(_project().private)


def test_no_import_cycles():
    cycles = _project().cycles()
    assert cycles == [], "\n".join(" <-> ".join(c) for c in cycles)


def test_no_module_over_the_line_limit():
    assert _project().long == [], "\n".join(_project().long)


def test_every_tool_has_a_row_in_the_layout_doc():
    """docs/layout.md's benchmark.tools table names every tool module (a new tool is found)."""
    section = (ROOT / "docs" / "layout.md").read_text().split("## benchmark.tools", 1)[1]
    tools = sorted((ROOT / "benchmark" / "tools").glob("*.py"))
    missing = [
        p.name for p in tools if p.name != "__init__.py" and f"| `{p.name}` |" not in section
    ]
    assert len(tools) > 5 and missing == [], f"add a row to docs/layout.md for: {missing}"


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


@pytest.mark.parametrize(
    ("files", "kind", "expected"),
    [
        ({"scenefmt/a.py": "import svorf.b\n", "svorf/b.py": ""}, "layering", "svorf.b"),
        ({"generators/a.py": "def f():\n    import torch\n"}, "layering", "torch"),
        ({"svorf/a.py": "import bpy\n"}, "layering", "bpy"),
        (
            {"svorf/a.py": "from benchmark.tools import t\n", "benchmark/tools/t.py": ""},
            "layering",
            "svorf may not import benchmark.tools.t",
        ),
        (
            {"benchmark/tools/t.py": "import benchmark.b\n", "benchmark/b.py": ""},
            "layering",
            "benchmark.tools may not import benchmark.b",
        ),
        (
            {"svorf/a.py": "from svorf.b import _hidden\n", "svorf/b.py": "_hidden = 1\n"},
            "private",
            "svorf.b._hidden",
        ),
        (
            {"svorf/a.py": "from svorf import b\nb._hidden()\n", "svorf/b.py": ""},
            "private",
            "svorf.b._hidden",
        ),
        (
            {"svorf/a.py": "import svorf.b\nsvorf.b._x\n", "svorf/b.py": ""},
            "private",
            "svorf.b._x",
        ),
        (
            {
                "svorf/a.py": "from . import b\n",
                "svorf/b.py": "def f():\n    from svorf import a\n",
            },
            "cycles",
            "svorf.a <-> svorf.b",
        ),
    ],
)
def test_the_checks_find_each_kind_of_problem(tmp_path, files, kind, expected):
    """The checker itself, on tiny made-up trees with one problem each."""
    _write(tmp_path, {"svorf/__init__.py": "", "scenefmt/__init__.py": "", **files})
    found = scan(tmp_path)
    got = [" <-> ".join(c) for c in found.cycles()] if kind == "cycles" else getattr(found, kind)
    assert any(expected in g for g in got), got
    others = {"layering", "private", "cycles"} - {kind}
    for other in others:
        rest = found.cycles() if other == "cycles" else getattr(found, other)
        assert rest == [], (other, rest)


def test_a_package_init_reexporting_its_modules_is_not_a_cycle(tmp_path):
    _write(
        tmp_path,
        {
            "svorf/__init__.py": "from svorf.a import f\n",
            "svorf/a.py": "from svorf import b\ndef f():\n    return b\n",
            "svorf/b.py": "import svorf\n",
        },
    )
    assert scan(tmp_path).cycles() == []


def test_the_benchmark_may_import_its_tools(tmp_path):
    _write(
        tmp_path,
        {
            "svorf/__init__.py": "",
            "benchmark/tools/t.py": "import svorf\n",
            "benchmark/p.py": "from benchmark.tools import t\nimport svorf\n",
        },
    )
    assert scan(tmp_path).layering == []
