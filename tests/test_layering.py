"""The architecture, checked: folders are layers and imports only go down them (function-local
imports count), no import cycle, one module per ``usplat`` command, at most 8 modules at the top
of ``usplat_dr/``, every package in the wheel, what importing a layer loads, and that the
scripts in ``train/`` and the plugins in ``plugins/`` use only what a user of the library can
(``SCRIPT_RULES``)."""

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
    "_llvm": 0, "_threads": 0, "portable": 0,
    "": 1, "backend": 1, "config": 1, "io": 1,  # "": ``usplat_dr`` itself (the libLLVM choice)
    "geometry": 2,
    "render": 3,
    "model": 4, "data": 4,
    "evaluation": 5, "plugins": 5,
    "training": 6, "viewer": 6,
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


#: Imports the rule allows upward: the package's ``__getattr__`` hands out ``usplat_dr.load``
#: on first use (``import usplat_dr`` itself imports no torch: tested below).
LAZY_EXPORTS = {"usplat_dr": {"usplat_dr.training.loader"}}
GRAPH = {name: imports(name, path) - {name} - LAZY_EXPORTS.get(name, set())
         for name, path in MODULES.items()}


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


def test_a_job_imports_no_other_job_but_the_shared_ones():
    # what the jobs share is in jobs/arguments.py (arguments and helpers) and jobs/report.py
    # (result files to Markdown and PNG); a command's own module is imported by the CLI alone
    shared = {"usplat_dr.jobs.arguments", "usplat_dr.jobs.report"}
    crossing = [f"{m} imports {t}" for m, targets in GRAPH.items() if part(m) == "jobs"
                for t in targets if part(t) == "jobs" and t != m and t not in shared
                and t != "usplat_dr.jobs"]
    assert not crossing, "\n".join(sorted(crossing))


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


def test_images_are_decoded_through_one_door():
    """Every image the library or a plugin decodes goes through ``usplat_dr.io.user_files``
    (PNG or JPEG only, its size checked before decoding): a direct ``Image.open``,
    ``imageio`` read or ``Image.frombytes``-style decoder elsewhere would let any format Pillow
    knows (EPS: Ghostscript) or any claimed size through."""
    door = MODULES["usplat_dr.io.user_files"]
    others = []
    for path in MODULES.values():
        if path == door:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("open", "imread", "v3") \
                    and isinstance(node.value, ast.Name) \
                    and node.value.id in ("Image", "imageio", "iio", "skimage"):
                others.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not others, "images decoded outside usplat_dr.io.user_files: " + ", ".join(others)


def test_top_level_holds_only_plumbing():
    top = sorted(p.stem for p in PACKAGE.glob("*.py"))
    assert len(top) <= 8, top
    assert {LAYERS[m if m != "__init__" else ""] for m in top} <= {0, 1, 8, 9}, top


def test_one_job_module_per_command_named_after_it():
    from usplat_dr.cli import COMMANDS, job_module

    modules = [job_module(command) for command in COMMANDS]
    assert len(set(modules)) == len(modules)
    shared = {"__init__", "arguments", "report"}  # helpers of several commands, not commands
    assert {m.rsplit(".", 1)[1] for m in MODULES if m.startswith("usplat_dr.jobs.")} - shared \
        == set(modules)
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


# ---- Scripts and plugins: only what a user of the library can use ----

SCRIPT_RULES = """\
Files in train/ and plugins/ (every import, function-local ones included):
- no usplat_dr.jobs: the jobs are the commands' internals; a script runs a command through
  usplat_dr.cli (main([...]), COMMANDS), the one way in, and uses the library below jobs;
- no private name from usplat_dr: no module or name starting with "_" imported, and none read as
  an attribute of an imported usplat_dr module (a script uses what users can);
- no sys.path edit (the library is installed; the tests' helpers are not a script's);
- no sibling script imported by bare name (it works only from that folder's sys.path entry);
  in train/ no relative import either (train/ is not a package). Code two scripts share is
  the library's, or one runs the other as a subprocess."""

#: Known exceptions: {file: {what it imports: the move that removes it}}. A listed exception
#: that no longer occurs fails too, so the list shrinks with the moves.
PENDING: dict[str, dict[str, str]] = {}


def script_files() -> list[Path]:
    """The .py files of train/ and plugins/; a symbolic link is another name for a file that
    is checked under its own."""
    return sorted(path for base in (ROOT / "train", ROOT / "plugins")
                  for path in base.rglob("*.py")
                  if "__pycache__" not in path.parts and not path.is_symlink())


#: Public API that starts with "_": a NamedTuple's methods and fields (``SceneInputs``).
NAMEDTUPLE_API = {"_replace", "_fields", "_asdict", "_make", "_field_defaults"}
JOBS = "a jobs internal (a script runs a command through usplat_dr.cli)"


def is_private(name: str) -> bool:
    return (name.startswith("_") and not (name.startswith("__") and name.endswith("__"))
            and name not in NAMEDTUPLE_API)


def script_problems(path: Path, text: str | None = None) -> list[tuple[int, str, str]]:
    """``(line, what, why)`` for each break of ``SCRIPT_RULES`` in ``path`` (its ``text`` when
    given): ``what`` is the module or name at fault."""
    tree = ast.parse(path.read_text() if text is None else text)
    siblings = ({p.stem for p in path.parent.glob("*.py")}
                | {p.parent.name for p in path.parent.glob("*/__init__.py")})
    in_train = ROOT / "train" in path.parents
    found = []
    modules = {}  # local name -> usplat_dr module it is bound to (for attribute reads)

    def check_module(line: int, module: str) -> None:
        parts = module.split(".")
        if parts[0] == "usplat_dr":
            if parts[1:2] == ["jobs"]:
                found.append((line, module, JOBS))
            if any(is_private(x) for x in parts):
                found.append((line, module, "a private module"))
        elif parts[0] in siblings:
            found.append((line, module, "a sibling script by bare name"))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                check_module(node.lineno, alias.name)
                if alias.name.startswith("usplat_dr"):
                    local = alias.asname or alias.name.split(".")[0]
                    modules[local] = alias.name if alias.asname else "usplat_dr"
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if in_train:
                    found.append((node.lineno, "." * node.level + (node.module or ""),
                                  "a relative import (train/ is not a package)"))
                continue
            check_module(node.lineno, node.module)
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                if node.module == "sys" and alias.name == "path":
                    found.append((node.lineno, "sys.path", "a sys.path edit"))
                if node.module.split(".")[0] != "usplat_dr":
                    continue
                if is_private(alias.name):
                    found.append((node.lineno, full, "a private name"))
                if full == "usplat_dr.jobs":
                    found.append((node.lineno, full, JOBS))
                modules[alias.asname or alias.name] = full
        elif (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
              and node.value.id == "sys" and node.attr == "path"):
            found.append((node.lineno, "sys.path", "a sys.path edit"))
    for node in ast.walk(tree):  # attribute reads of imported usplat_dr modules: x._private
        chain = []
        while isinstance(node, ast.Attribute):
            chain.append(node.attr)
            node = node.value
        if isinstance(node, ast.Name) and node.id in modules and chain:
            private = [a for a in chain if is_private(a)]
            if private:
                found.append((node.lineno, f"{modules[node.id]}...{private[0]}",
                              "a private name"))
    return sorted(set(found))


def test_scripts_use_only_the_public_library():
    problems, pending = [], set()
    for path in script_files():
        rel = path.relative_to(ROOT).as_posix()
        for line, what, why in script_problems(path):
            if what in PENDING.get(rel, {}):
                pending.add((rel, what))
            else:
                problems.append(f"{rel}:{line}: {what}: {why}")
    assert not problems, SCRIPT_RULES + "\nbroken by:\n" + "\n".join(problems)
    stale = [f"{f}: {w}" for f, ws in PENDING.items() for w in ws if (f, w) not in pending]
    assert not stale, "PENDING lists exceptions that no longer occur: " + ", ".join(stale)


@pytest.mark.parametrize("code, what", [
    ("from usplat_dr.jobs.bench import PRUNES", "usplat_dr.jobs.bench"),
    ("def f():\n    import usplat_dr.jobs.report", "usplat_dr.jobs.report"),
    ("from usplat_dr import jobs", "usplat_dr.jobs"),
    ("def f():\n    from usplat_dr.render.bridge import _value_flags",
     "usplat_dr.render.bridge._value_flags"),
    ("from usplat_dr import _llvm", "usplat_dr._llvm"),
    ("import usplat_dr._threads", "usplat_dr._threads"),
    ("from usplat_dr.render import bridge\nbridge._value_flags([], 1, 2)",
     "usplat_dr.render.bridge..._value_flags"),
    ("import usplat_dr.render.bridge\nusplat_dr.render.bridge._wrapped",
     "usplat_dr..._wrapped"),
    ("import sys\nsys.path.insert(0, 'tests')", "sys.path"),
    ("def main():\n    import sys\n    sys.path.append('x')", "sys.path"),
    ("def main():\n    from training import make_trainer", "training"),
    ("import rasterizer", "rasterizer"),
    ("from . import training", "."),
])
def test_script_rules_catch(code, what):
    """Each rule on a script in train/bench/ that breaks it (checked as text: no file is
    written); the same script without the line passes."""
    path = ROOT / "train" / "bench" / "example.py"
    assert what in [w for _, w, _ in script_problems(path, code)], script_problems(path, code)
    fine = ("import usplat_dr\nfrom usplat_dr.cli import main\n"
            "from usplat_dr.data.types import SceneInputs\nSceneInputs._fields")
    assert script_problems(path, fine) == []


def test_the_lazy_export_imports_nothing_until_used():
    code = ("import sys, usplat_dr; assert 'torch' not in sys.modules; "
            "from usplat_dr.training.loader import load; assert usplat_dr.load is load")
    subprocess.run([sys.executable, "-c", code], check=True)

