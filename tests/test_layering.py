"""The package's import layering, read from the source (every ``import``, module-level or inside a function):

- floors: physics -> data_modules -> models -> training -> callbacks -> front ends (cli, inference, experiments,
  reporting, evaluation). A module imports its own floor, lower floors and the shared root helpers, never a higher
  floor; the shared helpers (registry, config, atomic, paths, output_guard, run_lock, wandb_env, lazy, visualize,
  allocator) import only each other.
- the scan package (``models/scan/``): one dispatcher (``dispatch.py``). The kernel modules (common, reference,
  cpu, triton, mamba) never import it, nor the package's ``__init__`` that re-exports it, nor anything of
  ``models`` outside the scan package; ``common`` imports nothing of the package.
- no module imports another that (directly or not) imports it back: the import graph of ``tofdenoise`` has no
  cycle (``KNOWN_CYCLES`` is empty since the stand-in real set's steps moved to ``data_modules.realset``; a new
  cycle fails).

Stdlib only (``ast``), so it runs wherever the tests run.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = "tofdenoise"

FRONT_ENDS = ("cli", "inference", "experiments", "reporting", "evaluation")
FLOORS = {
    "physics": 0,
    "data_modules": 1,
    "models": 2,
    "training": 3,
    "callbacks": 4,
    **dict.fromkeys(FRONT_ENDS, 5),
}
SHARED = {
    "records",
    "registry",
    "config",
    "atomic",
    "paths",
    "output_guard",
    "run_lock",
    "wandb_env",
    "lazy",
    "visualize",
    "allocator",
}
SCAN = f"{PACKAGE}.models.scan"
SCAN_DISPATCHER = {SCAN, f"{SCAN}.dispatch"}
#: cycles older than this test (none left: the last, cli.sensor <-> cli.sensor_captures, went with issue 24 point 3)
KNOWN_CYCLES: list[list[str]] = []


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted((SRC / PACKAGE).rglob("*.py")):
        parts = path.relative_to(SRC).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """The ``tofdenoise`` modules ``name`` imports (``from pkg import sub`` counts as ``pkg.sub``)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            subs = [f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in MODULES]
            found.update(subs or [target])
    return {t for t in found if t == PACKAGE or t.startswith(PACKAGE + ".")}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _part(module: str) -> str:
    """The top-level part of the package a module belongs to (``models`` for ``tofdenoise.models.scan.cpu``)."""
    return module.split(".")[1] if module != PACKAGE else ""


def _floor(module: str) -> int | None:
    part = _part(module)
    if part in SHARED:
        return -1
    return FLOORS.get(part)


def test_every_part_of_the_package_has_a_floor():
    parts = {_part(m) for m in MODULES} - {""}
    assert parts - set(FLOORS) - SHARED == set(), "give a new top-level module or package a floor in this test"


def test_no_floor_imports_a_higher_floor():
    bad = []
    for module, targets in GRAPH.items():
        if module == PACKAGE:
            continue  # the package root's lazy ``tofdenoise.denoise``
        floor = _floor(module)
        for target in targets:
            target_floor = _floor(target)
            if target == PACKAGE or target_floor is None:
                continue
            if floor == -1 and target_floor != -1:
                bad.append(f"{module} (shared helper) imports {target} (floor {_part(target)})")
            elif floor != -1 and target_floor > floor:
                bad.append(f"{module} (floor {_part(module)}) imports {target} (higher floor {_part(target)})")
    assert not bad, "\n".join(sorted(bad))


def test_only_the_command_line_imports_the_command_line():
    """``cli/`` is the top: the library (experiments, inference, reporting, ...) never imports a verb's package, so
    every workflow runs without the command line (issue 24, points 3 and 4)."""
    cli = f"{PACKAGE}.cli"
    bad = [
        f"{module} imports {target}"
        for module, targets in GRAPH.items()
        if _part(module) != "cli"
        for target in targets
        if target == cli or target.startswith(cli + ".")
    ]
    assert not bad, "\n".join(sorted(bad))


def test_scan_kernels_never_import_the_dispatcher():
    kernels = [m for m in MODULES if m.startswith(SCAN + ".") and m not in SCAN_DISPATCHER]
    assert {m.rpartition(".")[2] for m in kernels} >= {"common", "reference", "cpu", "triton", "mamba"}
    bad = []
    for module in kernels:
        for target in GRAPH[module]:
            if target in SCAN_DISPATCHER:
                bad.append(f"{module} imports the dispatcher {target}")
            elif target.startswith(f"{PACKAGE}.models") and not target.startswith(SCAN + "."):
                bad.append(f"{module} imports {target} (outside the scan package)")
    common_imports = {t for t in GRAPH[f"{SCAN}.common"] if t.startswith(SCAN)}
    assert not common_imports, f"scan.common imports {common_imports}"
    assert not bad, "\n".join(sorted(bad))


def test_only_ss2d_and_the_package_use_the_scan_dispatcher():
    users = {m for m, targets in GRAPH.items() if targets & SCAN_DISPATCHER} - SCAN_DISPATCHER
    assert users <= {f"{PACKAGE}.models", f"{PACKAGE}.models.ss2d"}, users


def _cycles() -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), package root left out."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH.get(v, ()):
            if w == PACKAGE or w not in GRAPH:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
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

    for v in GRAPH:
        if v != PACKAGE and v not in index:
            visit(v)
    return out


def test_no_new_import_cycle():
    assert [c for c in _cycles() if c not in KNOWN_CYCLES] == []


def test_the_checks_see_imports_inside_functions(tmp_path):
    """The reader counts a function-level relative import (how the old scan modules imported each other back)."""
    path = tmp_path / "mod.py"
    path.write_text("def f():\n    from .dispatch import selective_scan\n    from . import cpu\n")
    assert _imports(f"{SCAN}.reference", path) == {f"{SCAN}.dispatch", f"{SCAN}.cpu"}


#: lower floors whose imports stay at the top of the file; inside a function only these (optional or heavy:
#: kernels that need a GPU or a compiler, the package's lazy ``__getattr__``, OpenEXR)
LAZY_ALLOWED = {
    f"{PACKAGE}.models.scan.dispatch",
    f"{PACKAGE}.models.ss2d",
    f"{PACKAGE}.data_modules",
}
LAZY_ALLOWED_TARGETS = {f"{PACKAGE}.data_modules.exr", f"{PACKAGE}.atomic"}


def _imports_inside_functions(path: Path) -> list[tuple[str, int, str]]:
    """``(function, line, module)`` of every absolute import inside a function body of ``path``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for sub in ast.walk(node):
            if isinstance(sub, ast.Import):
                found += [(node.name, sub.lineno, alias.name) for alias in sub.names]
            elif isinstance(sub, ast.ImportFrom) and not sub.level:
                found.append((node.name, sub.lineno, sub.module or ""))
    return found


def test_lower_floors_import_the_package_at_the_top():
    """physics .. callbacks: a ``tofdenoise`` import inside a function hides a dependency (issue 24, point 8)."""
    bad = []
    for module, path in MODULES.items():
        floor = _floor(module)
        if floor is None or floor < 0 or floor > FLOORS["callbacks"] or module in LAZY_ALLOWED:
            continue
        bad += [
            f"{path.relative_to(SRC)}:{line} imports {name} inside {function}"
            for function, line, name in _imports_inside_functions(path)
            if name.startswith(PACKAGE) and name not in LAZY_ALLOWED_TARGETS
        ]
    assert not bad, "\n".join(bad)


def test_no_module_imports_the_standard_library_inside_a_function():
    """A standard-library import costs nothing at the top, so inside a function it only hides a dependency; the
    exceptions the package allows are third-party imports that are optional (an extra) or heavy (torch, lightning,
    matplotlib kept out of a page renderer or a ``--help``)."""
    stdlib = set(sys.stdlib_module_names)
    bad = [
        f"{path.relative_to(SRC)}:{line} imports {name} inside {function}"
        for path in MODULES.values()
        for function, line, name in _imports_inside_functions(path)
        if name.partition(".")[0] in stdlib
    ]
    assert not bad, "\n".join(bad)


def _verb_modules() -> set[str]:
    """The modules ``tofdenoise <verb>`` routes to: the first argument of every ``Verb(...)`` in ``cli/main.py``."""
    tree = ast.parse(MODULES[f"{PACKAGE}.cli.main"].read_text(encoding="utf-8"))
    return {
        f"{PACKAGE}.cli.{node.args[0].value}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Verb" and node.args
    }


def _cli_runs_another_verb(graph: dict[str, set[str]], stdlib_imports: dict[str, set[str]]) -> list[str]:
    verbs = _verb_modules()
    bad = []
    for module, targets in graph.items():
        if not module.startswith(f"{PACKAGE}.cli.") or module == f"{PACKAGE}.cli.main":
            continue
        bad += [f"{module} imports the verb {t}" for t in sorted(targets & verbs - {module})]
        bad += [f"{module} imports {m}" for m in sorted(stdlib_imports.get(module, set()) & {"subprocess"})]
    return bad


def _top_level_imports(path: Path) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.add(node.module.split(".")[0])
    return found


def test_no_verb_runs_another_verb():
    """A verb's module parses and calls the library (docs/architecture.md, "The command line"): it never imports
    another verb's module nor starts a sub-process (the training runs of grid and reproduce are started by
    ``experiments/runner.py``, one process per run). Issue 24 point 3: ``sensor realset`` ran ``cli.sensor.main`` per
    step and ``reproduce`` ran ``tofdenoise sensor`` as sub-processes."""
    verbs = _verb_modules()
    assert {f"{PACKAGE}.cli.{m}" for m in ("train", "sensor", "reproduce", "lightning_cli")} <= verbs
    stdlib = {m: _top_level_imports(p) for m, p in MODULES.items() if m.startswith(f"{PACKAGE}.cli.")}
    assert _cli_runs_another_verb(GRAPH, stdlib) == []
    # the check sees both: a verb importing another, a verb starting a process
    graph = {**GRAPH, f"{PACKAGE}.cli.grid": GRAPH[f"{PACKAGE}.cli.grid"] | {f"{PACKAGE}.cli.sensor"}}
    assert _cli_runs_another_verb(graph, {**stdlib, f"{PACKAGE}.cli.report": {"subprocess"}}) == [
        f"{PACKAGE}.cli.grid imports the verb {PACKAGE}.cli.sensor",
        f"{PACKAGE}.cli.report imports subprocess",
    ]
