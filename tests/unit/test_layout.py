"""The layout holds: no import cycles between modules, and imports point down the layers of DESIGN.md section 1."""

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("missions", "nac_onboard", "sitl", "ground")
#: the error bases every layer may raise (NAC's, and the mission library's own, which the CLIs map to exit 2): they
#: import nothing of the project but each other's leaf.
SHARED_LEAVES = {"nac_onboard.errors": {"missions.errors"}, "missions.errors": set()}
#: package -> what it may import besides the standard library and itself (not even a shared leaf of another package)
SELF_CONTAINED = {"missions": {"missions.geo": ("numpy",)}}

#: module prefix -> prefixes it must never import (a layer above it, or I/O a pure core must not do).
FORBIDDEN = {
    "missions": ("nac_onboard", "sitl", "ground", "pymavlink", "socket"),
    "nac_onboard": ("sitl", "ground"),
    "nac_onboard.compute.kernels": ("mpi4py", "socket", "nac_onboard.mavlink", "nac_onboard.agent"),
    # the radio between vehicles is pure: no sockets, processes, clocks or sleeping, nothing above it
    "nac_onboard.radio": ("socket", "selectors", "subprocess", "threading", "time", "nac_onboard.clock",
                          "nac_onboard.agent", "nac_onboard.compute", "nac_onboard.mavlink", "nac_onboard.link",
                          "pymavlink", "mpi4py"),
    "nac_onboard.mavlink": ("nac_onboard.agent", "nac_onboard.compute", "nac_onboard.link", "nac_onboard.radio"),
    "nac_onboard.link": ("nac_onboard.agent", "nac_onboard.compute", "nac_onboard.mavlink"),
    "nac_onboard.agent": ("nac_onboard.compute",),
    "sitl.vehicle": ("sitl.mavlink", "sitl.server", "sitl.experiment", "pymavlink", "socket", "nac_onboard",
                     "ground"),
    "sitl.mavlink": ("sitl.server", "sitl.experiment", "socket", "ground"),
    "sitl.server": ("sitl.experiment", "ground"),
    "sitl.telemetry_radio": ("socket", "pymavlink", "sitl.server", "sitl.experiment", "nac_onboard.link", "ground"),
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
                wrong += [f"{name} imports {dep}" for dep in deps - set(SHARED_LEAVES) for b in banned
                          if dep == b or dep.startswith(b + ".")]
    for leaf, allowed in SHARED_LEAVES.items():
        wrong += [f"{leaf} imports {dep}" for dep in graph[leaf] - allowed if dep.split(".")[0] in PACKAGES]
    assert not wrong, "\n".join(sorted(wrong))


def test_self_contained_packages_import_the_standard_library_only(graph):
    """missions is a library of its own: the standard library (numpy for its geodesy), nothing of NAC's, not even
    its error base (its MissionFileError is its own, mapped to exit 2 by nac_onboard.errors.run_cli)."""
    wrong = []
    for package, extra in SELF_CONTAINED.items():
        for name, deps in graph.items():
            if name != package and not name.startswith(package + "."):
                continue
            allowed = {package, *sys.stdlib_module_names, *extra.get(name, ())}
            wrong += [f"{name} imports {dep}" for dep in deps if dep.split(".")[0] not in allowed]
    assert not wrong, "\n".join(sorted(wrong))


#: the radio package's one edge: the only module of nac_onboard.radio that reads or writes files
RADIO_EDGE = "nac_onboard.radio.files"
FILE_IO = ("os", "io", "json", "tomllib", "tomli", "pathlib", "shutil", "nac_onboard.tomlfile")


def test_the_radio_touches_files_only_at_its_edge(graph):
    radio = [name for name in graph if name.startswith("nac_onboard.radio.")]
    assert RADIO_EDGE in radio and len(radio) > 1
    wrong = [f"{name} imports {dep}" for name in radio if name != RADIO_EDGE for dep in graph[name]
             for banned in FILE_IO if dep == banned or dep.startswith(banned + ".")]
    assert not wrong, "\n".join(sorted(wrong))


def test_the_walker_sees_a_cycle(tmp_path):
    """The cycle check itself works: two modules importing each other are found."""
    (tmp_path / "a.py").write_text("from b import x\n")
    (tmp_path / "b.py").write_text("import a\n")
    modules = {"a": tmp_path / "a.py", "b": tmp_path / "b.py"}
    assert imports_of(modules["a"], "a", modules) >= {"b"}
    assert imports_of(modules["b"], "b", modules) == {"a"}
