"""The package's import graph has no cycles (module-level and function-level imports, TYPE_CHECKING ones included),
and the model does not import its user interface; neither has benchmarks/."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "willags_ns"
BENCHMARKS = PACKAGE.parent / "benchmarks"


def _modules(package: Path = PACKAGE) -> dict[str, Path]:
    out = {}
    for path in package.rglob("*.py"):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """module -> the package modules it imports anywhere in its file (`from a.b import c` counts a.b.c when c is a
    module, else a.b)."""
    mods = _modules(package)

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [f"{node.module}.{a.name}" for a in node.names]
            for name in names:
                if name.split(".")[0] == package.name:
                    target = resolve(name)
                    if target is not None and target != mod:
                        deps.add(target)
        graph[mod] = deps
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
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
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_cycles_finds_a_planted_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_package_has_no_import_cycles():
    graph = import_graph()
    assert "willags_ns.model" in graph and "willags_ns.appearance.networks" in graph["willags_ns.model"]
    assert cycles(graph) == []


def room_of(module: str) -> str:
    """The room of a package module: its folder under willags_ns (``appearance``, ``engine``, ...), or the module
    itself for one at the package's root (``willags_ns.model``)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 2 else module


def room_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """room -> the rooms its modules import (module-level and function-level imports)."""
    rooms: dict[str, set[str]] = {}
    for mod, deps in graph.items():
        a = room_of(mod)
        rooms.setdefault(a, set()).update(room_of(d) for d in deps if room_of(d) != a)
    return rooms


ROOM_ORDER = ("render", "data", "splats", "appearance", "mask", "objective", "eval", "tools", "engine", "scripts")
"""The folders from the lowest to the highest: a room imports only rooms before it (and the root's modules say
where they sit by what they import)."""


def test_rooms_import_one_way():
    """No loop between folders (a file-level graph without cycles can still loop at the folder level), and every
    folder imports only folders lower in ROOM_ORDER."""
    rooms = room_graph(import_graph())
    assert cycles(rooms) == []
    rank = {r: i for i, r in enumerate(ROOM_ORDER)}
    assert set(rank) == {r for r in rooms if "." not in r and r != "willags_ns"}, "every folder has its place"
    upward = [(a, b) for a, deps in rooms.items() for b in deps if a in rank and b in rank and rank[b] >= rank[a]]
    assert upward == []


def test_room_loops_are_found():
    graph = {"willags_ns.a.x": {"willags_ns.b.y"}, "willags_ns.b.y": {"willags_ns.c.z"}, "willags_ns.c.z": set()}
    assert cycles(room_graph(graph)) == []
    graph["willags_ns.c.z"] = {"willags_ns.a.w"}  # no file cycle (a.w is another file), but a -> b -> c -> a
    graph["willags_ns.a.w"] = set()
    assert cycles(graph) == [] and cycles(room_graph(graph)) == [["a", "b", "c"]]


def test_the_model_does_not_import_the_viewer():
    graph = import_graph()
    assert "willags_ns.viewer" not in graph["willags_ns.model"]


def test_benchmarks_have_no_import_cycles():
    graph = import_graph(BENCHMARKS)
    assert "benchmarks.curves" in graph["benchmarks.results"]  # the graph was read
    assert cycles(graph) == []


METHOD_ROOMS = ("appearance", "mask", "splats", "objective", "render")


def test_the_package_root_holds_at_most_ten_modules():
    root = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert "model.py" in root and len(root) <= 10, root


def test_the_method_rooms_import_neither_the_model_nor_the_engine():
    graph = import_graph()
    outside = ("willags_ns.model", "willags_ns.method_configs", "willags_ns.engine")
    for mod, deps in graph.items():
        if mod.split(".")[1:2] and mod.split(".")[1] in METHOD_ROOMS:
            assert not [d for d in deps if d.startswith(outside)], mod
        if mod.startswith("willags_ns.engine"):
            assert not [d for d in deps if d == "willags_ns.model" or d.split(".")[1] in METHOD_ROOMS], mod


def private_imports(package: Path = PACKAGE, target: str = "willags_ns") -> list[str]:
    """`from <target>.x import _name` in a module other than x itself, and imports of a `_private` module of
    `target` from outside its own package (a module's _private names are its own; a package's _private modules are
    its package's)."""
    found = []
    for path in package.rglob("*.py"):
        own = ".".join(path.relative_to(package.parent).with_suffix("").parts[:-1])
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == target:
                names = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                private_module = any(part.startswith("_") for part in node.module.split("."))
                if names or (private_module and node.module.rpartition(".")[0] != own):
                    found.append(f"{path.relative_to(package.parent)}:{node.lineno} {node.module} {names}")
    return found


PICKLED_PRIVATE = {
    "numpy._core": "numpy 2 pickles its arrays under it: torch's safe globals must name it (engine/compat)"
}
"""Other libraries' private modules the package imports, each with why: what a checkpoint's pickle names."""


def foreign_private_imports(package: Path = PACKAGE) -> list[str]:
    """`from lib.x import _name` and `from lib._x import ...` of a library other than willags_ns (its private names
    and modules: they change without notice between its releases), except PICKLED_PRIVATE."""
    found = []
    for path in package.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom) or not node.module or node.level:
                continue
            if node.module.split(".")[0] in (package.name, "__future__") or node.module in PICKLED_PRIVATE:
                continue
            names = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
            if names or any(part.startswith("_") and not part.startswith("__") for part in node.module.split(".")):
                found.append(f"{path.relative_to(package.parent)}:{node.lineno} {node.module} {names}")
    return found


def test_no_private_name_of_another_library_is_imported(tmp_path):
    assert foreign_private_imports() == []
    fake = tmp_path / "willags_ns"
    fake.mkdir()
    (fake / "a.py").write_text("from gsplat.strategy.ops import _update\nfrom numpy._core import multiarray\n")
    assert [f.split(" ", 1)[1] for f in foreign_private_imports(fake)] == ["gsplat.strategy.ops ['_update']"]


def test_private_imports_are_found(tmp_path):
    fake = tmp_path / "pkg"
    fake.mkdir()
    (fake / "a.py").write_text("from willags_ns.b import _hidden\nfrom willags_ns.b import shown\n")
    (fake / "c.py").write_text("from willags_ns.render._torch import rasterize\n")
    found = sorted(f.split(" ", 1)[1] for f in private_imports(fake))
    assert found == ["willags_ns.b ['_hidden']", "willags_ns.render._torch []"]


def test_no_module_imports_another_modules_private_names():
    assert private_imports() == []
    assert private_imports(BENCHMARKS) == []  # benchmarks/ reach willags_ns only through public names
