"""Import rules of the package, checked on the source with `ast` (nothing is imported).

1. The module-level import graph among `sgn_jax.*` modules has no cycles.
2. An import of an `sgn_jax` module inside a function is allowed only when it is listed in
   `DEFERRED_IMPORTS` with its reason (see docs/architecture.md, "Imports").

How the graph is built. A module-level import is any import statement that is not inside a
function body (class bodies and top-level `if`/`try` blocks run at import time and count;
blocks under `if TYPE_CHECKING:` do not). `import sgn_jax.x` and `from sgn_jax.x import y`
are edges to `sgn_jax.x`, or to `sgn_jax.x.y` when that is a module;
`from sgn_jax import api` is an edge to `sgn_jax.api`. Importing `sgn_jax.a.b` also runs the
package `sgn_jax.a` (its `__init__`, which re-exports its submodules), so it adds an edge to
`sgn_jax.a` too, except from modules inside `sgn_jax.a` itself (while a package's `__init__`
runs, its submodules import their siblings without re-entering it). The root package
`sgn_jax` is a node like the others; its `__init__` imports no `sgn_jax` module.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = "sgn_jax"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE

# (importing module, imported module) -> why the import stays inside a function.
DEFERRED_IMPORTS: dict[tuple[str, str], str] = {
    ("sgn_jax.cli", "sgn_jax.analysis.plots"):
        "plots imports matplotlib at module level; only the plotting commands need it, so "
        "`sgn-jax --help` and the other commands do not load it",
    ("sgn_jax.pipelines.demo", "sgn_jax.analysis.plots"):
        "demo is imported by sgn_jax.api and sgn_jax.cli; only run_demo plots (matplotlib)",
    ("sgn_jax.experiment_tools", "sgn_jax.analysis.plots"):
        "the experiment scripts import sgn_jax.experiment_tools; only its figure helpers "
        "(new_figure, save_figure, plot_case_curves) need matplotlib",
    ("sgn_jax.pipelines.charge_sweep", "sgn_jax.analysis.plots"):
        "charge_sweep is imported by sgn_jax.api and sgn_jax.cli; only plot_charge_sweep draws "
        "(matplotlib)",
    ("sgn_jax.pipelines.spectra", "sgn_jax.analysis.collision_plots"):
        "spectra is imported by sgn_jax.api and sgn_jax.cli; only CollisionSpectra.plot draws "
        "(matplotlib)",
}


def _module_files() -> dict[str, Path]:
    """Module name -> source file, for every module and package under sgn_jax/."""
    modules = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.Module):
    """Yield (import node, inside_function) for every import that can run."""
    def walk(node, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import | ast.ImportFrom):
                yield child, in_function
            elif isinstance(child, ast.If) and _is_type_checking(child.test):
                yield from walk(ast.Module(body=child.orelse, type_ignores=[]), in_function)
            else:
                nested = in_function or isinstance(
                    child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
                yield from walk(child, nested)
    yield from walk(tree, False)


def _targets(node: ast.Import | ast.ImportFrom, importer: str, modules) -> list[str]:
    """The sgn_jax modules an import statement names (relative imports resolved)."""
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
        return [n for n in names if n == PACKAGE or n.startswith(PACKAGE + ".")]
    base = node.module or ""
    if node.level:
        package = importer if modules[importer].name == "__init__.py" else importer.rpartition(
            ".")[0]
        for _ in range(node.level - 1):
            package = package.rpartition(".")[0]
        base = f"{package}.{base}" if base else package
    if not (base == PACKAGE or base.startswith(PACKAGE + ".")):
        return []
    targets = []
    for alias in node.names:
        sub = f"{base}.{alias.name}"
        targets.append(sub if sub in modules else base)
    return list(dict.fromkeys(targets))


def _with_parent_packages(importer: str, target: str) -> list[str]:
    """The target plus the packages that importing it runs (see the module docstring)."""
    out = [target]
    parts = target.split(".")
    for i in range(2, len(parts)):
        package = ".".join(parts[:i])
        if not importer.startswith(package + "."):
            out.append(package)
    return out


def import_graph():
    """(module-level edges {module: {imported: line}}, function-level [(module, imported, line)])."""
    modules = _module_files()
    edges: dict[str, dict[str, int]] = {name: {} for name in modules}
    deferred = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node, in_function in _imports(tree):
            for target in _targets(node, name, modules):
                if in_function:
                    deferred.append((name, target, node.lineno))
                    continue
                for dep in _with_parent_packages(name, target):
                    if dep != name:
                        edges[name].setdefault(dep, node.lineno)
    return edges, deferred


def _find_cycle(edges) -> list[str] | None:
    """One cycle of the graph as [a, b, ..., a], or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for dep in sorted(edges.get(node, {})):
            if state.get(dep) == 1:
                return stack[stack.index(dep):] + [dep]
            if dep not in state:
                cycle = visit(dep)
                if cycle:
                    return cycle
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def _where(module: str, line: int) -> str:
    path = _module_files()[module]
    return f"{path.relative_to(PACKAGE_DIR.parent)}:{line}"


def test_the_module_level_import_graph_has_no_cycles():
    edges, _ = import_graph()
    assert len(edges) > 20, "found too few modules: is PACKAGE_DIR right?"
    cycle = _find_cycle(edges)
    if cycle:
        pytest.fail("module-level import cycle (break it, see docs/architecture.md, Imports):\n"
                    + "\n".join(f"  {_where(a, edges[a][b])}: {a} imports {b}"
                                 for a, b in zip(cycle, cycle[1:], strict=False)),
                    pytrace=False)


def test_function_level_imports_of_the_package_are_allowlisted():
    _, deferred = import_graph()
    offending = sorted({
        f"  {_where(module, line)}: {module} imports {target} inside a function"
        for module, target, line in deferred if (module, target) not in DEFERRED_IMPORTS})
    if offending:
        pytest.fail("move these imports to the top of the module, or list them in "
                    "DEFERRED_IMPORTS (tests/test_architecture.py) with a reason:\n"
                    + "\n".join(offending), pytrace=False)


def test_the_allowlist_has_no_stale_entries():
    _, deferred = import_graph()
    used = {(module, target) for module, target, _ in deferred}
    stale = sorted(set(DEFERRED_IMPORTS) - used)
    assert not stale, f"DEFERRED_IMPORTS entries that no longer occur: {stale}"


def test_the_checker_sees_cycles_and_deferred_imports():
    assert _find_cycle({"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3}}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b": 1}, "b": {}, "c": {"a": 2}}) is None
    tree = ast.parse(
        "import sgn_jax.config\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from sgn_jax.surrogate import train\n"
        "def f():\n    from sgn_jax.geometry import jar_sdf\n")
    modules = _module_files()
    found = [(_targets(node, "sgn_jax.api", modules), fn) for node, fn in _imports(tree)]
    assert found == [(["sgn_jax.config"], False), ([], False), (["sgn_jax.geometry"], True)]
    assert _with_parent_packages("sgn_jax.api", "sgn_jax.geometry.jar") == [
        "sgn_jax.geometry.jar", "sgn_jax.geometry"]
    assert _with_parent_packages("sgn_jax.geometry.sdf_grid", "sgn_jax.geometry.jar") == [
        "sgn_jax.geometry.jar"]


# ---------------------------------------------------------------------------------------------
# Layers (docs/architecture.md, "Layers"): every module has one, and no import goes up.

LAYERS = ("core", "records", "analysis", "pipelines", "user")
"""Lowest first. A module may import (at module level or inside a function) modules of its own
layer and of the layers below it, never above:

- core: pure JAX / numpy (scene, motion, geometry, DEM, surrogate, design, regime, pairs);
- records: the configs and the files (config, trajectory, prediction, checkpoint, atomic I/O,
  cache, ensembles, envelope): they build and check core objects (a checkpoint builds its model
  kind from the surrogate's registry, a prediction counts pairs with ``sgn_jax.pairs``);
- analysis: metrics, plots and the animation read records (trajectory and prediction files)
  and apply the core's rules (regime, pairs);
- pipelines: where a config meets the core on a host; the drivers produce records and call the
  analysis (``demo`` writes the metrics, plots and GIF; ``experiments`` evaluates with the
  metrics); the analysis never drives a run;
- user: ``sgn_jax.api``, ``sgn_jax.experiment_tools`` (what the experiment scripts use beyond
  the API) and the CLI, on top of everything.
"""

MODULE_LAYERS = {
    # The root package runs only the x64 switch and defines __version__ (records and pipelines
    # import it for that); its public names come from sgn_jax.api on first access (PEP 562),
    # which the import graph does not see.
    PACKAGE: "core",
    "sgn_jax.errors": "core",
    "sgn_jax.motion": "core",
    "sgn_jax.scene": "core",
    "sgn_jax.pairs": "core",
    "sgn_jax.design": "core",
    "sgn_jax.regime": "core",
    "sgn_jax.testing": "core",
    "sgn_jax.geometry": "core",
    "sgn_jax.dem": "core",
    "sgn_jax.surrogate": "core",
    "sgn_jax.config": "records",
    "sgn_jax.config_reference": "records",
    "sgn_jax.records": "records",
    "sgn_jax.analysis": "analysis",
    "sgn_jax.pipelines": "pipelines",
    "sgn_jax.api": "user",
    "sgn_jax.experiment_tools": "user",
    "sgn_jax.cli": "user",
}
"""Module or package -> layer. A package's entry covers its modules (a new file in
``sgn_jax/surrogate/`` is core); a new module directly under ``sgn_jax/`` needs its own entry
(the root package's entry covers only ``sgn_jax/__init__.py``)."""


def layer_of(module: str) -> str | None:
    """The layer of a module: its own entry, else its nearest package's (not the root's)."""
    if module in MODULE_LAYERS:
        return MODULE_LAYERS[module]
    parts = module.split(".")
    for i in range(len(parts) - 1, 1, -1):
        package = ".".join(parts[:i])
        if package in MODULE_LAYERS:
            return MODULE_LAYERS[package]
    return None


def upward_imports(edges, deferred) -> list[tuple[str, str, int, bool]]:
    """(importer, imported, line, inside_function) for every import of a higher layer."""
    rank = {layer: i for i, layer in enumerate(LAYERS)}
    pairs = [(m, dep, line, False) for m, deps in edges.items() for dep, line in deps.items()]
    pairs += [(m, dep, line, True) for m, dep, line in deferred]
    found = []
    for module, dep, line, in_function in sorted(pairs):
        low, high = layer_of(module), layer_of(dep)
        if low is not None and high is not None and rank[high] > rank[low]:
            found.append((module, dep, line, in_function))
    return found


def test_every_module_has_a_layer():
    modules = _module_files()
    missing = sorted(m for m in modules if layer_of(m) is None)
    assert not missing, (f"modules without a layer: {missing}; add them to MODULE_LAYERS "
                         "(tests/test_architecture.py) and to docs/architecture.md, Layers")
    stale = sorted(m for m in MODULE_LAYERS if m not in modules)
    assert not stale, f"MODULE_LAYERS names modules that do not exist: {stale}"
    assert set(MODULE_LAYERS.values()) <= set(LAYERS)


def test_no_module_imports_a_layer_above_its_own():
    edges, deferred = import_graph()
    problems = [
        f"  {_where(module, line)}: {module} ({layer_of(module)}) imports {dep} "
        f"({layer_of(dep)}){' inside a function' if in_function else ''}"
        for module, dep, line, in_function in upward_imports(edges, deferred)]
    if problems:
        pytest.fail("imports go down the layers only (" + " < ".join(LAYERS) + "): move the "
                    "shared piece down, or the caller up (docs/architecture.md, Layers):\n"
                    + "\n".join(problems), pytrace=False)


def test_the_upward_import_checker_sees_a_violation():
    # The upward import this check was written against: the animation (analysis) built the
    # jar mesh with sgn_jax.pipelines.configure; now the demo pipeline passes the mesh in.
    edges = {"sgn_jax.analysis.animation": {"sgn_jax.pipelines.configure": 36,
                                            "sgn_jax.records.io_utils": 35},
             "sgn_jax.pipelines.demo": {"sgn_jax.analysis.animation": 50}}
    deferred = [("sgn_jax.surrogate.rollout", "sgn_jax.config", 7),
                ("sgn_jax.api", "sgn_jax.analysis.plots", 180)]
    assert upward_imports(edges, deferred) == [
        ("sgn_jax.analysis.animation", "sgn_jax.pipelines.configure", 36, False),
        ("sgn_jax.surrogate.rollout", "sgn_jax.config", 7, True)]
    assert layer_of("sgn_jax.surrogate.contact") == "core"  # a new model kind: core
    assert layer_of("sgn_jax.records.base") == "records"
    assert layer_of("sgn_jax.newmodule") is None  # a new root module must be assigned


# The pure JAX core never reaches the config, file I/O or the pipelines (transitively), and
# imports no file-I/O module.

CORE_MODULES = tuple(m for m in _module_files() if layer_of(m) == "core")
"""The pure JAX core (docs/architecture.md, "Layers")."""

OUTSIDE_THE_CORE = tuple(m for m, layer in MODULE_LAYERS.items() if layer != "core")
"""Config, records and file I/O, analysis, pipelines and the user-facing layer."""

FILE_IO_MODULES = ("pathlib", "os", "io", "json", "csv", "tomllib", "shutil", "tempfile",
                   "orbax", "orbax.checkpoint", "trimesh.exchange", "imageio", "matplotlib")
"""Standard-library and third-party modules of file I/O that the core must not import."""


def _closure(edges, start: str) -> dict[str, list[str]]:
    """Every module reachable from ``start`` -> one import chain that reaches it."""
    chains = {start: [start]}
    todo = [start]
    while todo:
        node = todo.pop()
        for dep in sorted(edges.get(node, {})):
            if dep not in chains:
                chains[dep] = chains[node] + [dep]
                todo.append(dep)
    return chains


def _external_imports(path: Path) -> dict[str, int]:
    """Top-level names of non-sgn_jax modules imported at module level -> line."""
    found = {}
    for node, in_function in _imports(ast.parse(path.read_text())):
        if in_function:
            continue
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if not node.level else [])
        for name in names:
            if name and not name.startswith(PACKAGE):
                found.setdefault(name, node.lineno)
    return found


def test_the_core_modules_exist():
    expected = {"sgn_jax.motion", "sgn_jax.scene", "sgn_jax.dem.engine", "sgn_jax.geometry.jar",
                "sgn_jax.surrogate.graph", "sgn_jax.surrogate.model", "sgn_jax.surrogate.sgn",
                "sgn_jax.surrogate.rollout", "sgn_jax.surrogate.train", "sgn_jax.design"}
    missing = sorted(expected - set(CORE_MODULES))
    assert not missing, f"expected core modules missing from the core layer: {missing}"


def test_the_core_never_imports_the_config_io_or_pipelines():
    edges, _ = import_graph()
    modules = _module_files()
    problems = []
    for core in CORE_MODULES:
        if core not in modules:
            continue
        for reached, chain in _closure(edges, core).items():
            if any(reached == o or reached.startswith(o + ".") for o in OUTSIDE_THE_CORE):
                problems.append(f"  {core} reaches {reached}: " + " -> ".join(chain))
    if problems:
        pytest.fail("the core must not import the config, records/file I/O or the pipelines "
                    "(move the adapter to sgn_jax.pipelines; docs/architecture.md, Layers):\n"
                    + "\n".join(problems), pytrace=False)


def test_the_core_does_no_file_io():
    modules = _module_files()
    problems = []
    for core in CORE_MODULES:
        if core not in modules:
            continue
        for name, line in _external_imports(modules[core]).items():
            if name in FILE_IO_MODULES or name.split(".")[0] in ("pathlib", "os", "orbax"):
                problems.append(f"  {_where(core, line)}: {core} imports {name}")
    if problems:
        pytest.fail("file I/O belongs to the pipelines and records layers:\n"
                    + "\n".join(problems), pytrace=False)


def test_the_layer_checker_sees_a_violation():
    edges = {"sgn_jax.motion": {"sgn_jax.surrogate.graph": 1},
             "sgn_jax.surrogate.graph": {"sgn_jax.config": 2}, "sgn_jax.config": {}}
    chains = _closure(edges, "sgn_jax.motion")
    assert chains["sgn_jax.config"] == [
        "sgn_jax.motion", "sgn_jax.surrogate.graph", "sgn_jax.config"]


# ---------------------------------------------------------------------------------------------
# One base exception; experiments use the public API only.

def _package_modules():
    import importlib

    for name in _module_files():
        yield importlib.import_module(name)


def test_every_exception_class_of_the_package_derives_from_sgnjaxerror():
    """Errors and warnings alike (warnings derive from ``sgn_jax.errors.SGNJaxWarning``)."""
    from sgn_jax.errors import SGNJaxError

    offending = set()
    for module in _package_modules():
        for value in vars(module).values():
            if (isinstance(value, type) and issubclass(value, BaseException)
                    and value.__module__.startswith(PACKAGE)
                    and not issubclass(value, SGNJaxError)):
                offending.add(f"{value.__module__}.{value.__qualname__}")
    assert not offending, (
        f"exception classes that do not derive from sgn_jax.errors.SGNJaxError: "
        f"{sorted(offending)}")


EXPERIMENTS_DIR = PACKAGE_DIR.parent / "experiments"
PUBLIC_MODULES = {PACKAGE, f"{PACKAGE}.api", f"{PACKAGE}.experiment_tools"}


def test_experiments_import_only_the_public_api():
    """Every script under experiments/ imports from the package only ``sgn_jax``,
    ``sgn_jax.api`` and ``sgn_jax.experiment_tools`` (at any depth, inside functions too), and
    never another experiment script through ``sys.path.insert``: what several scripts share
    lives in the package. benchmarks/ may import deeper modules: they measure internals."""
    scripts = sorted(EXPERIMENTS_DIR.rglob("*.py"))
    assert len(scripts) >= 10, "found too few experiment scripts: is EXPERIMENTS_DIR right?"
    local = {path.stem for path in scripts}
    problems = []
    for path in scripts:
        tree = ast.parse(path.read_text(), filename=str(path))
        where = path.relative_to(EXPERIMENTS_DIR.parent)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""] if not node.level else ["." * node.level]
            else:
                if (isinstance(node, ast.Attribute) and node.attr == "insert"
                        and isinstance(node.value, ast.Attribute) and node.value.attr == "path"
                        and isinstance(node.value.value, ast.Name)
                        and node.value.value.id == "sys"):
                    problems.append(f"  {where}:{node.lineno}: sys.path.insert")
                continue
            for name in names:
                top = name.split(".")[0]
                if name.startswith("."):
                    problems.append(f"  {where}:{node.lineno}: relative import")
                elif top == PACKAGE and name not in PUBLIC_MODULES:
                    problems.append(f"  {where}:{node.lineno}: imports {name}")
                elif top in local:
                    problems.append(f"  {where}:{node.lineno}: imports the script {name}")
    if problems:
        pytest.fail("experiments import only sgn_jax / sgn_jax.api / sgn_jax.experiment_tools "
                    "(add what they need to sgn_jax.experiment_tools):\n" + "\n".join(problems),
                    pytrace=False)


def test_the_package_data_paths_resolve_from_the_modules_folders():
    """Modules that find shipped files relative to their own file (``Path(__file__)``) still find
    them after a move between folders (records/ is one level below the package root)."""
    from sgn_jax.config import builtin_config_path
    from sgn_jax.records import checkpoint, envelope, shipped_models

    data = PACKAGE_DIR / "data"
    assert envelope.ENVELOPE_PATH == data / "envelope.toml" and envelope.ENVELOPE_PATH.is_file()
    assert checkpoint._SHIPPED_MODELS_DIR == data / "models"
    assert shipped_models.SHIPPED_MODELS_DIR == data / "models"
    assert (data / "models" / shipped_models.REGISTRY_FILE).is_file()
    assert builtin_config_path("emax_300rpm").is_file()
