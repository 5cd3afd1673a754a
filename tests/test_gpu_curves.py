"""Round curve segments in the GPU kernel, against the portable traversal and a float64 reference.

As in ``test_gpu_instanced.py``: the kernel runs in Triton's interpreter on the CPU (in a fresh process) or on
a CUDA GPU, launched through the same :class:`gpu.KernelCall`. The reference is the portable traversal of the
same scene view with the portable leaf tests (``curve.intersect``): both make the same decisions step for step,
so the leaf (hit or miss, and which segment) and the traversal counters are equal. Distances agree within the
float32 distance tolerance of ``tests/reference.py`` (8 eps relative): the kernel evaluates ``curve.intersect``'s
formulas in its order of operations without contraction, while XLA contracts some multiply-adds into fused
ones (measured: up to 5 ulps apart, about half the hits bit-identical). Both are also checked per ray against
the float64 reference of ``jaxrt.bench.curves`` (the nearest hit, within the bounds of
``tests/test_curves_primitive.py``).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import TOLERANCE
from test_curves_primitive import DISTANCE, EPS32, ROUNDING, aimed_rays
from test_curves_structure import hair
from test_gpu_instanced import (
    INTERPRETED,
    LAUNCHES,
    ON_GPU,
    assert_same_fields,
    kernel_launches_here,
    kernel_test,
    run_kernel_tests_in_interpreter,
)

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import pipeline
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import drivers, gpu
from jaxrt.bench.curves import host_segments, reference_hits

kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")
ALL_RAYS = np.uint32(0xFFFFFFFF)
RTOL = TOLERANCE[np.dtype(np.float32)].distance
CURVE = int(rt.IntersectionType.CURVE)
TRIANGLE = int(rt.IntersectionType.TRIANGLE)


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__, "not interpreter and not kernel_ir")


# --- which scenes the kernel takes (no Triton needed) ----------------------------------------------------------


def _infos(structure):
    return tuple(structure.geometry_info)


def test_kernel_declines_instanced_and_moving_curves():
    """Round and flat curves in a static primitive structure are the kernel's (and the CPU traversal's); curves
    below instances or with keyframe motion are declined, each with its reason."""
    round_ = rt.build_primitive_structure(hair(seed=1, strands=2))
    flat = rt.build_primitive_structure(hair(seed=1, strands=2, curve_type="flat"))
    plain = rt.Intersector()
    assert pipeline.kernel_declines(plain, _infos(round_), "gpu") is None
    assert pipeline.kernel_declines(plain, _infos(flat), "gpu") is None
    assert pipeline.kernel_declines(rt.Intersector(curve_type="flat"), _infos(round_), "gpu") is None
    assert "below instances" in pipeline.kernel_declines(plain, _infos(flat), "gpu", levels=1)
    assert "below instances" in pipeline.kernel_declines(plain, _infos(round_), "gpu", levels=1)
    assert "keyframe motion" in pipeline.kernel_declines(plain, _infos(round_), "gpu", motion=True)
    assert pipeline.kernel_declines(plain, _infos(round_), "cpu") is None  # test_cpu_curves.py
    assert pipeline.kernel_declines(plain, _infos(flat), "cpu") is None
    # A curve intersector no longer rules the kernel out on its own (the scene decides).
    if jax.default_backend() != "gpu":
        assert "default JAX backend" in gpu.unavailable_reason(rt.Intersector(curve_type="round"))


def test_every_tag_is_covered_by_the_kernel():
    """Result fields are recomputed in JAX from the leaf, distance and instance chain the kernel returns, so no
    tag may send a scene the kernel covers to the portable traversal (``curve_data`` once did, hair and all)."""
    names = {tag.name for tag in vars(rt.tags).values() if isinstance(tag, rt.tags.Tag)}
    names.add(rt.tags.max_levels(1).name)
    assert {"curve_data", "normal", "triangle_data"} <= names
    assert names <= gpu.COVERED_TAGS


def test_forced_gpu_backend_names_the_reason():
    strands = rt.build_primitive_structure(hair(seed=2, strands=2, curve_type="flat"))
    structure = rt.build_instance_structure([strands], rt.Instances([0], np.eye(4, dtype=np.float32)[None, :3]))
    origin, direction = aimed_rays(np.random.default_rng(0), hair(seed=2, strands=2), 4)
    intersector = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(1), backend="gpu")
    with pytest.raises(ValueError, match="curves below instances are not covered by the GPU kernel"):
        intersector.intersect(rt.Ray(jnp.asarray(origin), jnp.asarray(direction)), structure)


def test_curve_rows_hold_the_packed_segments():
    """96 bytes per leaf: the control points, the base point, the flags' bits and the previous derivative."""
    from jaxrt._src.traversal import packed

    structure = rt.build_primitive_structure(hair(seed=3, strands=2, end_caps="sphere"))
    view = scene_view(structure)
    rows = np.asarray(packed.pack_curves(view.leaves.curve, view.leaves.curve_flags))
    segment = np.asarray(view.leaves.curve)
    assert rows.shape == (segment.shape[0], packed.CURVE_WIDTH) and rows.dtype == np.float32
    np.testing.assert_array_equal(rows[:, :16], segment[:, :4].reshape(-1, 16))
    np.testing.assert_array_equal(rows[:, 16:19], segment[:, 4, :3])
    np.testing.assert_array_equal(rows[:, 19].view(np.int32), np.asarray(view.leaves.curve_flags))
    np.testing.assert_array_equal(rows[:, 20:], segment[:, 5])


# --- the curve leaf test alone, against the CPU traversal -----------------------------------------------------------


def _moved(geometry, shift):
    """``geometry`` (curves or triangles) moved by ``shift``."""
    if isinstance(geometry, rt.CurveGeometry):
        return rt.CurveGeometry(geometry.control_points + shift, geometry.radii, geometry.indices,
                                basis=geometry.basis.value, control_point_count=geometry.control_point_count,
                                curve_type=geometry.curve_type.value, end_caps=geometry.end_caps.value)  # fmt: skip
    return rt.TriangleGeometry(np.asarray(geometry.vertices) + shift)


#: The scenes of :func:`test_curve_leaf_equals_the_cpu_traversal` (:func:`_leaf_scenes`).
LEAF_SCENES = ("round", "flat", "mixed", "mixed-far", "round-far", "mixed-5-pieces", "mixed-no-newton")


def _leaf_scenes():
    """``{name: (geometries, intersector, far)}`` of :data:`LEAF_SCENES`: round segments of every basis and cap
    with triangles (the round test only), ribbons of every basis and cap (the flat test only), kinked round and
    flat chains with round tubes (both tests, per row), those far from the origin, and static options (pieces not
    a power of two, no Newton steps)."""
    triangles = rt.TriangleGeometry(np.random.default_rng(40).uniform(-1, 2, (24, 3)).astype(np.float32))
    round_ = [triangles, hair(seed=41, strands=2, basis="bezier", end_caps="sphere"),
              hair(seed=42, strands=2, basis="catmull_rom", end_caps="none"),
              hair(seed=43, strands=2, basis="bspline", end_caps="disk")]  # fmt: skip
    flat = [hair(seed=44, strands=2, basis="bezier", end_caps="disk", curve_type="flat"),
            hair(seed=45, strands=2, basis="catmull_rom", end_caps="sphere", curve_type="flat"),
            hair(seed=46, strands=2, basis="bspline", count=3, end_caps="none", curve_type="flat"),
            hair(seed=47, strands=2, basis="linear", count=2, end_caps="disk", curve_type="flat")]  # fmt: skip
    mixed = [_kinked("sphere")[0], _flat_kinked("disk")[1], hair(seed=48, strands=2, end_caps="disk")]
    plain = rt.Intersector()
    pieces = rt.Intersector(curve_options=rt.CurveOptions(pieces=5, iterations=2, approach_iterations=1))
    scenes = [(round_, plain, 0.0), (flat, plain, 0.0), (mixed, plain, 0.0), (mixed, plain, 1.1e4),
              (round_, plain, 1.3e3), (mixed, pieces, 0.0), (mixed, rt.Intersector(curve_options=rt.CurveOptions(iterations=0)), 0.0)]  # fmt: skip
    return dict(zip(LEAF_SCENES, scenes, strict=True))


def _leaf_pairs(geometries, intersector, far: float, seed: int):
    """Lanes of (ray, leaf) pairs of a structure of ``geometries`` (moved ``far`` along a fixed direction): up to
    96 hitting pairs, 40 misses (many grazing: the rays pass within 1.5 radii of the centre lines), 16 triangle
    leaves; intervals that end or start within 1% of the hit on a quarter of the hitting lanes; lanes that test
    no leaf; three segments made degenerate (a point, zero radius, a zero start tangent). Returns the kernel's
    rows and ray block, the static options, and per lane the CPU traversal's ``(hit, distance)``, or where the
    lane tests no curve the hit and distance it starts from (a triangle test's answer)."""
    from jaxrt._src.traversal import cpu, cpu_curves, packed

    shift = np.float32(far) * np.array([1.0, -0.37, 0.61], np.float32)
    geometries = [_moved(g, shift) if far else g for g in geometries]
    view = scene_view(rt.build_primitive_structure(geometries))
    static = gpu.curve_leaves(view, leaf_tests.curve_configuration(intersector, view)).options
    segments = np.array(view.leaves.curve, np.float32)
    flags = np.asarray(view.leaves.curve_flags).astype(np.int32)
    curve_leaves = np.nonzero(flags & 32)[0]
    segments[curve_leaves[0], :4, :3] = 0.0  # every control point at the base point
    segments[curve_leaves[1], :4, 3] = 0.0  # zero radius
    segments[curve_leaves[2], 1, :] = segments[curve_leaves[2], 0, :]  # a zero start tangent
    rows = np.asarray(packed.pack_curves(jnp.asarray(segments), jnp.asarray(flags)))
    rng = np.random.default_rng(seed)
    rays = [aimed_rays(rng, g, 16) for g in geometries if isinstance(g, rt.CurveGeometry)]
    origin = np.concatenate([o for o, _ in rays])
    direction = np.concatenate([d for _, d in rays])
    frame = np.asarray(cpu.curve_frames(jnp.asarray(origin), jnp.asarray(direction)))
    params = np.asarray(cpu.curve_params(static), np.int64)

    def numba(ray, leaf, lo, hi):
        n = len(ray)
        out = [np.empty(n, bool), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.int64)]
        cpu_curves.pairs(np.ascontiguousarray(segments[leaf]), flags[leaf], origin[ray], frame[ray], lo, hi, params,
                         np.float32(np.inf), *out)  # fmt: skip
        return out[0], out[1]

    ray, leaf = np.repeat(np.arange(len(origin)), len(curve_leaves)), np.tile(curve_leaves, len(origin))
    hit, distance = numba(ray, leaf, np.zeros(len(ray), np.float32), np.full(len(ray), np.inf, np.float32))
    misses = rng.permutation(np.nonzero(~hit)[0])[:40]
    chosen = np.concatenate([rng.permutation(np.nonzero(hit)[0])[:96], misses])
    ray, leaf, distance = ray[chosen], leaf[chosen], distance[chosen]
    triangle_leaves = np.nonzero((flags & 32) == 0)[0]
    if len(triangle_leaves):
        extra = rng.integers(0, len(origin), 16)
        ray, leaf = np.concatenate([ray, extra]), np.concatenate([leaf, rng.choice(triangle_leaves, 16)])
        distance = np.concatenate([distance, np.full(16, np.inf, np.float32)])
    pad = -len(ray) % 32
    ray, leaf = np.concatenate([ray, ray[:pad]]), np.concatenate([leaf, leaf[:pad]])
    distance = np.concatenate([distance, distance[:pad]])
    n = len(ray)
    lo, hi = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    near = np.isfinite(distance)
    ends = near & (rng.random(n) < 0.15)
    starts = near & ~ends & (rng.random(n) < 0.1)
    hi[ends] = (distance[ends] * rng.uniform(0.99, 1.01, ends.sum())).astype(np.float32)
    lo[starts] = (distance[starts] * rng.uniform(0.99, 1.01, starts.sum())).astype(np.float32)
    test = rng.random(n) > 0.1
    hit_in = rng.random(n) < 0.3
    distance_in = np.where(hit_in, rng.uniform(1.0, 30.0, n), np.inf).astype(np.float32)
    block = np.zeros((34, n), np.float32)
    block[:3] = origin[ray].T
    block[3], block[4], block[5], block[6], block[7] = lo, hi, test, hit_in, distance_in
    block[24:] = frame[ray].T
    hit, distance = numba(ray, leaf, lo, hi)
    curve = test & ((flags[leaf] & 32) != 0)
    return rows[leaf], block, static, np.where(curve, hit, hit_in), np.where(curve, distance, distance_in)


def _run_leaf_pairs(rows, block, static):
    """The kernel's curve leaf test on every lane of ``block`` (:func:`curve_leaf_kernels.leaf_pairs`):
    ``(hit, distance)``."""
    from curve_leaf_kernels import leaf_pairs

    n = block.shape[1]
    pieces, iterations, approach, tolerance, disk, sphere, flat = static
    params = dict(LANES=32, PIECES=pieces, ITERATIONS=iterations, APPROACH=approach, TOLERANCE=tolerance,
                  DISK=bool(disk), SPHERE=bool(sphere), FLAT=flat)  # fmt: skip
    if ON_GPU:
        import jax_triton as jt

        shapes = [jax.ShapeDtypeStruct((n,), jnp.int32), jax.ShapeDtypeStruct((n,), jnp.float32)]
        hit, distance = jt.triton_call(jnp.asarray(rows), jnp.asarray(block), n, kernel=leaf_pairs, out_shape=shapes,
                                       grid=(n // 32,), num_warps=1, num_stages=1, enable_fp_fusion=False, **params)  # fmt: skip
        return np.asarray(hit) != 0, np.asarray(distance)
    from test_gpu_instanced import _HostArray

    outs = [np.full(n, -7, np.int32), np.full(n, np.nan, np.float32)]
    leaf_pairs[(n // 32,)](_HostArray(rows), _HostArray(block), n, *(_HostArray(o) for o in outs), **params)
    return outs[0] != 0, outs[1]


@kernel_test
@pytest.mark.parametrize("name", LEAF_SCENES)
def test_curve_leaf_equals_the_cpu_traversal(name):
    """The kernel's curve leaf test (the shared formula's Triton instance) gives the CPU traversal's hits and
    distances (the formula's Numba instance) bit for bit: round and flat segments of every basis and cap, grazing rays, intervals ending or starting at the hit,
    degenerate segments, strands far from the origin, static options; lanes that test no curve keep the
    triangle test's answer. (The curve parameter is not an output of the kernel's leaf test: the result fields
    re-intersect the leaf in JAX; ``tests/test_formulas.py`` compares the formula's ``u`` across backends.)"""
    geometries, intersector, far = _leaf_scenes()[name]
    seed = 50 + LEAF_SCENES.index(name)
    rows, block, static, want_hit, want_distance = _leaf_pairs(geometries, intersector, far, seed)
    hit, distance = _run_leaf_pairs(rows, block, static)
    np.testing.assert_array_equal(hit, want_hit, err_msg=f"{name}: hit, kernel vs CPU traversal")
    np.testing.assert_array_equal(distance.view(np.int32), want_distance.view(np.int32), err_msg=f"{name}: t")
    curve = (block[5] != 0) & ((rows[:, 19].view(np.int32) & 32) != 0)
    assert (hit & curve).sum() >= 25 and (~hit & curve).sum() >= 30, name


# --- the kernel's tests -------------------------------------------------------------------------------------------

COMBOS = [("bezier", 4, "sphere"), ("bezier", 3, "disk"), ("catmull_rom", 4, "none")]
COMBOS += [("bspline", 4, "disk"), ("bspline", 3, "sphere"), ("linear", 2, "sphere")]


def _rays(geometry, n: int, seed: int, *, t_min=None, t_max=None, disabled: int = 0):
    origin, direction = aimed_rays(np.random.default_rng(seed), geometry, n)
    lo = np.zeros(n, np.float32) if t_min is None else t_min.astype(np.float32)
    hi = np.full(n, np.inf, np.float32) if t_max is None else t_max.astype(np.float32)
    enabled = np.ones(n, bool)
    if disabled:
        enabled[-disabled:] = False
    return origin, direction, lo, hi, enabled


def check(structure, ray_args, intersector: rt.Intersector | None = None, *, any_hit: bool = False):
    """The kernel against the portable traversal of the same view: equal leaves and counters, distances within
    the float32 distance tolerance."""
    intersector = intersector or rt.Intersector()
    view = scene_view(structure)
    origin, direction, t_min, t_max, enabled = (jnp.asarray(a) for a in ray_args)
    mask = jnp.full(origin.shape[:1], ALL_RAYS, jnp.uint32)
    geometry = (origin, direction, t_min, t_max, enabled, mask)
    curves = gpu.curve_leaves(view, leaf_tests.curve_configuration(intersector, view))
    got = gpu.trace_scene(view.traversal, view.layout, *geometry, any_hit=any_hit, cull=intersector.cull, curves=curves)
    tester = leaf_tests.leaf_tester(intersector, view)
    fn = functools.partial(drivers.traverse, view.traversal, view.layout, tester, any_hit=any_hit)
    want = jax.jit(jax.vmap(fn))(*geometry)
    for name in ("leaf", "nodes_visited", "primitives_tested"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=RTOL, atol=0)
    assert not np.asarray(got.stack_overflow).any()
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    return np.asarray(got.leaf), np.asarray(got.distance)


def check_reference(geometry, ray_args, leaf, distance):
    """Per ray of a structure of ``geometry`` alone, the kernel's nearest hit against the float64 reference
    over every segment (rays whose reference is ambiguous at some segment are skipped)."""
    origin, direction, t_min, t_max, enabled = ray_args
    segments = host_segments(geometry)
    r, s = len(origin), segments.points.shape[0]
    ray_index, segment_index = np.repeat(np.arange(r), s), np.tile(np.arange(s), r)
    radius = float(np.max(np.asarray(geometry.radii)))
    points = np.asarray(geometry.control_points, np.float64)
    scale = np.max(np.linalg.norm(points[None] - origin[:, None], axis=-1), axis=1)
    rounding = ROUNDING * EPS32 * scale
    lo = np.asarray(t_min, np.float64)
    hi = np.where(enabled, np.asarray(t_max, np.float64), -np.inf)
    ref = reference_hits(
        origin, direction, lo, hi, segments, ray_index, segment_index, band=1e-2 * radius + rounding.max()
    )
    ref_t = np.where(ref.hit & enabled[ray_index], ref.distance, np.inf).reshape(r, s)
    decided = ~ref.ambiguous.reshape(r, s).any(axis=1)
    nearest = ref_t.min(axis=1)
    hit = leaf >= 0
    allowed = (DISTANCE * radius + rounding) / np.linalg.norm(direction.astype(np.float64), axis=1)
    wrong = decided & (hit != np.isfinite(nearest))
    both = decided & hit & np.isfinite(nearest)
    wrong |= both & (np.abs(np.where(both, distance - nearest, 0.0)) > allowed)
    assert not wrong.any(), f"rays {np.nonzero(wrong)[0][:8]} differ from the float64 reference"
    assert decided.sum() >= 0.8 * r and both.sum() >= 0.5 * r
    return int(both.sum())


@kernel_test
@pytest.mark.parametrize(("basis", "count", "caps"), COMBOS)
def test_every_basis_and_cap(basis, count, caps, kernel_here):
    """Every basis and control point count (all cubic Bezier after conversion; linear with its exact one-piece
    test), each end cap kind, with interval limits and disabled rays."""
    geometry = hair(seed=len(basis) + count, strands=3, basis=basis, count=count, end_caps=caps)
    rng = np.random.default_rng(count)
    n = 32
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), 0.0)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), np.inf)
    ray_args = _rays(geometry, n, seed=count + 7, t_min=t_min, t_max=np.maximum(t_max, t_min), disabled=2)
    leaf, distance = check(rt.build_primitive_structure(geometry), ray_args)
    assert (leaf[-2:] == -1).all()
    check_reference(geometry, ray_args, leaf, distance)


def _kinked(caps: str):
    """Two strands with sharp kinks at their joints (a linear and a Bezier chain): the joint spheres fill them."""
    linear = np.array([[0, 0, 0], [1, 0, 0], [1.1, 1, 0], [2, 1.2, 0.3]], np.float32)
    bezier = np.array([[0, 0, 1], [0.4, 0.1, 1], [0.8, 0, 1], [1, 0, 1], [1.1, 0.4, 1], [1, 0.8, 1], [1.2, 1, 1]])
    return (
        rt.CurveGeometry(linear, np.full(4, 0.08, np.float32), np.arange(3), basis="linear", control_point_count=2,
                         end_caps=caps),
        rt.CurveGeometry(bezier.astype(np.float32), np.full(7, 0.1, np.float32), np.array([0, 3]), basis="bezier",
                         control_point_count=4, end_caps=caps),
    )  # fmt: skip


@kernel_test
def test_kinked_joints_with_triangles_any_hit_and_intervals(kernel_here):
    """Kink joints, mixed with triangles in one structure (each leaf takes its kind's test), nearest and any
    hit; rays aimed at the joints."""
    linear, bezier = _kinked("sphere")
    rng = np.random.default_rng(5)
    triangles = rt.TriangleGeometry(rng.uniform(-1, 2.5, (24, 3)).astype(np.float32))
    structure = rt.build_primitive_structure([triangles, bezier])
    n = 64
    joints = np.array([[1, 0, 1]], np.float64)
    target = joints + rng.normal(scale=0.1, size=(n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = (target - 8.0 * direction).astype(np.float32)
    t_max = np.where(rng.random(n) < 0.25, rng.uniform(6.0, 9.0, n), np.inf).astype(np.float32)
    ray_args = (origin, direction.astype(np.float32), np.zeros(n, np.float32), t_max, np.ones(n, bool))
    leaf, distance = check(structure, ray_args)
    kinds = np.asarray(scene_view(structure).leaves.curve_flags)[np.maximum(leaf, 0)] != 0
    assert (kinds & (leaf >= 0)).sum() > 10 and (~kinds & (leaf >= 0)).sum() > 5
    check(structure, ray_args, any_hit=True)
    # The linear chain alone (one exact round cone per segment, no Newton) against the float64 reference.
    ray_args = _rays(linear, 32, seed=11)
    leaf, distance = check(rt.build_primitive_structure(linear), ray_args)
    check_reference(linear, ray_args, leaf, distance)


@kernel_test
def test_options_and_hit_lists(kernel_here):
    """Static curve options (pieces that are not a power of two, no Newton steps), the K nearest hits and
    counting every hit."""
    geometry = hair(seed=8, strands=3, end_caps="disk")
    ray_args = _rays(geometry, 32, seed=9)
    for options in (rt.CurveOptions(pieces=5, iterations=2, approach_iterations=1), rt.CurveOptions(iterations=0)):
        check(rt.build_primitive_structure(geometry), ray_args, rt.Intersector(curve_options=options))
    _check_hit_lists("round")


def _check_hit_lists(curve_type: str) -> None:
    """The K nearest hits and counting every hit, kernel against portable path, through stacked strands."""
    # Stacked strands (Bezier, and linear ones) that rays from above cross one after another.
    rng = np.random.default_rng(10)
    strands = [np.stack([np.linspace(0, 3, 7), 0.1 * np.sin(np.arange(7) + j), np.full(7, j)], -1) for j in range(4)]
    indices = np.concatenate([np.array([0, 3]) + 7 * j for j in range(4)])
    radii = np.full(28, 0.2, np.float32)
    stacked = [rt.CurveGeometry(np.concatenate(strands).astype(np.float32), radii, indices, basis="bezier",
                                control_point_count=4, end_caps="sphere", curve_type=curve_type)]  # fmt: skip
    stacked.append(rt.CurveGeometry(stacked[0].control_points + np.float32(0.5), radii, np.arange(27), basis="linear",
                                    control_point_count=2, curve_type=curve_type))  # fmt: skip
    structure = rt.build_primitive_structure(stacked)
    n = 32
    origin = np.stack([rng.uniform(0.1, 3.4, n), rng.uniform(-0.2, 0.7, n), np.full(n, 9.0)], -1).astype(np.float32)
    direction = np.stack([rng.normal(scale=0.02, size=n), rng.normal(scale=0.02, size=n), -np.ones(n)], -1)
    ray_args = (origin, direction.astype(np.float32), np.zeros(n, np.float32), np.full(n, np.inf, np.float32))
    view = scene_view(structure)
    mask = jnp.full((n,), ALL_RAYS, jnp.uint32)
    args = (*(jnp.asarray(a) for a in ray_args), jnp.ones(n, bool), mask)
    intersector = rt.Intersector()
    curves = gpu.curve_leaves(view, leaf_tests.curve_configuration(intersector, view))
    got = gpu.trace_scene(view.traversal, view.layout, *args, any_hit=False, cull=0, curves=curves, max_hits=3)
    tester = leaf_tests.leaf_tester(intersector, view)
    fn = functools.partial(drivers.traverse, view.traversal, view.layout, tester, any_hit=False, max_hits=3)
    want = jax.jit(jax.vmap(fn))(*args)
    np.testing.assert_array_equal(np.asarray(got.hits.leaf), np.asarray(want.hits.leaf))
    np.testing.assert_array_equal(np.asarray(got.hits.total), np.asarray(want.hits.total))
    np.testing.assert_allclose(np.asarray(got.hits.distance), np.asarray(want.hits.distance), rtol=RTOL, atol=0)
    assert (np.asarray(got.hits.total) > 1).sum() > 3
    # Counting every hit.
    got = gpu.trace_scene(view.traversal, view.layout, *args, any_hit=False, cull=0, curves=curves, count_all=True)
    fn = functools.partial(
        drivers.traverse, view.traversal, view.layout, tester, any_hit=False, max_hits=0, count_all=True
    )
    want = jax.jit(jax.vmap(fn))(*args)
    np.testing.assert_array_equal(np.asarray(got.hits.total), np.asarray(want.hits.total))
    assert (np.asarray(got.hits.total) > 3).sum() > 3


@kernel_test
@pytest.mark.parametrize(("curve_type", "end_caps", "seed"), [("round", "sphere", 12), ("flat", "disk", 22)])
def test_intersector_fields_and_gradients_from_the_kernel(curve_type, end_caps, seed, kernel_here, monkeypatch):
    """``Intersector(backend="gpu")`` on tubes or ribbons with triangles: the kernel picks the leaf, the result
    fields (``curve_parameter``, distances, ids) and the gradients come from the differentiable
    re-intersection, equal to the portable path's; ray masks (a zero mask misses)."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    geometry = hair(seed=seed, strands=3, end_caps=end_caps, curve_type=curve_type)
    rng = np.random.default_rng(seed + 1)
    triangles = rt.TriangleGeometry(rng.uniform(-2, 2, (12, 3)).astype(np.float32))
    origin, direction = aimed_rays(rng, geometry, 32)
    mask = np.full(32, ALL_RAYS)
    mask[:3] = 0
    tags = (rt.tags.curve_data, rt.tags.triangle_data)

    def run(backend, points, ray_origin):
        g = rt.CurveGeometry(points, geometry.radii, geometry.indices, basis="catmull_rom", control_point_count=4,
                             end_caps=end_caps, curve_type=curve_type)  # fmt: skip
        structure = rt.build_primitive_structure([triangles, g])
        ray = rt.Ray(ray_origin, jnp.asarray(direction), mask=jnp.asarray(mask))
        return rt.Intersector(*tags, backend=backend).intersect(ray, structure)

    args = (geometry.control_points, jnp.asarray(origin))
    got, want = run("gpu", *args), run("portable", *args)
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    types = np.asarray(want.type)
    assert (types == CURVE).sum() > 10 and (types[:3] == 0).all()
    assert_same_fields(got, want, rtol=1e-5)

    def loss(backend):
        def f(points, ray_origin):
            result = run(backend, points, ray_origin)
            hit = result.type == CURVE
            return jnp.sum(jnp.where(hit, result.distance + result.curve_parameter, 0.0))

        return jax.grad(f, argnums=(0, 1))(*args)

    for a, b in zip(loss("gpu"), loss("portable"), strict=True):
        assert np.isfinite(np.asarray(a)).all() and np.abs(np.asarray(b)).max() > 0
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


FLAT_COMBOS = [("bezier", 4, "sphere"), ("catmull_rom", 4, "disk"), ("bspline", 3, "none"), ("linear", 2, "disk")]


@kernel_test
@pytest.mark.parametrize(("basis", "count", "caps"), FLAT_COMBOS)
def test_flat_every_basis_and_cap(basis, count, caps, kernel_here):
    """Flat (ray-facing ribbon) segments of every basis, each end cap kind, with interval limits and disabled
    rays: the kernel against the portable path and the float64 reference."""
    geometry = hair(seed=len(basis) + count + 1, strands=3, basis=basis, count=count, end_caps=caps, curve_type="flat")
    rng = np.random.default_rng(count + 20)
    n = 32
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), 0.0)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(4.0, 12.0, n), np.inf)
    ray_args = _rays(geometry, n, seed=count + 27, t_min=t_min, t_max=np.maximum(t_max, t_min), disabled=2)
    structure = rt.build_primitive_structure(geometry)
    _aim_at_free_ends(structure, ray_args, 12, seed=count)
    leaf, distance = check(structure, ray_args)
    assert (leaf[-2:] == -1).all()
    check_reference(geometry, ray_args, leaf, distance)


def _aim_at_free_ends(structure, ray_args, k: int, seed: int) -> None:
    """Aims the first ``k`` rays (in place) at the strands' free ends, within about a radius (the caps)."""
    from jaxrt._src.primitives import curve

    view = scene_view(structure)
    bezier = np.asarray(curve.world_bezier(view.leaves.curve), np.float64)
    flags = np.asarray(view.leaves.curve_flags)
    curves = (flags & curve.IS_CURVE) != 0
    start, end = curves & ((flags & curve.HAS_PREVIOUS) == 0), curves & ((flags & curve.HAS_NEXT) == 0)
    ends = np.concatenate([bezier[start, 0], bezier[end, 3]])
    rng = np.random.default_rng(seed)
    pick = ends[rng.integers(0, len(ends), k)]
    target = pick[:, :3] + rng.normal(scale=0.5, size=(k, 3)) * np.abs(pick[:, 3:])
    direction = rng.normal(size=(k, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    ray_args[0][:k] = target - 6.0 * direction
    ray_args[1][:k] = direction


def _flat_kinked(caps: str):
    """:func:`_kinked`'s strands as ribbons."""
    return tuple(
        rt.CurveGeometry(g.control_points, g.radii, g.indices, basis=g.basis.value, control_point_count=count,
                         end_caps=caps, curve_type="flat")
        for g, count in zip(_kinked(caps), (2, 4), strict=True)
    )  # fmt: skip


@kernel_test
def test_flat_joints_mixed_with_round_and_triangles(kernel_here):
    """Ribbon joints (the ray-facing disks that fill an open kink) with triangles, nearest and any hit; round and
    flat segments in one structure (each row's flag picks its test); an intersector that makes every curve flat;
    static options (no Newton steps, pieces not a power of two); the K nearest hits and counting every hit."""
    linear, bezier = _flat_kinked("disk")
    rng = np.random.default_rng(25)
    triangles = rt.TriangleGeometry(rng.uniform(-1, 2.5, (24, 3)).astype(np.float32))
    structure = rt.build_primitive_structure([triangles, bezier, linear])
    n = 64
    joints = np.array([[1, 0, 1], [1, 0, 0], [1.1, 1, 0]], np.float64)[rng.integers(0, 3, n)]
    target = joints + rng.normal(scale=0.1, size=(n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = (target - 8.0 * direction).astype(np.float32)
    t_max = np.where(rng.random(n) < 0.25, rng.uniform(6.0, 9.0, n), np.inf).astype(np.float32)
    ray_args = (origin, direction.astype(np.float32), np.zeros(n, np.float32), t_max, np.ones(n, bool))
    leaf, _ = check(structure, ray_args)
    kinds = np.asarray(scene_view(structure).leaves.curve_flags)[np.maximum(leaf, 0)] != 0
    assert (kinds & (leaf >= 0)).sum() > 10 and (~kinds & (leaf >= 0)).sum() > 5
    check(structure, ray_args, any_hit=True)
    # Round and flat in one structure, and the same strands all flat through the intersector.
    round_linear = _kinked("sphere")[0]
    mixed = rt.build_primitive_structure([round_linear, bezier])
    leaf, _ = check(mixed, ray_args)
    flags = np.asarray(scene_view(mixed).leaves.curve_flags)[np.maximum(leaf, 0)]
    assert ((flags & 16 != 0) & (leaf >= 0)).sum() > 5 and ((flags & 16 == 0) & (leaf >= 0)).sum() > 5
    check(mixed, ray_args, rt.Intersector(curve_type="flat"))
    geometry = hair(seed=18, strands=3, end_caps="sphere", curve_type="flat")
    ray_args = _rays(geometry, 32, seed=19)
    for options in (rt.CurveOptions(pieces=5, iterations=2), rt.CurveOptions(iterations=0)):
        check(rt.build_primitive_structure(geometry), ray_args, rt.Intersector(curve_options=options))
    _check_hit_lists("flat")


def _bits(tree):
    """Every array of a traversal result as raw bytes (distances compared bit for bit)."""
    return [np.asarray(a).tobytes() for a in jax.tree_util.tree_leaves(tree)]


@kernel_test
def test_curve_batches_change_no_decision(kernel_here):
    """Deferred curve tests (``KernelOptions.curve_batch``) only make rays wait: for every threshold the result
    is the on-sight kernel's bit for bit (leaf, distance, counters, the K nearest hits and counts), with
    triangles, round and flat segments in one structure, nearest and any hit."""
    linear, bezier = _flat_kinked("sphere")
    round_ = hair(seed=30, strands=3, end_caps="disk")
    rng = np.random.default_rng(31)
    triangles = rt.TriangleGeometry(rng.uniform(-1, 2.5, (12, 3)).astype(np.float32))
    view = scene_view(rt.build_primitive_structure([triangles, bezier, linear, round_]))
    n = 96
    origin, direction = aimed_rays(rng, round_, n // 2)
    joints = np.array([[1, 0, 1], [1, 0, 0], [1.1, 1, 0]], np.float64)[rng.integers(0, 3, n // 2)]
    aimed = rng.normal(size=(n // 2, 3))
    aimed /= np.linalg.norm(aimed, axis=1, keepdims=True)
    origin = np.concatenate([origin, joints + rng.normal(scale=0.1, size=(n // 2, 3)) - 8.0 * aimed])
    direction = np.concatenate([direction, aimed])
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(6.0, 9.0, n), np.inf)
    args = (jnp.asarray(origin, jnp.float32), jnp.asarray(direction, jnp.float32), jnp.zeros(n, jnp.float32),
            jnp.asarray(t_max, jnp.float32), jnp.asarray(rng.random(n) > 0.05), jnp.full(n, ALL_RAYS, jnp.uint32))  # fmt: skip
    intersector = rt.Intersector()
    curves = gpu.curve_leaves(view, leaf_tests.curve_configuration(intersector, view))
    queries = [dict(any_hit=False), dict(any_hit=True), dict(any_hit=False, max_hits=3)]
    queries.append(dict(any_hit=False, count_all=True))
    for query in queries:
        runs = {}
        for batch in (0, 1, 7, 32) if query == queries[0] else (0, 5):
            options = gpu.KernelOptions(curve_batch=batch)
            runs[batch] = gpu.trace_scene(view.traversal, view.layout, *args, cull=0, curves=curves, options=options,
                                          **query)  # fmt: skip
        for batch, got in runs.items():
            assert _bits(got) == _bits(runs[0]), (query, batch)
        assert (np.asarray(runs[0].leaf) >= 0).sum() > n // 3 or query.get("count_all")


def _kernel_ir(monkeypatch, curves: tuple) -> str:
    """Triton IR of ``trace_kernel`` of a primitive structure (``test_gpu_multihit._kernel_ir``), with the curve
    options ``curves`` (``()``: no curves)."""
    from test_gpu_multihit import _kernel_ir as ir_of

    monkeypatch.setattr(gpu, "_Config", functools.partial(gpu._Config, curves=curves))
    return ir_of(0, 0, False)


@pytest.mark.skipif(INTERPRETED, reason="compiles the kernel's IR (outside the interpreter)")
def test_kernel_ir_without_curves_reads_no_curve_rows(monkeypatch):
    """Without curves the curve rows are a parameter that no instruction reads (the body is the kernel's
    without curve support, up to the renumbering of arguments); with curves they are read."""
    pytest.importorskip("triton")
    body = lambda text: text.split("tt.func public @trace_kernel", 1)[1].split("\n", 1)[1]  # noqa: E731
    assert "%curves_ptr" not in body(_kernel_ir(monkeypatch, ()))
    assert "%curves_ptr" in body(_kernel_ir(monkeypatch, (8, 3, 3, 1e-3, True, True, 0)))
    assert "%curves_ptr" in body(_kernel_ir(monkeypatch, (8, 3, 3, 1e-3, True, True, 1)))
