"""The import graph of ``l1flow_rl`` (with ``l1flow_rl.envs``, which lives in ``envs/``) has no cycle,
and no module imports one of the package's own modules inside a function to dodge one.

Every module is parsed with ``ast`` (nothing is imported). An import counts where it runs: at module
level (class bodies and ``try``/``if`` blocks included, ``if TYPE_CHECKING:`` blocks not, as they
never run) or inside a function. ``from a.b import c`` is an edge to ``a.b.c`` when that is a module,
else to ``a.b``, and to the packages above it that the importer is not inside of (Python runs their
``__init__`` first; the importer's own ancestors are already being imported). Imports built from
strings (``importlib.import_module``) are not seen: the simulator and expert registries load their
packages that way, by design, as a plug-in lookup.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
from pathlib import Path

from core_install import extra_top_levels

ROOT = Path(__file__).resolve().parents[3]
#: package name -> directory (pyproject.toml's package-dir)
PACKAGES = {"l1flow_rl": ROOT / "l1flow_rl", "l1flow_rl.envs": ROOT / "envs"}

#: The function-level imports of the package's own modules that are allowed, (importer, imported)
#: -> the optional dependency the imported module needs at import (the extras install it, a core
#: install lacks it): importing it lazily keeps the importer usable without that extra. The test
#: checks that the imported module really imports the dependency at module level, and that the
#: dependency is outside the core install; anything else inside a function is a layering error.
ALLOWED_FUNCTION_IMPORTS: dict[tuple[str, str], str] = {
    # demonstration files: every format reader imports h5py (the app extra)
    ("l1flow_rl.data.loading", "l1flow_rl.data.formats.base"): "h5py",
    ("l1flow_rl.data.loading", "l1flow_rl.data.formats.dp_zarr"): "h5py",
    ("l1flow_rl.data.loading", "l1flow_rl.data.formats.lerobot"): "h5py",
    ("l1flow_rl.data.loading", "l1flow_rl.data.formats.lerobot_v3"): "h5py",
    ("l1flow_rl.data.loading", "l1flow_rl.data.formats.maniskill"): "h5py",
    ("l1flow_rl.data.loading", "l1flow_rl.data.formats.robomimic"): "h5py",
    ("l1flow_rl.envs.robosuite.dataset", "l1flow_rl.data.formats.robomimic"): "h5py",
    ("l1flow_rl.envs.robosuite.dataset", "l1flow_rl.envs.robosuite.regenerate"): "h5py",
    ("l1flow_rl.experts.robosuite.demos", "l1flow_rl.data.formats.robomimic_writer"): "h5py",
    ("l1flow_rl.experts.robosuite.shifted", "l1flow_rl.data.formats.robomimic_writer"): "h5py",
    ("l1flow_rl.experts.robosuite.demos", "l1flow_rl.envs.robosuite.regenerate"): "h5py",
    # ManiSkill's worker envs are gymnasium's AsyncVectorEnv (the maniskill extra)
    ("l1flow_rl.envs.maniskill", "l1flow_rl.envs.maniskill.async_env"): "gymnasium",
}


def module_files() -> dict[str, Path]:
    files: dict[str, Path] = {}
    for package, directory in PACKAGES.items():
        for path in sorted(directory.rglob("*.py")):
            rel = path.relative_to(directory).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            files[".".join([package, *parts])] = path
    return files


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _targets(node: ast.Import | ast.ImportFrom, module: str, is_package: bool, known: set[str]) -> set[str]:
    return {
        t for target in _named(node, module, is_package, known) for t in _with_parents(target, module, known)
    }


def _with_parents(target: str, importer: str, known: set[str]) -> set[str]:
    """``target`` and its packages that are not the importer's own ancestors."""
    parts = target.split(".")
    own = {".".join(importer.split(".")[:i]) for i in range(1, importer.count(".") + 2)}
    packages = {".".join(parts[:i]) for i in range(1, len(parts))}
    return (packages & known) - own | {target}


def _named(node: ast.Import | ast.ImportFrom, module: str, is_package: bool, known: set[str]) -> set[str]:
    if isinstance(node, ast.Import):
        return {alias.name for alias in node.names if alias.name in known}
    base = node.module or ""
    if node.level:  # relative: resolve against the importing module's package
        package = module if is_package else module.rsplit(".", 1)[0]
        package = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
        base = f"{package}.{base}" if base else package
    out = set()
    for alias in node.names:
        if f"{base}.{alias.name}" in known:
            out.add(f"{base}.{alias.name}")
        elif base in known:
            out.add(base)
    return out


def imports_of(
    module: str, path: Path, known: set[str], typing: bool = False
) -> tuple[set[str], dict[str, int], set[str], dict[int, str]]:
    """(module-level targets with their packages, {function-level named target: first line},
    module-level third-party top-level names, {line: third-party top-level name} inside functions).
    ``typing``: count the imports under ``if TYPE_CHECKING:`` as module level too."""
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    top: set[str] = set()
    inner: dict[str, int] = {}
    external: set[str] = set()
    lazy_external: dict[int, str] = {}

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                for sub in (*child.body, *child.orelse) if typing else child.orelse:
                    visit_stmt(sub, in_function)
                continue
            visit_stmt(child, in_function)

    def visit_stmt(child: ast.AST, in_function: bool) -> None:
        if isinstance(child, (ast.Import, ast.ImportFrom)):
            if in_function:
                for target in _named(child, module, is_package, known) - {module}:
                    inner.setdefault(target, child.lineno)
                names = [a.name for a in child.names] if isinstance(child, ast.Import) else [child.module]
                if not getattr(child, "level", 0) and names[0] and names[0].split(".")[0] != "l1flow_rl":
                    lazy_external[child.lineno] = names[0].split(".")[0]
            else:
                top.update(_targets(child, module, is_package, known) - {module})
                if isinstance(child, ast.Import):
                    external.update(alias.name.split(".")[0] for alias in child.names)
                elif not child.level and child.module:
                    external.add(child.module.split(".")[0])
        funcs = (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)
        visit(child, in_function or isinstance(child, funcs))

    visit(tree, False)
    return top, inner, external - {"l1flow_rl"}, lazy_external


@functools.cache
def import_graph(
    typing: bool = False,
) -> tuple[dict[str, set[str]], dict[tuple[str, str], str], dict[str, set[str]]]:
    """(module-level graph, {(importer, imported): "path:line"} of function-level imports, each
    module's module-level third-party imports). ``typing``: with the type-checking-only imports."""
    files = module_files()
    known = set(files)
    graph: dict[str, set[str]] = {}
    inner: dict[tuple[str, str], str] = {}
    external: dict[str, set[str]] = {}
    for module, path in files.items():
        graph[module], found, external[module], _ = imports_of(module, path, known, typing)
        for target, line in found.items():
            inner[(module, target)] = f"{path.relative_to(ROOT)}:{line}"
    return graph, inner, external


def imported_with(module: str, graph: dict[str, set[str]]) -> set[str]:
    """``module`` and every module of the package that importing it runs (module-level closure)."""
    seen, todo = set(), [module]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph.get(m, ()))
    return seen


@functools.cache
def _extras() -> frozenset[str]:
    return frozenset(extra_top_levels())


def is_optional(top_level: str) -> bool:
    """Whether a top-level module is missing from a core install (not stdlib, not a core requirement)."""
    return top_level in _extras()


def _has_reason_comment(path: Path, line: int) -> bool:
    """A ``#`` comment on the import's line, or above it in its block of imports (``try:`` included)."""
    lines = path.read_text().splitlines()
    i = line - 1
    if "#" in lines[i]:
        return True
    while i > 0:
        i -= 1
        text = lines[i].strip()
        if text.startswith("#"):
            return True
        if not (text.startswith(("import ", "from ")) or text in ("", "try:")):
            return False
    return False


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as a cycle path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return [_cycle_path(graph, set(c)) for c in components]


def _cycle_path(graph: dict[str, set[str]], component: set[str]) -> list[str]:
    """One concrete cycle inside a strongly connected component: start -> ... -> start."""
    start = min(component)
    parents: dict[str, str] = {start: start}
    frontier = [start]
    while frontier:  # breadth first, so the printed cycle is a shortest one through ``start``
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & component):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(parents[path[-1]])
                    return [*reversed(path), start]
                if w not in parents:
                    parents[w] = v
                    nxt.append(w)
        frontier = nxt
    return sorted(component)


def test_the_walk_sees_the_package():
    graph, inner, external = import_graph()
    assert "l1flow_rl.envs.registry" in graph and "l1flow_rl.config.validate" in graph
    assert "l1flow_rl.modules.actor" in graph["l1flow_rl.workspace.build"]
    # a child's import runs its package's __init__ first: an edge to the package too
    assert {"l1flow_rl.evaluation", "l1flow_rl.evaluation.protocols"} <= graph[
        "l1flow_rl.envs.pusht.protocol"
    ]
    assert ("l1flow_rl.data.loading", "l1flow_rl.data.formats.base") in inner
    assert "h5py" in external["l1flow_rl.data.formats.base"]


def test_find_cycles_prints_the_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycles(graph) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_among_modules():
    graph, inner, _ = import_graph()
    cycles = find_cycles(graph)
    assert not cycles, "import cycles among l1flow_rl's modules (module level):\n" + "\n".join(
        " -> ".join(c) for c in cycles
    )
    # nor one that the allowed lazy imports would close when they run
    full = {m: set(targets) for m, targets in graph.items()}
    for importer, imported in inner:
        full[importer].add(imported)
    cycles = find_cycles(full)
    assert not cycles, "import cycles through function-level imports:\n" + "\n".join(
        " -> ".join(c) for c in cycles
    )


def test_deployment_and_modules_layers_have_no_cycle_even_for_type_checkers():
    """The deployment package sits above the modules: ``export`` may import ``modules``, never the
    reverse through a circle, not even one that only type checkers follow (the actor reads folders
    through ``export.folder``, which names the actor by its base class)."""
    graph, _, _ = import_graph(typing=True)
    layers = ("l1flow_rl.export", "l1flow_rl.modules")
    sub = {m: {t for t in ts if t.startswith(layers)} for m, ts in graph.items() if m.startswith(layers)}
    cycles = find_cycles(sub)
    assert not cycles, "cycles among export/ and modules/ (type-checking imports counted):\n" + "\n".join(
        " -> ".join(c) for c in cycles
    )
    assert find_cycles({"a": {"b"}, "b": {"a"}}), "the check must see a two-module circle"


def test_function_level_imports_of_own_modules_are_allowed_ones():
    _, inner, _ = import_graph()
    unlisted = {edge: where for edge, where in inner.items() if edge not in ALLOWED_FUNCTION_IMPORTS}
    assert not unlisted, (
        f"{len(unlisted)} import(s) of l1flow_rl's own modules inside functions; import them at module "
        "level (a cycle they dodge is a layering error), or, for a module that needs an optional "
        "dependency, list them in ALLOWED_FUNCTION_IMPORTS:\n"
        + "\n".join(f"{where}: {a} -> {b}" for (a, b), where in sorted(unlisted.items()))
    )
    stale = sorted(set(ALLOWED_FUNCTION_IMPORTS) - set(inner))
    assert not stale, f"allowed function-level imports that no longer exist: {stale}"


def test_each_allowed_lazy_import_is_for_an_optional_dependency_and_says_so():
    graph, inner, external = import_graph()
    files = module_files()
    for (importer, imported), dependency in ALLOWED_FUNCTION_IMPORTS.items():
        needs = set().union(*(external[m] for m in imported_with(imported, graph)))
        assert dependency in needs, f"{imported} does not import {dependency!r} at module level"
        assert is_optional(dependency), (
            f"{dependency!r} is part of the core install: import {imported} at top"
        )
        path, line = inner[(importer, imported)].rsplit(":", 1)
        assert _has_reason_comment(ROOT / path, int(line)), f"{path}:{line}: say why the import is lazy"
    assert files  # the walk found the package


def test_imports_inside_functions_are_optional_dependencies_with_a_reason():
    """A third-party import inside a function is one that a core install lacks (a simulator, plots,
    video, h5py, ...), with a comment saying so; the core's own dependencies and the standard
    library are imported at the top."""
    known = set(module_files())
    core, silent = [], []
    for module, path in module_files().items():
        for line, top in imports_of(module, path, known)[3].items():
            where = f"{path.relative_to(ROOT)}:{line} ({top})"
            if not is_optional(top):
                core.append(where)
            elif not _has_reason_comment(path, line):
                silent.append(where)
    assert not core, "imports of the core install or the standard library inside functions:\n" + "\n".join(
        core
    )
    assert not silent, "lazy imports of optional dependencies without a reason comment:\n" + "\n".join(silent)


def test_config_schemas_import_nothing_else_of_the_package():
    """``config/`` holds the schemas; the validator (which asks the registries) is the one exception."""
    graph, _, _ = import_graph()
    schemas = [m for m in graph if m.startswith("l1flow_rl.config") and m != "l1flow_rl.config.validate"]
    outside = {m: sorted(t for t in graph[m] if not t.startswith("l1flow_rl.config")) for m in schemas}
    assert not {m: t for m, t in outside.items() if t}


def test_validating_a_config_imports_no_simulator():
    # (mujoco is left out: torchrl.envs imports it itself wherever it is installed)
    code = (
        "import sys\n"
        "from omegaconf import OmegaConf\n"
        "from l1flow_rl.config import AppConfig, load_task_config\n"
        "from l1flow_rl.config.validate import validate_config\n"
        "for task in ('maniskill_pickcube_rgb', 'pusht_image', 'robosuite_lift_image'):\n"
        "    cfg = OmegaConf.structured(AppConfig)\n"
        "    cfg.task = OmegaConf.structured(load_task_config(task))\n"
        "    validate_config(cfg)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in\n"
        "    ('mani_skill', 'sapien', 'robosuite', 'gym_pusht', 'pymunk', 'gymnasium', 'h5py')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
