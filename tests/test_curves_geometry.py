"""CurveGeometry: validation with named errors, enums, Metal's basis conventions, links between segments."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src.curves import bezier_segments, pack_segments, segment_links

POINTS = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 0], [4, 0, 0]], np.float32)
RADII = np.full(5, 0.1, np.float32)


def make(**overrides):
    args = dict(control_points=POINTS, radii=RADII, indices=[0, 1], basis="catmull_rom", control_point_count=4)
    args.update(overrides)
    return rt.CurveGeometry(args.pop("control_points"), args.pop("radii"), args.pop("indices"), **args)


@pytest.mark.parametrize(
    "basis,count", [("bezier", 2), ("bezier", 5), ("bspline", 2), ("catmull_rom", 3), ("linear", 3), ("linear", 4)]
)
def test_basis_count_combinations_are_rejected(basis, count):
    with pytest.raises(ValueError, match=f"control_point_count={count} is not valid for basis '{basis}'"):
        make(basis=basis, control_point_count=count, indices=[0])


@pytest.mark.parametrize(
    "overrides,error,match",
    [
        (dict(indices=[0, 2]), ValueError, r"indices\[1\] = 2 starts a 4-point segment that runs past the 5"),
        (dict(indices=[-1]), ValueError, r"indices\[0\] = -1"),
        (dict(indices=[]), ValueError, "indices is empty"),
        (dict(indices=[[0]]), ValueError, "indices must have shape"),
        (dict(indices=[0.0]), TypeError, "indices must have an integer dtype"),
        (dict(radii=np.array([0.1, -0.2, 0.1, 0.1, 0.1], np.float32)), ValueError, r"radii\[1\] = -0.2"),
        (dict(radii=np.array([0.1, np.nan, 0.1, 0.1, 0.1], np.float32)), ValueError, "radii has a non-finite"),
        (dict(radii=np.full(4, 0.1, np.float32)), ValueError, r"radii must have shape \(P,\) = \(5,\)"),
        (dict(control_points=POINTS[:, :2]), ValueError, r"control_points must have shape \(P, 3\)"),
        (dict(control_points=np.zeros((0, 3), np.float32), radii=np.zeros(0, np.float32)), ValueError, "empty"),
        (dict(control_points=np.where(POINTS == 2, np.inf, POINTS)), ValueError, "control_points has a non-finite"),
        (dict(control_points=POINTS.astype(np.int32)), TypeError, "control_points must be float32 or float64"),
        (dict(basis="hermite"), ValueError, "basis must be one of 'bezier', 'catmull_rom', 'bspline', 'linear'"),
        (dict(curve_type="tube"), ValueError, "curve_type must be one of 'round', 'flat'"),
        (dict(end_caps="cone"), ValueError, "end_caps must be one of 'none', 'disk', 'sphere'"),
        (dict(control_point_count=4.0), TypeError, "control_point_count must be an int"),
        (dict(primitive_data=np.zeros(3)), ValueError, "leading dimension must equal the primitive count 2"),
    ],
)
def test_bad_inputs_name_the_argument(overrides, error, match):
    with pytest.raises(error, match=match):
        make(**overrides)


def test_enums_accept_members_and_names():
    a = make(basis=rt.CurveBasis.CATMULL_ROM, curve_type=rt.CurveType.FLAT, end_caps=rt.CurveEndCaps.SPHERE)
    b = make(basis="CATMULL_ROM", curve_type="flat", end_caps="Sphere")
    assert (a.basis, a.curve_type, a.end_caps) == (b.basis, b.curve_type, b.end_caps)
    for enum in (rt.CurveBasis, rt.CurveType, rt.CurveEndCaps):
        for member in enum:
            assert member.__doc__ and member.__doc__ != enum.__doc__  # each member documents itself


def _evaluate(bezier, u):
    w = np.array([(1 - u) ** 3, 3 * u * (1 - u) ** 2, 3 * u**2 * (1 - u), u**3])
    return w @ np.asarray(bezier, np.float64)


def test_metal_conventions():
    """Catmull-Rom segments span their 2nd to 3rd point; cubic B-splines start at (p0 + 4 p1 + p2) / 6;
    quadratic B-splines at (p0 + p1) / 2; Bezier and linear at their first point."""
    p = POINTS.astype(np.float64)
    cases = [
        ("catmull_rom", 4, p[1], p[2]),
        ("bspline", 4, (p[0] + 4 * p[1] + p[2]) / 6, (p[1] + 4 * p[2] + p[3]) / 6),
        ("bspline", 3, (p[0] + p[1]) / 2, (p[1] + p[2]) / 2),
        ("bezier", 4, p[0], p[3]),
        ("bezier", 3, p[0], p[2]),
        ("linear", 2, p[0], p[1]),
    ]
    for basis, count, start, end in cases:
        bezier = bezier_segments(make(basis=basis, control_point_count=count, indices=[0]))[0]
        np.testing.assert_allclose(_evaluate(bezier, 0.0)[:3], start, atol=1e-6, err_msg=basis)
        np.testing.assert_allclose(_evaluate(bezier, 1.0)[:3], end, atol=1e-6, err_msg=basis)
    # The Catmull-Rom curve passes through its control points with the tangent (p2 - p0) / 2.
    bezier = bezier_segments(make(indices=[0]))[0]
    np.testing.assert_allclose(3 * (bezier[1] - bezier[0])[:3], (p[2] - p[0]) / 2, atol=1e-6)


def test_links_between_segments():
    # Bezier segments share end points (step 3); Catmull-Rom ones overlap (step 1).
    bezier = rt.CurveGeometry(
        np.zeros((10, 3), np.float32), np.ones(10, np.float32), [6, 0, 3], basis="bezier", control_point_count=4
    )
    has_previous, has_next, _ = segment_links(bezier, bezier_segments(bezier))
    np.testing.assert_array_equal(has_previous, [True, False, True])
    np.testing.assert_array_equal(has_next, [False, True, True])
    chain = make(indices=[0, 1])
    has_previous, has_next, previous = segment_links(chain, bezier_segments(chain))
    np.testing.assert_array_equal(has_previous, [False, True])
    np.testing.assert_array_equal(has_next, [True, False])
    # The predecessor's end derivative equals the segment's own start derivative (C1 continuity).
    own = 3 * (bezier_segments(chain)[1, 1] - bezier_segments(chain)[1, 0])
    np.testing.assert_allclose(previous[1], own, atol=1e-6)


def test_pytree_and_jit():
    geometry = make(end_caps="disk", curve_type="flat")
    leaves, treedef = jax.tree_util.tree_flatten(geometry)
    again = jax.tree_util.tree_unflatten(treedef, leaves)
    assert again.info == geometry.info and again.primitive_count == 2
    segments, flags = jax.jit(pack_segments)(geometry)
    assert segments.shape == (2, 6, 4) and flags.dtype == jnp.int32
    # Traced arrays: shapes are still checked, values are not.
    jax.jit(lambda points: make(control_points=points).control_points)(POINTS)
