"""The kind registry: one definition per primitive kind, and what is derived from it (coverage, tags)."""

from __future__ import annotations

import ast
import dataclasses
import enum
from pathlib import Path

import pytest

import jaxrt as rt
from jaxrt._src import intersector as intersector_module
from jaxrt._src import pipeline, result
from jaxrt._src.kinds import registry
from jaxrt._src.structures import GeometryInfo, PrimitiveAccelerationStructure
from jaxrt._src.traversal import analytic_rows, gpu, waves

SRC = Path(__file__).resolve().parents[1] / "jaxrt" / "_src"


def test_each_kind_is_defined_once_and_matches_the_public_enum():
    names = [k.name for k in registry.KINDS]
    assert len(set(names)) == len(names)
    for kind in registry.KINDS:
        assert registry.kind(kind.name) is kind
        assert rt.IntersectionType(kind.intersection_type).name == kind.name.upper()
        assert set(kind.coverage) == set(registry.BACKENDS)
        assert set(kind.fields.values()) <= set(kind.tags) | set(registry.SCENE_FIELDS.values())
    with pytest.raises(ValueError, match="unknown geometry kind 'disc'"):
        registry.kind("disc")


def test_geometries_name_their_kind_from_the_registry():
    pairs = [
        (rt.TriangleGeometry, registry.TRIANGLE),
        (rt.MotionTriangleGeometry, registry.TRIANGLE),
        (rt.BoundingBoxGeometry, registry.BOUNDING_BOX),
        (rt.MotionBoundingBoxGeometry, registry.BOUNDING_BOX),
        (rt.CurveGeometry, registry.CURVE),
        (rt.MotionCurveGeometry, registry.CURVE),
        (rt.SphereGeometry, registry.SPHERE),
        (rt.MotionSphereGeometry, registry.SPHERE),
    ]
    for cls, kind in pairs:
        assert cls.kind == kind.name


def test_leaf_arrays_are_fields_of_the_structure():
    fields = {f.name for f in dataclasses.fields(PrimitiveAccelerationStructure)}
    for kind in registry.KINDS:
        assert kind.leaf_arrays and kind.leaf_arrays[0].name in fields
        for array in kind.leaf_arrays:
            assert array.name in fields, array.name
            assert array.keyframes is None or array.keyframes in fields, array.keyframes
            assert array.fill in ("zeros", "empty box")


def test_tags_and_fields_derive_from_the_registry():
    public = {getattr(rt.tags, name).name for name in rt.tags.__all__ if name not in ("Tag", "max_levels")}
    assert registry.RESULT_TAGS == public | {"max_levels"}
    assert gpu.COVERED_TAGS == registry.RESULT_TAGS
    assert intersector_module._SUPPORTED_TAGS == registry.RESULT_TAGS
    assert result.FIELD_TAGS == registry.FIELD_TAGS
    assert result.FIELD_TAGS["curve_parameter"] == "curve_data"


def _info(kind, *, opaque=True, motion=False):
    return GeometryInfo(kind.name, opaque, None, motion)


TRI, BOX, CURVE = registry.TRIANGLE, registry.BOUNDING_BOX, registry.CURVE


def _user_function(ray, candidate):
    return True, 1.0


@pytest.mark.parametrize(
    "intersector, infos, backend, motion, levels, reason",
    [
        (rt.Intersector(), (_info(TRI),), "gpu", False, 0, None),
        (rt.Intersector(), (_info(TRI),), "cpu", False, 3, None),
        (rt.Intersector(), (_info(TRI),), "cpu", True, 0, None),
        (rt.Intersector(), (_info(TRI, motion=True),), "cpu", False, 0, None),
        (
            rt.Intersector(),
            (_info(TRI),),
            "cpu",
            True,
            2,
            "keyframe motion in instance structures is not covered by the CPU traversal",
        ),
        (
            rt.Intersector(intersection_functions={0: rt.intersection_functions.disk}),
            (_info(BOX, motion=True),),
            "cpu",
            False,
            0,
            "bounding-box geometry in a structure with keyframe motion is not covered by the CPU traversal",
        ),
        (rt.Intersector(), (_info(TRI, motion=True),), "gpu", False, 0, None),
        (rt.Intersector(), (_info(CURVE),), "cpu", False, 0, None),
        (
            rt.Intersector(),
            (_info(CURVE),),
            "cpu",
            False,
            1,
            "curves below instances are not covered by the CPU traversal",
        ),
        (
            rt.Intersector(),
            (_info(CURVE, motion=True),),
            "cpu",
            False,
            0,
            "curves in a structure with keyframe motion are not covered by the CPU traversal",
        ),
        (
            rt.Intersector(),
            (_info(CURVE),),
            "gpu",
            False,
            1,
            "curves below instances are not covered by the GPU kernel",
        ),
        (
            rt.Intersector(),
            (_info(CURVE, motion=True),),
            "gpu",
            False,
            0,
            "curves in a structure with keyframe motion are not covered by the GPU kernel",
        ),
        (
            rt.Intersector(intersection_functions={1: rt.intersection_functions.sphere}),
            (_info(CURVE), _info(BOX)),
            "gpu",
            False,
            0,
            "curves and bounding-box geometry in one structure are not covered by the GPU kernel",
        ),
        (
            rt.Intersector(intersection_functions={0: rt.intersection_functions.disk}),
            (_info(BOX),),
            "cpu",
            False,
            2,
            None,
        ),
        (
            rt.Intersector(intersection_functions={0: rt.intersection_functions.disk}),
            (_info(BOX),),
            "gpu",
            True,
            0,
            "bounding-box geometry in a structure with keyframe motion is not covered by the GPU kernel",
        ),
        (rt.Intersector(intersection_functions={0: _user_function}), (_info(BOX),), "gpu", False, 0, None),
        (
            rt.Intersector(intersection_functions={0: _user_function}),
            (_info(BOX),),
            "gpu",
            False,
            1,
            "bounding-box geometry with user intersection functions (geometry 0: _user_function) below instances, "
            "with keyframe motion or with curves or with spheres is not covered by the GPU kernel (it traces "
            "rt.intersection_functions.sphere, disk and capped_cylinder)",
        ),
        (
            rt.Intersector(intersection_functions={0: _user_function}),
            (_info(BOX),),
            "cpu",
            False,
            0,
            "bounding-box geometry with user intersection functions (geometry 0: _user_function) is not covered by "
            "the CPU traversal (it traces rt.intersection_functions.sphere, disk and capped_cylinder)",
        ),
        (rt.Intersector(filter=lambda c: True), (_info(TRI, opaque=False),), "gpu", False, 0, None),
        (rt.Intersector(filter=lambda c: True), (_info(TRI),), "cpu", False, 0, None),
        (
            rt.Intersector(filter=lambda c: True),
            (_info(TRI, opaque=False),),
            "cpu",
            False,
            0,
            "filters on non-opaque geometry are not covered by the CPU traversal",
        ),
        (
            rt.Intersector(filter=lambda c: True),
            (_info(TRI, opaque=False), _info(CURVE)),
            "gpu",
            False,
            0,
            "filters on non-opaque geometry below instances, with keyframe motion or with curves or with spheres are "
            "not covered by the GPU kernel",
        ),
    ],
)
def test_coverage_derives_from_the_kinds(intersector, infos, backend, motion, levels, reason):
    assert pipeline.kernel_declines(intersector, infos, backend, motion, levels) == reason


def test_waves_follow_the_kinds():
    assert waves.covers((_info(TRI), _info(BOX)))
    assert not waves.covers((_info(TRI), _info(CURVE)))
    assert not waves.covers((_info(TRI),), levels=1)
    assert not waves.covers((_info(TRI, motion=True),))
    assert not registry.waves_cover((_info(TRI),), "cpu")
    user = rt.Intersector(intersection_functions={0: _user_function})
    assert registry.needs_jax(user, (_info(BOX),))
    alpha = rt.Intersector(filter=lambda c: True)
    assert registry.needs_jax(alpha, (_info(TRI, opaque=False),))
    assert not registry.needs_jax(alpha, (_info(TRI, opaque=False),), filter_decided=True)
    assert not registry.needs_jax(alpha, (_info(TRI),))


def test_no_module_compares_kinds_by_string():
    """Outside ``kinds/``, no comparison names a kind by its string (``g.kind == "curve"``)."""
    names = {k.name for k in registry.KINDS}
    found = []
    for path in sorted(SRC.rglob("*.py")):
        if "kinds" in path.relative_to(SRC).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                operands = [node.left, *node.comparators]
                for operand in operands:
                    values = operand.elts if isinstance(operand, ast.Tuple | ast.Set | ast.List) else [operand]
                    for v in values:
                        if isinstance(v, ast.Constant) and v.value in names:
                            found.append(f"{path.relative_to(SRC)}:{node.lineno} compares with {v.value!r}")
    assert not found, "\n".join(found)


#: The shared modules that reach a kind only through its ``Kind`` record (hooks) or by iterating over
#: ``registry.KINDS``: a kind added through the registry (spheres) is named in none of them.
KIND_FREE = (
    "leaves.py",
    "fields.py",
    "winding.py",
    "point_query.py",
    "checks.py",
    "pipeline.py",
    "kinds/__init__.py",
    "structures.py",
    "result.py",
    "../tags.py",
    "traversal/gpu.py",
    "traversal/cpu.py",
    "traversal/cpu_kernel.py",
    "traversal/triton_analytic.py",
    "traversal/triton_kernel.py",
)


@pytest.mark.parametrize("module", KIND_FREE)
def test_shared_modules_name_no_registry_kind(module):
    """The leaf tests, fields, point queries, checks, the pipeline, the build, the public enum and tags and the
    compiled loops import neither ``SPHERE`` nor the sphere kind's module: a new kind reaches them through its
    hooks and the registry."""
    tree = ast.parse((SRC / module).read_text())
    imported, named = [], []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            imported += [(node.module or "") + "." + a.name for a in node.names]
        elif isinstance(node, ast.Attribute):
            named.append("." + node.attr)
        elif isinstance(node, ast.Name):  # a bare ``SPHERE`` only where imported (the kernel's SPHERE: sphere caps)
            named.append(node.id)
    names = imported + [n for n in named if not n == "SPHERE" or any(i.endswith(".SPHERE") for i in imported)]
    assert not [n for n in names if n == "SPHERE" or n.endswith(".SPHERE") or n.endswith("kinds.sphere")], module


def test_functions_decline_before_filters():
    both = rt.Intersector(intersection_functions={1: _user_function}, filter=lambda c: True)
    infos = (_info(TRI, opaque=False), _info(BOX))
    assert "user intersection functions" in pipeline.kernel_declines(both, infos, "cpu")
    assert pipeline.kernel_declines(both, infos, "gpu") is None


def test_public_names_derive_from_the_registry():
    """``rt.IntersectionType`` has one member per kind, and ``rt.tags`` each kind's own tags."""
    members = {m.name: m.value for m in rt.IntersectionType}
    assert members == {"NONE": 0, **{k.name.upper(): k.intersection_type for k in registry.KINDS}}
    assert issubclass(rt.IntersectionType, enum.IntEnum) and rt.IntersectionType.SPHERE == 4
    for kind in registry.KINDS:
        assert kind.doc and kind.geometry and kind.float_array
        assert set(kind.tag_docs) <= set(kind.tags)
        for name in kind.tag_docs:
            assert getattr(rt.tags, name) == rt.tags.Tag(name) and name in rt.tags.__all__
    assert rt.tags.KNOWN == registry.RESULT_TAGS
    assert [k.geometry for k in registry.KINDS] == [c.__name__ for c in (rt.TriangleGeometry, rt.BoundingBoxGeometry, rt.CurveGeometry, rt.SphereGeometry)]  # fmt: skip


def test_analytic_rows_derive_from_the_registry():
    codes = [k.analytic.code for k in registry.KINDS if k.analytic is not None]
    assert codes == [5] and analytic_rows.FORMULA_SHAPES == 1 << 5
    assert [k.analytic.code for k in analytic_rows.ROW_KINDS] == sorted(codes)
    for kind in analytic_rows.ROW_KINDS:
        assert kind.formula_leaves and kind.analytic.code >= 5 and analytic_rows.shape_bit(kind.analytic.code) != 3
    source = analytic_rows.triton_source()
    assert "    SHAPES: tl.constexpr = ANALYTIC & 39\n" in source
    assert "if (SHAPES & 32) != 0:\n        lanes = mask & (code == 5.0)" in source
    assert "h, t, _ = _sphere_ray_sphere(px, py, pz, radius, ox, oy, oz, dx, dy, dz, t_min, t_max)" in source


def test_generated_dispatch_takes_a_new_kind():
    """A second kind with an analytic row (here the sphere formula again, code 6) is dispatched by the generated
    Numba functions without an edit to the loop."""
    numba = pytest.importorskip("numba")
    import numpy as np

    from jaxrt._src import formulas

    shapes = (*analytic_rows.SHAPES, analytic_rows.Shape(6, "sphere", "ray_sphere", ("px", "py", "pz", "radius"), 3))
    u = {f"_U{i}": np.uint64(i) for i in range(1, 8)}
    tests = lambda module, name: getattr(formulas.instance(module, "numba"), name)  # noqa: E731
    source = analytic_rows.numba_source(shapes)
    module = analytic_rows.compile_source("test_new_kind", source, dict(np=np, **u, tests=tests), shapes)
    analytic = numba.njit(module.analytic)
    is_formula_row = numba.njit(module.is_formula_row)
    formula_row = numba.njit(module.formula_row)
    ray_sphere = formulas.instance("sphere", "numba").ray_sphere
    inf = np.inf
    for code in (5.0, 6.0):
        row = np.array([0.0, 0.0, 0.0, code, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0])
        assert is_formula_row(row[3])
        args = (0.0, 0.0, -5.0, 0.0, 0.0, 1.0, 0.0, inf)
        want = ray_sphere(0.0, 0.0, 0.0, 2.0, *args)[:2]
        assert want == (True, 3.0)
        assert analytic(row, *args, 1.0, inf) == want
        assert formula_row(row, np.uint64(0), *args, inf) == want
    assert not is_formula_row(1.0) and not is_formula_row(0.0)
    disk = np.array([0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0])
    assert analytic(disk, 0.0, 0.0, -5.0, 0.0, 0.0, 1.0, 0.0, inf, 1.0, inf) == (True, 5.0)
