"""The package's import graph, read from the source (every import, the lazy ones inside
functions too; ``if TYPE_CHECKING:`` blocks aside): no cycle between modules; no cycle through
``factors`` or ``sims`` taken as wholes (they sit beside the package and are installed under
it); no private name imported from another module; no module re-exporting names another
defines (a package's ``__init__`` is its public surface and may)."""

import ast
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: folder -> the import name it is installed as (pyproject's package-dir)
FOLDERS = {"nap3d_graph": "nap3d_graph", "factors": "nap3d_graph.factors", "sims": "nap3d_graph.sims"}


def _modules() -> dict[str, Path]:
    modules = {}
    for folder, name in FOLDERS.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join([*name.split("."), *parts])] = path
    return modules


MODULES = _modules()


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every Import / ImportFrom node, outside ``if TYPE_CHECKING:`` blocks."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(ast.iter_child_nodes(node))


def _absolute(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    package = module.split(".") if MODULES[module].name == "__init__.py" else module.split(".")[:-1]
    base = package[: len(package) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _graph():
    """module -> {module it imports}, and the names each ImportFrom takes, per module."""
    edges, taken = defaultdict(set), []
    for module, path in MODULES.items():
        for node in _imports(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                source = _absolute(module, node)
                targets = [source] + [f"{source}.{alias.name}" for alias in node.names]
                if source in MODULES:
                    taken.append((module, source, [alias.name for alias in node.names]))
            edges[module] |= {t for t in targets if t in MODULES and t != module}
    return edges, taken


def _cycles(edges: dict) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan, iterative)."""
    index, low, on_stack, stack, out, counter = {}, {}, set(), [], [], [0]
    nodes = set(edges) | {n for targets in edges.values() for n in targets}

    def visit(root):
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        out.append(sorted(component))
            elif child not in index:
                index[child] = low[child] = counter[0]
                counter[0] += 1
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(edges.get(child, ())))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])

    for node in sorted(nodes):
        if node not in index:
            visit(node)
    return out


@pytest.fixture(scope="module")
def graph():
    return _graph()


def test_the_reader_sees_the_whole_package(graph):
    edges, _ = graph
    assert len(MODULES) > 100 and "nap3d_graph.run.pipeline" in MODULES and "nap3d_graph.factors.gate" in MODULES
    # A known edge, through a relative import: the run builds its factors.
    assert "nap3d_graph.factors" in edges["nap3d_graph.run.pipeline"]


def test_no_import_cycle_between_modules(graph):
    edges, _ = graph
    assert _cycles(edges) == []
    # The check finds one when there is one.
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_cycle_through_factors_or_sims_as_wholes(graph):
    edges, _ = graph

    def whole(module):
        for name in ("nap3d_graph.factors", "nap3d_graph.sims"):
            if module == name or module.startswith(name + "."):
                return name
        return module

    collapsed = defaultdict(set)
    for module, targets in edges.items():
        collapsed[whole(module)] |= {whole(t) for t in targets if whole(t) != whole(module)}
    assert _cycles(collapsed) == []


def test_no_subpackage_imports_sims_or_factors_back(graph):
    """Taken a subpackage at a time (``nap3d_graph.datasets.*`` one node), no cycle goes
    through ``sims`` or ``factors``: what they use of the package never uses them."""
    edges, _ = graph

    def subpackage(module):
        parts = module.split(".")
        return ".".join(parts[:2]) if len(parts) > 2 or module in MODULES and MODULES[module].name == "__init__.py" \
            else module

    collapsed = defaultdict(set)
    for module, targets in edges.items():
        collapsed[subpackage(module)] |= {subpackage(t) for t in targets if subpackage(t) != subpackage(module)}
    tangled = [cycle for cycle in _cycles(collapsed)
               if {"nap3d_graph.sims", "nap3d_graph.factors"} & set(cycle)]
    assert tangled == []


def test_no_private_name_crosses_modules(graph):
    _, taken = graph
    crossing = [(module, source, name) for module, source, names in taken for name in names
                if name.startswith("_") and not name.startswith("__")]
    assert crossing == []


def test_no_module_re_exports_another_modules_names():
    offenders = {}
    for module, path in MODULES.items():
        if path.name == "__init__.py":
            continue
        tree = ast.parse(path.read_text())
        defined, exported = set(), []
        for node in tree.body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                defined.add(node.name)
            elif isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for target in targets:
                    names = target.elts if isinstance(target, ast.Tuple) else [target]
                    defined |= {n.id for n in names if isinstance(n, ast.Name)}
                    if isinstance(target, ast.Name) and target.id == "__all__":
                        exported = [e.value for e in node.value.elts]
        if missing := [name for name in exported if name not in defined]:
            offenders[module] = missing
    assert offenders == {}


def test_the_library_never_imports_the_command_line(graph):
    """The CLI sits on top: no library module imports it (the sweep is handed the CLI's entry
    point; ``__main__`` is the CLI's own entry)."""
    edges, _ = graph
    upward = sorted((module, target) for module, targets in edges.items() for target in targets
                    if target.startswith("nap3d_graph.cli") and not module.startswith("nap3d_graph.cli")
                    and module != "nap3d_graph.__main__")
    assert upward == [], upward


def test_library_errors_name_settings_not_flags():
    """A library module's error names the setting (in backticks, as the Python caller passes
    it); only the command line turns it into its flag (``cli.common.in_flags``). Flags of other
    tools (nerfstudio's) may be named."""
    import re

    flag = re.compile(r"(?<![\w-])--[a-z][a-z-]*")
    others = {"--pipeline"}  # nerfstudio's own command line
    found = []
    for module, path in MODULES.items():
        if module.startswith("nap3d_graph.cli") or module == "nap3d_graph.__main__":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Raise) and node.exc is not None:
                texts = [n.value for n in ast.walk(node.exc) if isinstance(n, ast.Constant) and isinstance(n.value, str)]
                flags = {f for t in texts for f in flag.findall(t)} - others
                if flags:
                    found.append(f"{module}:{node.lineno} {sorted(flags)}")
    assert found == [], found


#: Folders that still import each other: none. The last (issue 63) was ``fields`` <-> ``run``: a
#: field's error was measured through ``run.keyframe`` while the run's covariance reads the
#: field's error model; the keyframe measurement now sits below both (``nap3d.keyframe``).
KNOWN_TIES: set[tuple[str, str]] = set()


def test_folders_import_each_other_one_way(graph):
    """Between two folders of the package imports go one way (lazy ones inside functions
    counted), but for the ties listed in ``KNOWN_TIES``: mapping, evaluation, motion and
    datasets no longer reach back into what imports them."""
    edges, _ = graph

    def folder(module: str) -> str:
        parts = module.split(".")
        return parts[1] if len(parts) > 2 else parts[-1]

    pairs = {(folder(a), folder(b)) for a, targets in edges.items() for b in targets if folder(a) != folder(b)}
    ties = {tuple(sorted(p)) for p in pairs if (p[1], p[0]) in pairs}
    assert ties == KNOWN_TIES, sorted(ties - KNOWN_TIES)


#: Third-party packages that are optional extras (pyproject's ``full``, ``viz``, ``ray``, ``mesh``,
#: ``nerfstudio``) or slow to load: the one list of what may keep a project import inside a
#: function. Everything else in the package imports its own modules at the top.
LAZY_PACKAGES = {"torch", "numba", "filterpy", "evo", "matplotlib", "tqdm", "yaml", "small_gicp", "xfeat",
                 "rosbags", "threadpoolctl", "pyrealsense2", "rerun", "ray", "open3d", "nerfstudio"}


def _top_level_imports(module: str) -> tuple[set[str], set[str]]:
    """``(project modules, third-party top names)`` a module imports when it is loaded: the
    imports of its body outside functions and ``if TYPE_CHECKING:`` blocks."""
    project, third = set(), set()
    stack = list(ast.parse(MODULES[module].read_text()).body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        if isinstance(node, ast.If) and _is_type_checking(node):
            stack.extend(node.orelse)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [_absolute(module, node)] + [f"{_absolute(module, node)}.{a.name}" for a in node.names])
            project |= {n for n in names if n in MODULES}
            third |= {n.split(".")[0] for n in names if n.split(".")[0] not in ("nap3d_graph", "")}
            continue
        stack.extend(ast.iter_child_nodes(node))
    # A module is loaded with its packages: their __init__ runs first.
    parts = module.split(".")
    project |= {".".join(parts[:k]) for k in range(1, len(parts)) if ".".join(parts[:k]) in MODULES}
    return project - {module}, third


def _lazy_packages_loaded() -> dict[str, set[str]]:
    """module -> the ``LAZY_PACKAGES`` that loading it loads (through its top-level imports,
    each module's own reach walked afresh: a package and its modules load each other)."""
    direct = {m: _top_level_imports(m) for m in MODULES}
    loaded = {}
    for module in MODULES:
        seen, todo = {module}, [module]
        while todo:
            for other in direct[todo.pop()][0] - seen:
                seen.add(other)
                todo.append(other)
        loaded[module] = set().union(*(direct[m][1] for m in seen)) & LAZY_PACKAGES
    return loaded


def _imports_inside_functions(module: str) -> list[tuple[int, str]]:
    """``(line, project module)`` of each import of the project's own modules inside a function."""
    out = []

    def walk(node, inside: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                continue
            if inside and isinstance(child, (ast.Import, ast.ImportFrom)):
                names = ([a.name for a in child.names] if isinstance(child, ast.Import)
                         else [_absolute(module, child)])
                out.extend((child.lineno, n) for n in names if n.split(".")[0] == "nap3d_graph")
            walk(child, inside or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    walk(ast.parse(MODULES[module].read_text()), False)
    return out


def test_own_modules_are_imported_at_the_top_unless_they_load_an_optional_package():
    """An import of the project's own module inside a function hides a tie between modules
    from whoever reads the file's top; it stays there only when the module it imports loads a
    package of ``LAZY_PACKAGES`` that the importing module does not load itself (an optional
    extra a core command must not need, or a slow one)."""
    loaded = _lazy_packages_loaded()
    hidden = [f"{MODULES[m].relative_to(ROOT)}:{line} imports {target}"
              for m in MODULES for line, target in _imports_inside_functions(m)
              if target in MODULES and not (loaded[target] - loaded[m])]
    assert hidden == []
    # The reader sees what loading a module loads: the fields' training pulls torch, the
    # command line's core does not.
    assert "torch" in loaded["nap3d_graph.fields.training"] and "torch" not in loaded["nap3d_graph.cli.common"]
