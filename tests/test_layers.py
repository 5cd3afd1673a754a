"""The layering of ``jaxrt/_src`` (docs/design.md, "Kinds and layers"), checked on the parsed imports.

Every module belongs to one layer; a module imports only modules of its own layer or of the layers its layer
may read. The layers form a DAG, and the module graph (top-level and function-local imports together) has no
cycle. A function-local import is allowed only where it defers an optional dependency (Numba, Triton), so that
no local import hides an arrow.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "jaxrt"

#: Layer name -> (module prefixes below ``jaxrt._src`` (a prefix ending in "." names a package), the layers it
#: may import). ``jaxrt.tags`` (the public tag vocabulary, which imports nothing) counts as math.
LAYERS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    # scalar and array math: robustness helpers, keyframes, transforms, trees, the exact leaf formulas
    "math": (
        ("numerics", "versions", "motion", "transforms", "bvh.", "primitives.", "formulas.", "jaxrt.tags"),
        (),
    ),
    # one definition per primitive kind, and the registry that lists them
    "kinds": (("kinds.",), ("math",)),
    # the traversals: their contract (traversal.scene), the portable step, the GPU kernel, the CPU loop
    "traversal": (("traversal.",), ("math", "kinds")),
    # geometry descriptors and per-primitive records
    "geometry": (
        ("geometry", "curves", "spheres", "candidate", "ray", "primitive_data", "checks", "result", "normals"),
        ("math", "kinds"),
    ),
    # building structures (knows nothing of any traversal)
    "build": (("structures", "instances"), ("math", "kinds", "geometry")),
    # a structure as the traversals and the result see it; the GPU kernel's rows on a structure; point queries
    "scene": (
        (
            "scene_view",
            "prepacked",
            "compaction",
            "sizes",
            "leaves",
            "fields",
            "filter_states",
            "point_traversal",
            "point_query",
            "winding",
            "sdf_grid",
            "topology",
        ),
        ("math", "kinds", "traversal", "geometry", "build"),
    ),
    # rays -> scene -> traversal -> fields; the intersector and queries
    "pipeline": (("pipeline", "intersector", "query"), ("math", "kinds", "traversal", "geometry", "build", "scene")),
    # file formats, debugging pictures, shading helpers, rays over devices, many worlds, pixel integrals
    "top": (
        ("io.", "io", "heatmap", "shading", "sharding", "worlds", "visibility", "pixel_integral"),
        ("math", "kinds", "traversal", "geometry", "build", "scene", "pipeline"),
    ),
}

#: Function-local imports that defer an optional dependency (importing the target imports it).
DEFERRED = {
    ("traversal.cpu", "traversal.cpu_kernel"): "Numba",
    ("traversal.cpu", "traversal.cpu_order"): "Numba",
    ("traversal.gpu", "traversal.triton_kernel"): "Triton",
    ("traversal.points", "traversal.cpu_points"): "Numba",
    ("traversal.points", "traversal.triton_points"): "Triton",
    # the package instantiates its Numba operations on demand; they read the package's digest back then
    ("formulas.ops_numba", "formulas"): "Numba",
}


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted((ROOT / "_src").rglob("*.py")):
        parts = list(path.relative_to(ROOT / "_src").with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if parts and parts[-1] != "conftest":
            out[".".join(parts)] = path
    return out


def _target(module: str, package: str, node: ast.ImportFrom | ast.Import, name: str, modules) -> str | None:
    """The module (below ``jaxrt._src``, or a public ``jaxrt...`` name) an import names, or ``None`` (not jaxrt)."""
    if isinstance(node, ast.Import):
        full = name
    else:
        if node.level:
            base = package.split(".")[: len(package.split(".")) - node.level + 1]
            full = ".".join(["jaxrt", "_src", *[p for p in base if p], *([node.module] if node.module else [])])
        else:
            full = node.module or ""
        if f"{full}.{name}".removeprefix("jaxrt._src.") in modules:
            full = f"{full}.{name}"
        elif full == "jaxrt" and (ROOT / f"{name}.py").exists():  # a public module: ``from jaxrt import tags``
            full = f"jaxrt.{name}"
    if full == "jaxrt" or full.startswith("jaxrt."):
        return full.removeprefix("jaxrt._src.") if full.startswith("jaxrt._src.") else full
    return None


@functools.cache
def _imports() -> tuple[tuple[str, str, bool, int], ...]:
    """Every import of a jaxrt module in ``jaxrt/_src``: ``(module, target, local, line)``."""
    modules = _modules()
    edges = []
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        top = {id(n) for n in tree.body}
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            local = id(node) not in top
            for alias in node.names:
                target = _target(module, package, node, alias.name, modules)
                if target is not None and target != module:
                    edges.append((module, target, local, node.lineno))
    return tuple(edges)


def _layer(module: str) -> str:
    for name, (prefixes, _) in LAYERS.items():
        for prefix in prefixes:
            if module == prefix or (prefix.endswith(".") and module.startswith(prefix)):
                return name
            if module == prefix.rstrip("."):  # a package's own __init__
                return name
    raise AssertionError(f"jaxrt._src.{module} has no layer: add it to LAYERS in tests/test_layers.py")


def test_every_module_has_a_layer():
    for module in _modules():
        _layer(module)


def test_the_layers_form_a_dag():
    def visit(name: str, path: tuple[str, ...]) -> None:
        assert name not in path, f"the layers have a cycle: {' -> '.join((*path, name))}"
        for below in LAYERS[name][1]:
            visit(below, (*path, name))

    for name in LAYERS:
        visit(name, ())


def test_no_import_climbs():
    """Each import points to the module's own layer or to one its layer may read."""
    wrong = []
    for module, target, _, line in _imports():
        if target.startswith("jaxrt") and target != "jaxrt.tags":
            wrong.append(f"{module}:{line} imports the public package ({target})")
            continue
        mine, theirs = _layer(module), _layer(target)
        if theirs != mine and theirs not in LAYERS[mine][1]:
            wrong.append(f"{module}:{line} ({mine}) imports {target} ({theirs})")
    assert not wrong, "upward or sideways arrows:\n" + "\n".join(wrong)


def test_local_imports_only_defer_optional_dependencies():
    """A function-local import hides an arrow from a reader of the module's head: only those that defer
    Numba or Triton (so that installs without them still import the package) are allowed."""
    hidden = [
        f"{m}:{line} imports {t} inside a function"
        for m, t, local, line in _imports()
        if local and (m, t) not in DEFERRED
    ]
    assert not hidden, "\n".join(hidden)


def test_no_cycle():
    graph: dict[str, set[str]] = {}
    for module, target, _, _ in _imports():
        graph.setdefault(module, set()).add(target)
    state: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycle = path[path.index(nxt) :] + [nxt] if nxt in path else [node, nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*path, nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


def test_traversal_reads_only_its_contract_the_kinds_and_the_formulas():
    """The rule docs/design.md states for ``traversal/``, spelled out (the layer table encodes it too)."""
    for module, target, _, line in _imports():
        if module.startswith("traversal."):
            assert _layer(target) in ("traversal", "kinds", "math"), f"{module}:{line} imports {target}"


def test_the_checker_sees_an_upward_arrow():
    """The parser resolves the import forms the package uses (absolute, ``from package import module``)."""
    modules = {"traversal.step": None, "scene_view": None, "leaves": None}
    absolute = ast.parse("from jaxrt._src.scene_view import scene_view").body[0]
    assert _target("traversal.step", "traversal", absolute, "scene_view", modules) == "scene_view"
    package = ast.parse("from jaxrt._src import leaves").body[0]
    assert _target("traversal.gpu", "traversal", package, "leaves", modules) == "leaves"
    public = ast.parse("import jaxrt as rt").body[0]
    assert _target("heatmap", "", public, "jaxrt", modules) == "jaxrt"
    tags = ast.parse("from jaxrt import tags").body[0]
    assert _target("shading", "", tags, "tags", modules) == "jaxrt.tags"
    assert _layer("scene_view") not in LAYERS["traversal"][1]
