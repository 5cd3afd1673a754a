"""The kind registry: one definition per primitive kind, and what is derived from it (coverage, tags)."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

import jaxrt as rt
from jaxrt._src import intersector as intersector_module
from jaxrt._src import pipeline, result
from jaxrt._src.kinds import registry
from jaxrt._src.structures import GeometryInfo, PrimitiveAccelerationStructure
from jaxrt._src.traversal import gpu, waves

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
KIND_FREE = ("leaves.py", "fields.py", "winding.py", "point_query.py", "checks.py", "pipeline.py", "kinds/__init__.py")


@pytest.mark.parametrize("module", KIND_FREE)
def test_shared_modules_name_no_registry_kind(module):
    """The leaf tests, fields, point queries, checks and the pipeline import neither ``SPHERE`` nor the sphere
    kind's module: a new kind reaches them through its hooks."""
    tree = ast.parse((SRC / module).read_text())
    named = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            named += [(node.module or "") + "." + a.name for a in node.names]
        elif isinstance(node, ast.Name | ast.Attribute):
            named.append(node.id if isinstance(node, ast.Name) else node.attr)
    assert not [n for n in named if n == "SPHERE" or n.endswith(".SPHERE") or n.endswith("kinds.sphere")], module


def test_functions_decline_before_filters():
    both = rt.Intersector(intersection_functions={1: _user_function}, filter=lambda c: True)
    infos = (_info(TRI, opaque=False), _info(BOX))
    assert "user intersection functions" in pipeline.kernel_declines(both, infos, "cpu")
    assert pipeline.kernel_declines(both, infos, "gpu") is None
