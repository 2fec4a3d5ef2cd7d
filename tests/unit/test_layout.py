"""The layout holds: no import cycles between modules, and imports point down the layers of DESIGN.md section 1."""

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("missions", "nac_onboard", "sitl", "ground")
#: the one error base: every layer may raise its kinds, so it imports nothing of the project itself
SHARED_LEAVES = {"nac_onboard.errors"}

#: module prefix -> prefixes it must never import (a layer above it, or I/O a pure core must not do).
FORBIDDEN = {
    "missions": ("nac_onboard", "sitl", "ground", "pymavlink", "socket"),
    "nac_onboard": ("sitl", "ground"),
    "nac_onboard.compute.kernels": ("mpi4py", "socket", "nac_onboard.mavlink", "nac_onboard.agent"),
    "nac_onboard.link.channel": ("socket", "nac_onboard.mavlink", "nac_onboard.agent", "nac_onboard.compute"),
    "nac_onboard.mavlink": ("nac_onboard.agent", "nac_onboard.compute", "nac_onboard.link"),
    "nac_onboard.link": ("nac_onboard.agent", "nac_onboard.compute", "nac_onboard.mavlink"),
    "nac_onboard.agent": ("nac_onboard.compute",),
    "sitl.vehicle": ("sitl.mavlink", "sitl.server", "sitl.experiment", "pymavlink", "socket", "nac_onboard",
                     "ground"),
    "sitl.mavlink": ("sitl.server", "sitl.experiment", "socket", "ground"),
    "sitl.server": ("sitl.experiment", "ground"),
    "ground.logs": ("ground.operator", "sitl"),
    "ground.operator": ("ground.logs", "sitl"),
}


def module_files() -> dict[str, Path]:
    modules = {}
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            parts = path.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            modules[name] = path
    return modules


def imports_of(path: Path, name: str, modules: dict[str, Path]) -> set[str]:
    """Every module this file imports, anywhere in it (a function-level import couples modules just the same)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            found.add(base)
            # `from pkg import module` imports the module, not only the package
            found.update(f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in modules)
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = module_files()
    return {name: imports_of(path, name, modules) for name, path in modules.items()}


def test_no_import_cycles_between_modules(graph):
    internal = {name: {m for m in deps if m in graph and m != name} for name, deps in graph.items()}
    cycles, index, low, stack, on_stack = [], {}, {}, [], set()

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in internal[v]:
            if w not in index:
                visit(w)
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
                cycles.append(sorted(component))

    for v in sorted(internal):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_imports_point_down_the_layers(graph):
    wrong = []
    for name, deps in graph.items():
        for prefix, banned in FORBIDDEN.items():
            if name == prefix or name.startswith(prefix + "."):
                wrong += [f"{name} imports {dep}" for dep in deps - SHARED_LEAVES for b in banned
                          if dep == b or dep.startswith(b + ".")]
    for leaf in SHARED_LEAVES:
        wrong += [f"{leaf} imports {dep}" for dep in graph[leaf] if dep.split(".")[0] in PACKAGES]
    assert not wrong, "\n".join(sorted(wrong))


def test_the_walker_sees_a_cycle(tmp_path):
    """The cycle check itself works: two modules importing each other are found."""
    (tmp_path / "a.py").write_text("from b import x\n")
    (tmp_path / "b.py").write_text("import a\n")
    modules = {"a": tmp_path / "a.py", "b": tmp_path / "b.py"}
    assert imports_of(modules["a"], "a", modules) >= {"b"}
    assert imports_of(modules["b"], "b", modules) == {"a"}
