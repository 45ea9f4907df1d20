"""The house rules of DESIGN.md, read from the source with ``ast``: the floors (agent < topology, dashboards
< flocktrack; no import goes up), no import circle between modules (imports inside functions included),
no private name imported across modules, no estimator named outside its own module."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

from agent.estimators.registry import fusion_specs, specs

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("agent", "topology", "dashboards", "flocktrack")
FLOOR = {"agent": 1, "topology": 2, "dashboards": 2, "flocktrack": 3}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}


def _type_checking_lines(tree: ast.AST) -> set[int]:
    """Lines under ``if TYPE_CHECKING:`` (annotations only, never executed)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in node.body:
                out.update(range(sub.lineno, (sub.end_lineno or sub.lineno) + 1))
    return out


def _imports(path: Path, module: str) -> Iterator[tuple[str, list[str], int]]:
    """(imported module, names taken from it, line) for every executed import in ``path``."""
    tree = ast.parse(path.read_text(), str(path))
    skip = _type_checking_lines(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if getattr(node, "lineno", 0) in skip:
            continue
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, [], node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            names = [a.name for a in node.names]
            subs = [n for n in names if f"{base}.{n}" in MODULES]
            for n in subs:
                yield f"{base}.{n}", [], node.lineno
            yield base, [n for n in names if n not in subs], node.lineno


def _graph() -> dict[str, set[str]]:
    g: dict[str, set[str]] = {m: set() for m in MODULES}
    for m, p in MODULES.items():
        for target, _names, _line in _imports(p, m):
            if target in MODULES and target != m:
                g[m].add(target)
    return g


def test_no_import_goes_up_a_floor():
    bad = []
    for m, p in MODULES.items():
        for target, _names, line in _imports(p, m):
            top, ttop = m.split(".")[0], target.split(".")[0]
            if ttop in FLOOR and ttop != top and (FLOOR[ttop] >= FLOOR[top]):
                bad.append(f"{p.relative_to(ROOT)}:{line} imports {target} (floor {FLOOR[ttop]} ≥ {FLOOR[top]})")
    assert not bad, "\n".join(bad)


def _cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
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

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_between_modules():
    g = _graph()
    # a package's __init__ is imported with every module under it: an edge into one's own package's
    # __init__ is not a circle of its own
    for m in g:
        g[m] = {t for t in g[m] if not m.startswith(t + ".")}
    assert _cycles(g) == []


def test_no_private_name_is_imported_across_modules():
    importers = dict(MODULES)
    importers.update({f"tests.{p.stem}": p for p in (ROOT / "tests").rglob("*.py")})
    importers.update({f"bench.{p.stem}": p for p in (ROOT / "bench").glob("*.py")})
    bad = []
    for m, p in importers.items():
        for target, names, line in _imports(p, m):
            if target in MODULES and target != m:
                bad += [f"{p.relative_to(ROOT)}:{line} from {target} import {n}" for n in names
                        if n.startswith("_") and not n.startswith("__")]
    assert not bad, "\n".join(bad)


def test_no_estimator_is_named_outside_its_own_module():
    """The registry, the scenario loader, the CLI, the design and the metrics read the specs: no other
    module of the runtime names an estimator (as a string, or by importing its module)."""
    every = [*specs().values(), *fusion_specs().values()]     # the flock's estimators and the fusion role's
    names = {s.name for s in every}
    own = {Path(__import__(s.build.__module__, fromlist=["x"]).__file__).resolve() for s in every}
    est_modules = {s.build.__module__ for s in every}
    bad = []
    for m, p in MODULES.items():
        if p.resolve() in own or m.startswith("agent.estimators."):
            continue
        tree = ast.parse(p.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and node.value in names:
                bad.append(f"{p.relative_to(ROOT)}:{node.lineno} names {node.value!r}")
        for target, _names, line in _imports(p, m):
            if target in est_modules:
                bad.append(f"{p.relative_to(ROOT)}:{line} imports {target}")
    assert not bad, "\n".join(bad)


def test_every_estimator_module_is_found_by_the_registry():
    """A module that declares a spec is registered under the spec's name (and only once)."""
    for name, spec in specs().items():
        assert spec.name == name
        assert spec.build.__module__.startswith("agent.estimators.")


def test_bench_imports_nothing_from_tests():
    """A benchmark runs the product, not the test suite: nothing under bench/ imports a test module or
    puts tests/ on its path."""
    for p in (ROOT / "bench").glob("*.py"):
        text = p.read_text()
        assert not re.search(r"/\s*[\"']tests[\"']", text), f"{p.name} puts tests/ on its path"
        tests = {q.stem for q in (ROOT / "tests").rglob("*.py")}
        for target, _names, line in _imports(p, f"bench.{p.stem}"):
            assert target.split(".")[0] not in tests, f"{p.name}:{line} imports {target} from tests/"


def test_tests_are_grouped_by_layer():
    """Every test module lives in a layer's folder; tests/ itself holds only the project-wide checks and
    the shared helpers."""
    top = {p.name for p in (ROOT / "tests").glob("test_*.py")}
    assert top <= {"test_layers.py", "test_lint.py", "test_readme.py"}, top
    for layer in ("unit", "runtime", "deploy", "browser"):
        assert list((ROOT / "tests" / layer).glob("test_*.py")), layer


#: the runtime and its plumbing: thin signatures (the numerical core keeps the papers' matrix arguments)
PLUMBING = ["flocktrack", "dashboards", "topology", "agent/roles", "agent/runner.py", "agent/bus.py", "agent/inbox.py",
            "agent/link_emulation.py"]


def test_the_runtime_takes_at_most_five_positional_parameters_and_no_class_is_over_400_lines():
    bad = []
    for place in PLUMBING:
        root = ROOT / place
        for p in ([root] if root.is_file() else sorted(root.rglob("*.py"))):
            for node in ast.walk(ast.parse(p.read_text(), str(p))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    pos = [a.arg for a in node.args.posonlyargs + node.args.args if a.arg not in ("self", "cls")]
                    if len(pos) > 5:
                        bad.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name}() takes {len(pos)} positional "
                                   f"parameters (keyword-only for the rest, or one options object)")
                elif isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 400:
                    bad.append(f"{p.relative_to(ROOT)}:{node.lineno} class {node.name} is "
                               f"{node.end_lineno - node.lineno + 1} lines")
    assert not bad, "\n".join(bad)
