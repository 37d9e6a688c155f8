"""The architecture, checked: folders are layers and imports only go down them (function-local
imports count), no import cycle, one module per ``usplat`` command, at most 8 modules at the top
of ``usplat_dr/``, every package in the wheel, and what importing a layer loads."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).parents[1]
PACKAGE = ROOT / "usplat_dr"

#: Layer of each part of usplat_dr (the first dotted name after ``usplat_dr``): a module may
#: import modules of its own part and of lower layers. ``model`` and ``data`` share a layer
#: but may not import each other (the model never sees the dataset, the data never the model).
LAYERS = {
    "_llvm": 0, "_openmp": 0, "portable": 0,
    "": 1, "backend": 1, "config": 1, "io": 1,  # "": ``usplat_dr`` itself (the libLLVM choice)
    "geometry": 2,
    "render": 3,
    "model": 4, "data": 4,
    "evaluation": 5, "plugins": 5,
    "training": 6,
    "jobs": 7,
    "cli": 8, "__main__": 9,
}


def module_files() -> dict[str, Path]:
    """``{dotted module name: file}`` of usplat_dr, plugins/ included as usplat_dr.plugins."""
    files = {}
    for base, prefix in ((PACKAGE, "usplat_dr"), (ROOT / "plugins", "usplat_dr.plugins")):
        for path in base.rglob("*.py"):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            files[".".join([prefix, *parts])] = path
    return files


MODULES = module_files()


def imports(name: str, path: Path) -> set[str]:
    """The usplat_dr modules that ``name`` imports anywhere in its file (function bodies too):
    ``from a.b import c`` counts as ``a.b.c`` when that is a module, else as ``a.b``."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            package = name if path.name == "__init__.py" else name.rpartition(".")[0]
            base = node.module or ""
            if node.level:  # relative import
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            found |= {f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base
                      for a in node.names}
    return {m for m in found if m == "usplat_dr" or m.startswith("usplat_dr.")}


GRAPH = {name: imports(name, path) - {name} for name, path in MODULES.items()}


def part(module: str) -> str:
    return module.split(".")[1] if "." in module else ""


def test_every_module_has_a_layer():
    assert {part(m) for m in MODULES} <= set(LAYERS), sorted({part(m) for m in MODULES}
                                                             - set(LAYERS))


def test_imports_only_go_down_the_layers():
    upward = [f"{m} imports {t}" for m, targets in GRAPH.items() for t in targets
              if part(t) != part(m) and (LAYERS[part(t)] > LAYERS[part(m)]
                                         or LAYERS[part(t)] == LAYERS[part(m)])]
    assert not upward, "\n".join(sorted(upward))


def test_nothing_imports_jobs():
    # usplat_dr.cli loads the chosen job by name (importlib), the one way in
    assert not [m for m, targets in GRAPH.items() if part(m) != "jobs"
                and any(part(t) == "jobs" for t in targets)]


def test_no_import_cycle():
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(module: str, path: list[str]) -> list[str] | None:
        state[module] = 1
        for target in sorted(GRAPH.get(module, ())):
            if state.get(target) == 1:
                return path[path.index(target):] + [target]
            if target not in state and (cycle := visit(target, path + [target])):
                return cycle
        state[module] = 2
        return None

    for module in sorted(GRAPH):
        if module not in state:
            cycle = visit(module, [module])
            assert cycle is None, " -> ".join(cycle)


def test_function_local_imports_give_a_reason():
    """Function-local imports only where they protect start-up time or the libLLVM order, each
    with its reason in a comment on its line or the line above."""
    silent = []
    for path in MODULES.values():
        lines = path.read_text().splitlines()
        for fn in ast.walk(ast.parse("\n".join(lines))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                if isinstance(node, (ast.Import, ast.ImportFrom)) and not any(
                        "#" in lines[i] for i in (node.lineno - 2, node.lineno - 1)):
                    silent.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not silent, "function-local imports without a reason: " + ", ".join(silent)


def test_top_level_holds_only_plumbing():
    top = sorted(p.stem for p in PACKAGE.glob("*.py"))
    assert len(top) <= 8, top
    assert {LAYERS[m if m != "__init__" else ""] for m in top} <= {0, 1, 8, 9}, top


def test_one_job_module_per_command():
    from usplat_dr.cli import COMMANDS

    modules = [module for module, _ in COMMANDS.values()]
    assert len(set(modules)) == len(modules)
    for module in modules:
        assert f"usplat_dr.jobs.{module}" in MODULES, module
        tree = ast.parse(MODULES[f"usplat_dr.jobs.{module}"].read_text())
        functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        assert {"add_arguments", "run"} <= functions, module


def test_every_package_ships_in_the_wheel():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())
                 ["tool"]["setuptools"]["packages"])
    packages = {name for name, path in MODULES.items() if path.name == "__init__.py"}
    assert packages <= listed, sorted(packages - listed)


@pytest.mark.parametrize("module, absent", [
    ("usplat_dr.render", ["mitsuba", "usplat_dr.model", "torch"]),
    ("usplat_dr.model", ["mitsuba", "usplat_dr.data"]),
    ("usplat_dr.data", ["mitsuba", "usplat_dr.model"]),
    ("usplat_dr.cli", ["torch", "drjit", "usplat_dr.jobs"]),  # start-up time
])
def test_importing_a_layer_loads_only_what_it_needs(module, absent):
    code = f"import sys, {module}; print([m for m in {absent!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout.strip()
    assert out == "[]", f"import {module} loaded {out}"
