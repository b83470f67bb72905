"""The package's layout: its imports run one way, with no cycle.

Read from the source with `ast` (every `import` and `from ... import`, at the
top of a module, inside a function or under `TYPE_CHECKING`), so that a lazy
import cannot hide a cycle. The order, lowest first:

    core  <-  _io, _estimate, _control  <-  _verdict  <-  _diagnose, _whatif  <-  _screen  <-  top

A module imports from its own room or from a lower one; `_io`, `_estimate` and
`_control` do not import each other, nor do `_diagnose` and `_whatif`; the core's
modules and the top's are listed, so a new module has to be given its place.
"""

import ast
import pathlib
import sys

import pytest


PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "jaxstiction"

CORE = {"_blocks", "_checks", "_criteria", "_drawing", "_filters", "_fleet", "_linalg", "_loop", "_misc", "_models",
        "_programs", "_scenarios", "_simulate", "_spline"}
ROOMS = {"_io": 1, "_estimate": 1, "_control": 1, "_verdict": 2, "_diagnose": 3, "_whatif": 3, "_screen": 4}
TOP = {"__init__", "__main__", "internal", "_cli", "_demo", "_plots"}
LEVEL = {"core": 0, **ROOMS, "top": 5}


def _modules() -> dict[str, pathlib.Path]:
    """Dotted name (below the package) of every module, e.g. `_io.read`, `__init__`."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _room(module: str) -> str:
    """`core`, `top` or the room (`_io`, ...) of a module."""
    head = module.split(".")[0]
    if head in ROOMS:
        return head
    if module in CORE:
        return "core"
    if module in TOP:
        return "top"
    raise AssertionError(f"jaxstiction.{module} has no place in the layout: add it to CORE, TOP or a room "
                         "(tests/test_layout.py)")


def _target(name: str) -> str:
    """The module (as in `MODULES`) that an imported dotted name below the package is:
    the name itself, else its package's `__init__`."""
    if name == "":
        return "__init__"
    if name in MODULES:
        return name
    if f"{name}.__init__" in MODULES:
        return f"{name}.__init__"
    raise AssertionError(f"import of jaxstiction.{name}, which does not exist")


def _imports(module: str) -> set[str]:
    """The package's modules that `module` imports, anywhere in it."""
    tree = ast.parse(MODULES[module].read_text())
    package = module.split(".")[:-1]  # the package it is in (for `_io.__init__`, `_io`)
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name == "jaxstiction" or a.name.startswith("jaxstiction."):
                    out.add(_target(a.name.removeprefix("jaxstiction").lstrip(".")))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            elif node.module == "jaxstiction" or (node.module or "").startswith("jaxstiction."):
                name = node.module.removeprefix("jaxstiction").lstrip(".")
            else:
                continue
            for a in node.names:  # `from . import _cli` imports a module
                sub = f"{name}.{a.name}" if name else a.name
                out.add(_target(sub) if sub in MODULES or f"{sub}.__init__" in MODULES else _target(name))
    out.discard(module)
    return out


GRAPH = {m: _imports(m) for m in MODULES}


def test_every_module_has_a_place():
    for m in MODULES:
        _room(m)


def test_no_import_cycle():
    """Tarjan's strongly connected components: each must be a single module."""
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in GRAPH:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_downward(module):
    room = _room(module)
    for target in sorted(GRAPH[module]):
        there = _room(target)
        if there == room:
            continue
        assert LEVEL[there] < LEVEL[room], (
            f"jaxstiction.{module} ({room}) imports jaxstiction.{target} ({there}), which is not below it")


def test_no_all_in_private_modules():
    """`jaxstiction/__init__.py` is the public surface; private modules list nothing."""
    for m, path in MODULES.items():
        tree = ast.parse(path.read_text())
        names = {t.id for node in tree.body if isinstance(node, ast.Assign) for t in node.targets
                 if isinstance(t, ast.Name)}
        assert "__all__" not in names, f"jaxstiction.{m} has an __all__"


def test_the_checker_sees_cycles_and_upward_imports(monkeypatch):
    """The checks above on a made-up graph: a cycle, and an import from the core
    into a room."""
    fake = {"_checks": {"_io.read"}, "_io.read": {"_checks"}, "_io.__init__": set(), "__init__": set()}
    monkeypatch.setattr(sys.modules[__name__], "GRAPH", fake)
    with pytest.raises(AssertionError, match="import cycles"):
        test_no_import_cycle()
    with pytest.raises(AssertionError, match="not below it"):
        test_imports_run_downward("_checks")


def test_the_public_surface_holds_no_stray_modules():
    """What `import jaxstiction` shows is the API: no module it imported on the way
    (a standard-library helper) is left among its public names; `internal` is the
    one module there on purpose."""
    import types

    import jaxstiction

    stray = [k for k, v in vars(jaxstiction).items()
             if not k.startswith("_") and isinstance(v, types.ModuleType) and k != "internal"]
    assert not stray, f"jaxstiction exposes modules {stray}"
