"""The GPU kernel's analytic leaves (the built-in sphere, disk and capped cylinder), against the portable
traversal and a float64 brute force.

As in ``test_gpu_instanced.py``: the kernel runs in Triton's interpreter on the CPU (in a fresh process) or on
a CUDA GPU, launched through the same :class:`gpu.KernelCall`. The references are

- the portable traversal of the same scene view with the intersector's leaf tests (``drivers.traverse`` with
  ``BoxLeaves`` calling the JAX functions): both test the same leaves against the same bounds step for step,
  so the leaf, the instance chain and the traversal counters are equal, and distances agree to rounding
  (rtol 1e-6, as in ``test_gpu_instanced.py``: XLA may contract multiply-adds, the kernel never does);
- the intersector's result fields on the portable path (``backend="portable"``);
- a float64 brute force over every shape (:func:`assert_float64`): a hit is right when its primitive has a
  root within tolerance of the distance and no root that every correct implementation finds lies nearer;
  a miss when no such root exists. Roots within a relative 1e-3 of a shape's rim, or near the ray's interval
  ends, may go either way.

Capped cylinders are compared with :data:`CYLINDER_RTOL`: the side wall's quadratic subtracts nearly equal
products (``d |a|^2 - a (d . a)``, ``b^2 - a c``), so a distance moves by many ulps when one rounding changes,
and XLA contracts some multiply-adds into fused ones where the kernel does not. Both are equally accurate:
over 132,381 random ray/cylinder hits in float32 (seed 1, rays from 2.6 units), the kernel's formula and the
JAX function had median relative errors against float64 of 3.7e-7 and 3.7e-7, 99th percentiles 5.4e-6 and
5.3e-6, maxima 3.0e-4 and 1.7e-4; against each other median 2.9e-7, 99th percentile 6.5e-6, max 3.9e-4.

Scenes are tiny: the interpreter runs a few thousand steps a second.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_gpu_instanced import (
    INTERPRETED,
    LAUNCHES,
    ON_GPU,
    _instances,
    _mesh,
    assert_same_fields,
    kernel_launches_here,
    kernel_test,
    run_kernel_tests_in_interpreter,
)
from test_gpu_instanced import rays as shell_rays

import jaxrt as rt
from jaxrt._src import leaves as leaf_tests
from jaxrt._src import pipeline
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import gpu

FUNCTIONS = rt.intersection_functions
SHAPES = ("sphere", "disk", "capped_cylinder")
ALL_RAYS = np.uint32(0xFFFFFFFF)
#: Relative distance tolerance where capped cylinders are hit (module docstring); 1e-6 elsewhere.
CYLINDER_RTOL = 1e-3


# --- scenes -----------------------------------------------------------------------------------------------------


def shape_data(rng, count: int, spread: float = 1.0) -> dict[str, np.ndarray]:
    """Every field any built-in reads, so that geometries of different shapes share one data layout."""
    center = rng.uniform(-spread, spread, (count, 3))
    axis = rng.normal(size=(count, 3)) * rng.uniform(0.15, 0.35, (count, 1))
    data = {
        "center": center,
        "normal": rng.normal(size=(count, 3)),
        "radius": rng.uniform(0.12, 0.35, count),
        "p0": center - axis,
        "p1": center + axis,
    }
    return {k: v.astype(np.float32) for k, v in data.items()}


def shape_geometry(shape: str, data: dict, *, with_data: bool = True) -> rt.BoundingBoxGeometry:
    if shape == "sphere":
        lower, upper = FUNCTIONS.sphere_bounds(data["center"], data["radius"])
    elif shape == "disk":
        lower, upper = FUNCTIONS.disk_bounds(data["center"], data["normal"], data["radius"])
    else:
        lower, upper = FUNCTIONS.capped_cylinder_bounds(data["p0"], data["p1"], data["radius"])
    return rt.BoundingBoxGeometry(lower, upper, primitive_data=data if with_data else None)


def shapes_structure(seed: int, shapes=SHAPES, count: int = 8, *, triangles: int = 0, with_data: bool = True):
    """One geometry per shape (geometry ``i`` is ``shapes[i]``), then an optional triangle geometry; returns the
    structure, the intersector's functions and each box geometry's float64 parameters."""
    rng = np.random.default_rng(seed)
    geometries, functions, params = [], {}, {}
    for index, shape in enumerate(shapes):
        data = shape_data(rng, count)
        geometry = shape_geometry(shape, data, with_data=with_data)
        geometries.append(geometry)
        functions[index] = getattr(FUNCTIONS, shape)
        if with_data:
            params[index] = (shape, {k: v.astype(np.float64) for k, v in data.items()})
        else:  # the sphere inscribed in the float32 box
            lower, upper = (np.asarray(a, np.float64) for a in (geometry.lower, geometry.upper))
            params[index] = (shape, {"center": 0.5 * (lower + upper), "radius": 0.5 * (upper - lower).min(axis=1)})
    if triangles:
        tri = rng.uniform(-1.0, 1.0, (triangles, 1, 3)) + 0.4 * rng.standard_normal((triangles, 3, 3))
        geometries.append(rt.TriangleGeometry(tri.reshape(-1, 3).astype(np.float32)))
    return rt.build_primitive_structure(geometries), functions, params


def rays(n: int, seed: int, params: dict | None = None, *, spread: float = 1.3, masks: bool = False):
    """Rays from a shell aimed into the scene (random intervals, three disabled), a few starting at shape
    centres (inside spheres and cylinders: the far root)."""
    origin, direction, t_min, t_max, enabled, mask = (
        np.array(a) for a in shell_rays(n, seed, spread=spread, masks=masks)
    )
    if params:
        centers = np.concatenate([p["center"] for _, p in params.values()]).astype(np.float32)
        origin[:4] = centers[:4]
        t_min[:4] = 0.0
        aimed = np.arange(4, n // 2)  # these aim at shape centres (thin disks are hit too)
        target = centers[aimed % centers.shape[0]] + np.float32(0.05) * rng_normal(seed, (aimed.size, 3))
        direction[aimed] = target - origin[aimed]
    return tuple(jnp.asarray(a) for a in (origin, direction, t_min, t_max, enabled, mask))


def rng_normal(seed: int, shape: tuple) -> np.ndarray:
    return np.random.default_rng(seed + 1000).normal(size=shape).astype(np.float32)


def as_ray(ray_args) -> rt.Ray:
    origin, direction, t_min, t_max, enabled, mask = ray_args
    direction = jnp.where(enabled[:, None], direction, 0.0)  # disabled: a zero direction
    return rt.Ray(origin, direction, t_min, t_max, mask=mask)


# --- references -------------------------------------------------------------------------------------------------


def check(structure, ray_args, functions: dict, *, any_hit: bool = False, cull: int = 0, rtol: float = 1e-6):
    """The kernel against the portable traversal of the same view: equal leaves, chains and counters."""
    from jaxrt._src.traversal import drivers

    view = scene_view(structure)
    intersector = rt.Intersector(intersection_functions=functions)
    analytic = gpu.analytic_leaves(intersector.intersection_functions, view)
    got = gpu.trace_scene(view.traversal, view.layout, *ray_args, any_hit=any_hit, cull=cull, analytic=analytic)
    tester = leaf_tests.leaf_tester(
        rt.Intersector(intersection_functions=functions, triangle_cull_mode=_mode(cull)), view
    )
    fn = functools.partial(drivers.traverse, view.traversal, view.layout, tester, any_hit=any_hit)
    want = jax.jit(jax.vmap(fn))(*ray_args)
    for name in ("leaf", "instances", "nodes_visited", "primitives_tested"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=rtol, atol=1e-7)
    assert not np.asarray(got.stack_overflow).any()
    return got


def _mode(cull: int) -> str:
    return {0: "none", 1: "front", -1: "back"}[cull]


def intersect_both(intersector_args: dict, ray: rt.Ray, structure, tags=(), rtol: float = 1e-6) -> tuple:
    """The result fields through the kernel (a launch is required) and through the portable traversal."""
    LAUNCHES.clear()
    got = rt.Intersector(*tags, backend="gpu", **intersector_args).intersect(ray, structure)
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    want = rt.Intersector(*tags, backend="portable", **intersector_args).intersect(ray, structure)
    assert_same_fields(got, want, rtol)
    return got, want


def _roots64(shape: str, p: dict, o: np.ndarray, d: np.ndarray):
    """Every root of every primitive of one shape in float64: ``[(t, valid, clear)]`` arrays ``(R, P)``;
    ``clear``: the decision is not within a relative 1e-3 of the shape's rim (or of a grazing angle)."""
    o, d = o[:, None, :], d[:, None, :]
    dot = lambda a, b: np.sum(a * b, axis=-1)  # noqa: E731
    out = []
    with np.errstate(all="ignore"):
        if shape == "sphere":
            c, r = p["center"][None], p["radius"][None]
            f = o - c
            a, b = dot(d, d), dot(f, d)
            h = np.sqrt(dot(f - (b / a)[..., None] * d, f - (b / a)[..., None] * d))
            disc = r * r - h * h
            s = np.sqrt(np.maximum(disc, 0.0) * a)
            clear = np.abs(h - r) > 1e-3 * r
            for sign in (-1.0, 1.0):
                out.append(((-b + sign * s) / a, disc >= 0, clear))
        elif shape == "disk":
            c, n, r = p["center"][None], p["normal"][None], p["radius"][None]
            denom = dot(d, n)
            t = dot(c - o, n) / denom
            rho = np.sqrt(dot(o + t[..., None] * d - c, o + t[..., None] * d - c))
            grazing = np.abs(denom) <= 1e-3 * np.linalg.norm(d, axis=-1) * np.linalg.norm(n, axis=-1)
            out.append((t, (denom != 0) & (rho <= r), (np.abs(rho - r) > 1e-3 * r) & ~grazing))
        else:
            p0, p1, r = p["p0"][None], p["p1"][None], p["radius"][None]
            length = np.linalg.norm(p1 - p0, axis=-1)
            u = (p1 - p0) / length[..., None]
            oc = o - p0
            du, ou = dot(d, u), dot(oc, u)
            dp, op = d - du[..., None] * u, oc - ou[..., None] * u
            a, b, c = dot(dp, dp), dot(op, dp), dot(op, op) - r * r
            disc = b * b - a * c
            nearest = np.sqrt(np.maximum(dot(op, op) - b * b / np.where(a > 0, a, 1.0), 0.0))
            ring = np.abs(nearest - r) > 1e-3 * r
            for sign in (-1.0, 1.0):
                t = (-b + sign * np.sqrt(np.maximum(disc, 0.0))) / a
                along = ou + t * du
                valid = (a > 0) & (disc >= 0) & (along >= 0) & (along <= length)
                clear = ring & (np.abs(along) > 1e-3 * length) & (np.abs(along - length) > 1e-3 * length)
                out.append((t, valid, clear))
            for plane in (0.0, 1.0):
                t = (plane * length - ou) / du
                rho = np.sqrt(dot(op + t[..., None] * dp, op + t[..., None] * dp))
                grazing = np.abs(du) <= 1e-3 * np.linalg.norm(d, axis=-1)
                out.append((t, (du != 0) & (rho <= r), (np.abs(rho - r) > 1e-3 * r) & ~grazing))
    return out


def assert_float64(hit, params: dict, ray: rt.Ray, rtol: float = 1e-4) -> int:
    """The result's nearest hits against every root of every shape in float64 (distances within ``rtol``,
    relative to ``max(1, t)``); returns the hit count."""
    o, d = np.asarray(ray.origin, np.float64), np.asarray(ray.direction, np.float64)
    t_min, t_max = np.asarray(ray.min_distance, np.float64), np.asarray(ray.max_distance, np.float64)
    enabled = np.any(d != 0, axis=1)
    ts, certain, possible, gids, pids = [], [], [], [], []
    for geometry, (shape, p) in params.items():
        for t, valid, clear in _roots64(shape, p, o, d):
            t = np.where(np.isfinite(t), t, np.inf)
            tol = rtol * np.maximum(1.0, np.abs(np.where(np.isfinite(t), t, 0.0)))
            inside = (t >= t_min[:, None] - tol) & (t <= t_max[:, None] + tol)
            well_inside = (t >= t_min[:, None] + tol) & (t <= t_max[:, None] - tol)
            ts.append(t)
            certain.append(valid & clear & well_inside & enabled[:, None])
            possible.append((valid | ~clear) & inside)
            gids.append(np.full(t.shape, geometry))
            pids.append(np.broadcast_to(np.arange(t.shape[1]), t.shape))
    t, certain, possible = (np.concatenate(x, axis=1) for x in (ts, certain, possible))
    gid, pid = np.concatenate(gids, axis=1), np.concatenate(pids, axis=1)
    found = np.asarray(hit.type) == int(rt.IntersectionType.BOUNDING_BOX)
    distance = np.asarray(hit.distance, np.float64)
    g, k = np.asarray(hit.geometry_id), np.asarray(hit.primitive_id)
    for r in range(t.shape[0]):
        if not found[r]:
            assert not certain[r].any(), f"ray {r}: missed a certain root at {t[r][certain[r]].min()}"
            continue
        tol = rtol * max(1.0, abs(distance[r]))
        mine = possible[r] & (gid[r] == g[r]) & (pid[r] == k[r]) & (np.abs(t[r] - distance[r]) <= tol)
        assert mine.any(), f"ray {r}: geometry {g[r]} primitive {k[r]} has no root at {distance[r]}"
        nearer = certain[r] & (t[r] < distance[r] - tol)
        assert not nearer.any(), f"ray {r}: a certain root at {t[r][nearer].min()} is nearer than {distance[r]}"
    return int(found.sum())


# --- running the kernel in Triton's interpreter -----------------------------------------------------------------


kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    # The IR test compiles outside the interpreter.
    run_kernel_tests_in_interpreter(__file__, "not interpreter and not kernel_ir")


@pytest.fixture
def kernel_path(kernel_here, monkeypatch):
    """The intersector may take the kernel here (the interpreter stands in for the GPU)."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)


# --- the kernel's tests -------------------------------------------------------------------------------------------


@kernel_test
@pytest.mark.parametrize(
    "shape, with_data", [("sphere", True), ("sphere", False), ("disk", True), ("capped_cylinder", True)]
)
def test_each_shape(shape, with_data, kernel_path):
    """One shape per structure: the traversal step for step, every field, and float64 roots."""
    structure, functions, params = shapes_structure(10 + SHAPES.index(shape), (shape,), 12, with_data=with_data)
    ray_args = rays(64, 20 + SHAPES.index(shape), params)
    rtol = CYLINDER_RTOL if shape == "capped_cylinder" else 1e-6
    check(structure, ray_args, functions, rtol=rtol)
    ray = as_ray(ray_args)
    got, _ = intersect_both(dict(intersection_functions=functions), ray, structure, rtol=rtol)
    assert assert_float64(got, params, ray, max(rtol, 1e-4)) > 12


@kernel_test
@pytest.mark.parametrize("any_hit, cull", [(False, 1), (True, 0)])
def test_shapes_mixed_with_triangles(any_hit, cull, kernel_path):
    """All three shapes and a triangle geometry in one structure (triangles culled, shapes never), nearest
    and any hit."""
    structure, functions, params = shapes_structure(30, SHAPES, 5, triangles=8)
    ray_args = rays(64, 31, params)
    got = check(structure, ray_args, functions, any_hit=any_hit, cull=cull, rtol=CYLINDER_RTOL)
    kinds = np.asarray(scene_view(structure).leaves.geometry)[np.asarray(got.leaf)[np.asarray(got.leaf) >= 0]]
    assert set(kinds.tolist()) == {0, 1, 2, 3}, kinds  # every shape and the triangles are hit
    args = dict(intersection_functions=functions, accept_any_intersection=any_hit, triangle_cull_mode=_mode(cull))
    tags = (rt.tags.triangle_data, rt.tags.primitive_data)
    intersect_both(args, as_ray(ray_args), structure, tags, rtol=CYLINDER_RTOL)
    if not any_hit:
        shapes_only, _, shape_params = shapes_structure(30, SHAPES, 5)
        only, _ = intersect_both(
            dict(intersection_functions=functions), as_ray(ray_args), shapes_only, rtol=CYLINDER_RTOL
        )
        assert assert_float64(only, shape_params, as_ray(ray_args), CYLINDER_RTOL) > 12


@kernel_test
def test_hit_lists_and_counts(kernel_path):
    """``max_hits`` and ``count_intersections`` over shapes and triangles: the same lists as the portable path."""
    structure, functions, _ = shapes_structure(40, SHAPES, 5, triangles=6)
    ray = as_ray(rays(64, 41))
    got, _ = intersect_both(dict(intersection_functions=functions, max_hits=3), ray, structure, rtol=CYLINDER_RTOL)
    assert (np.asarray(got.hit_count) >= 2).sum() > 3
    counts = {}
    for backend in ("gpu", "portable"):
        intersector = rt.Intersector(intersection_functions=functions, backend=backend)
        counts[backend] = np.asarray(rt.count_intersections(ray, structure, intersector))
    np.testing.assert_array_equal(counts["gpu"], counts["portable"])
    assert counts["gpu"].max() >= 3


@kernel_test
@pytest.mark.parametrize("levels", [1, 2])
def test_below_instances(levels, kernel_path):
    """Shapes below one and two instance levels with masks and mirrored transforms, next to a mesh: the
    chains, the per-level rays and every field; geometry ids are local to each structure."""
    rng = np.random.default_rng(50 + levels)
    shapes, functions, _ = shapes_structure(51 + levels, ("sphere", "capped_cylinder", "disk"), 6)
    mesh = _mesh(rng)
    structure = rt.build_instance_structure([shapes, mesh], _instances(rng, [0, 1, 0], 1.0, masks=True))
    if levels == 2:
        outer = _instances(rng, [0, 1, 0], 1.6, masks=True)
        structure = rt.build_instance_structure([structure, shapes], outer)
    ray_args = rays(64, 60 + levels, spread=1.5, masks=True)
    got = check(structure, ray_args, functions, rtol=CYLINDER_RTOL)
    hit = np.asarray(got.leaf) >= 0
    chains = np.asarray(got.instances)[hit]
    assert hit.sum() > 10 and (chains >= 0).sum(axis=1).max() == levels
    tags = (rt.tags.instancing, rt.tags.max_levels(levels), rt.tags.world_space_data, rt.tags.primitive_data)
    intersect_both(dict(intersection_functions=functions), as_ray(ray_args), structure, tags, rtol=CYLINDER_RTOL)


@kernel_test
def test_vmap_over_scenes_is_one_launch(kernel_here):
    """``jax.vmap`` over (rays, scene, analytic rows): one launch, each scene's answer its own."""
    from jaxrt._src.traversal import drivers

    built = [shapes_structure(70 + s, ("sphere", "disk"), 6, triangles=3) for s in range(2)]
    views = [scene_view(s) for s, _, _ in built]
    functions = rt.Intersector(intersection_functions=built[0][1]).intersection_functions
    leaves = [gpu.analytic_leaves(functions, v) for v in views]
    layout = views[0].layout
    per_scene = [rays(24, 80 + s, built[s][2]) for s in range(2)]
    stack = lambda *xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731

    def trace(scene, rows, *ray_args):
        analytic = gpu.AnalyticLeaves(rows, leaves[0].shapes)
        return gpu.trace_scene(scene, layout, *ray_args, any_hit=False, cull=0, analytic=analytic)

    got = jax.jit(jax.vmap(trace))(stack(*[v.traversal for v in views]), jnp.stack([a.rows for a in leaves]),
                                   *stack(*per_scene))  # fmt: skip
    if not ON_GPU:
        assert [n for _, n in LAUNCHES] == [64], LAUNCHES  # 2 x 24 rays in one launch (padded to 2 x 32)
    for s, view in enumerate(views):
        one = jax.tree.map(lambda a, s=s: a[s], got)
        tester = leaf_tests.leaf_tester(rt.Intersector(intersection_functions=dict(functions)), view)
        want = jax.jit(jax.vmap(functools.partial(drivers.traverse, view.traversal, layout, tester, any_hit=False)))(
            *per_scene[s]
        )
        np.testing.assert_array_equal(np.asarray(one.leaf), np.asarray(want.leaf))
        np.testing.assert_allclose(np.asarray(one.distance), np.asarray(want.distance), rtol=1e-6, atol=1e-7)
        assert (np.asarray(one.leaf) >= 0).sum() > 5


@kernel_test
def test_gradients_through_the_kernel_path(kernel_path):
    """The kernel only picks the box: distance gradients with respect to the sphere parameters and the rays
    come from the function called again in JAX, as on the portable path."""
    data = shape_data(np.random.default_rng(90), 8)
    ray_args = rays(32, 91, {0: ("sphere", data)})
    ray = as_ray(ray_args)

    def loss(center, radius, origin, backend):
        lower, upper = FUNCTIONS.sphere_bounds(center, radius)
        geometry = rt.BoundingBoxGeometry(lower, upper, primitive_data={"center": center, "radius": radius})
        structure = rt.build_primitive_structure(geometry)
        intersector = rt.Intersector(intersection_functions={0: FUNCTIONS.sphere}, backend=backend)
        hit = intersector.intersect(rt.Ray(origin, ray.direction, ray.min_distance, ray.max_distance), structure)
        return jnp.sum(jnp.where(hit.type != 0, hit.distance, 0.0))

    args = (jnp.asarray(data["center"]), jnp.asarray(data["radius"]), ray.origin)
    got = jax.grad(loss, argnums=(0, 1, 2))(*args, "gpu")
    if not ON_GPU:
        assert LAUNCHES, "the kernel did not run"
    want = jax.grad(loss, argnums=(0, 1, 2))(*args, "portable")
    assert float(jnp.abs(want[1]).sum()) > 1.0
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-5)


@kernel_test
def test_user_functions_take_the_kernel_in_candidate_waves(kernel_path):
    """A user-written sphere (not the built-in, even if it calls it) is decided in JAX on the candidates the
    kernel lists (``traversal.waves``): launches, and the same hits as the built-in on the kernel."""
    structure, functions, params = shapes_structure(95, ("sphere",), 8)
    ray = as_ray(rays(32, 96, params))

    def my_sphere(r, candidate):
        return FUNCTIONS.sphere(r, candidate)

    LAUNCHES.clear()
    mine = rt.Intersector(intersection_functions={0: my_sphere}, backend="gpu").intersect(ray, structure)
    assert LAUNCHES or ON_GPU  # the interpreter records its launches
    builtin, _ = intersect_both(dict(intersection_functions=functions), ray, structure)
    assert_same_fields(mine, builtin)
    assert (np.asarray(mine.type) != 0).sum() > 5


# --- coverage and packing (no kernel run) -------------------------------------------------------------------------


def test_kernel_declines_only_user_functions():
    structure, functions, _ = shapes_structure(100, SHAPES, 2, triangles=2)
    infos = structure.geometry_info
    builtin = rt.Intersector(intersection_functions=functions)
    assert pipeline.kernel_declines(builtin, infos) is None
    assert pipeline.kernel_declines(builtin, infos, "gpu") is None
    assert pipeline.kernel_declines(builtin, infos, "cpu") is None
    assert "keyframe motion" in pipeline.kernel_declines(builtin, infos, "gpu", True)

    def my_disk(ray, candidate):
        return FUNCTIONS.disk(ray, candidate)

    user = rt.Intersector(intersection_functions={**functions, 1: my_disk})
    assert pipeline.kernel_declines(user, infos) is None  # candidate waves (test_gpu_waves.py)
    reason = pipeline.kernel_declines(user, infos, "gpu", levels=1)
    assert reason.startswith("bounding-box geometry with user intersection functions (geometry 1: my_disk) below")
    lambdas = rt.Intersector(intersection_functions={0: lambda r, c: FUNCTIONS.sphere(r, c)})
    # with keyframe motion the boxes themselves are declined first; below instances, the user functions
    assert "keyframe motion" in pipeline.kernel_declines(lambdas, infos, "gpu", True)
    assert "user intersection functions" in pipeline.kernel_declines(lambdas, infos, "gpu", levels=1)
    non_opaque = rt.build_primitive_structure(
        [shape_geometry("sphere", shape_data(np.random.default_rng(1), 2)), rt.TriangleGeometry(
            np.eye(3, dtype=np.float32), opaque=False)]
    )  # fmt: skip
    filtered = rt.Intersector(intersection_functions={0: FUNCTIONS.sphere}, filter=lambda c: jnp.asarray(True))
    assert pipeline.kernel_declines(filtered, non_opaque.geometry_info) is None  # candidate waves
    assert "filters on non-opaque" in pipeline.kernel_declines(filtered, non_opaque.geometry_info, "gpu", levels=1)


@pytest.mark.parametrize("with_data", [True, False])
def test_analytic_rows_hold_each_leafs_parameters(with_data):
    """Each box leaf's row: its geometry's shape code and its own parameters (leaf order); triangles 0."""
    shapes = SHAPES if with_data else ("sphere",)
    structure, functions, params = shapes_structure(110, shapes, 3, triangles=2, with_data=with_data)
    view = scene_view(structure)
    leaves = gpu.analytic_leaves(rt.Intersector(intersection_functions=functions).intersection_functions, view)
    assert leaves.shapes == (15 if with_data else 9)
    rows = np.asarray(leaves.rows)
    geometry, primitive = np.asarray(view.leaves.geometry), np.asarray(view.leaves.primitive)
    for k in range(rows.shape[0]):
        g, p = int(geometry[k]), int(primitive[k])
        if g < 0 or g == len(shapes):  # padding, triangles
            np.testing.assert_array_equal(rows[k, 3], 0.0)
            continue
        shape, values = params[g]
        assert rows[k, 3] == SHAPES.index(shape) + 1
        first, second = {"sphere": ("center", None), "disk": ("center", "normal"), "capped_cylinder": ("p0", "p1")}[
            shape
        ]
        np.testing.assert_array_equal(rows[k, :3], values[first][p].astype(np.float32))
        if second:
            np.testing.assert_array_equal(rows[k, 4:7], values[second][p].astype(np.float32))
        np.testing.assert_array_equal(rows[k, 7], np.float32(values["radius"][p]))


def test_missing_primitive_data_is_a_named_error():
    rng = np.random.default_rng(120)
    data = shape_data(rng, 3)
    geometry = shape_geometry("disk", data, with_data=False)
    view = scene_view(rt.build_primitive_structure(geometry))
    with pytest.raises(ValueError, match=r"primitive_data\['center'\]"):
        gpu.analytic_leaves(((0, FUNCTIONS.disk),), view)
    with pytest.raises(ValueError, match="not built-in"):
        gpu.analytic_leaves(((0, lambda r, c: FUNCTIONS.disk(r, c)),), view)


def _kernel_ir(levels: int, analytic: int) -> str:
    """Triton IR of ``trace_kernel`` with ``ANALYTIC = analytic`` for a CUDA target (no GPU needed)."""
    from test_gpu_multihit import _kernel_ir as multihit_ir

    kernel_call = gpu.kernel_call

    def with_analytic(*args, **kwargs):
        call = kernel_call(*args, **kwargs)
        return call._replace(params={**call.params, "ANALYTIC": analytic})

    gpu.kernel_call = with_analytic
    try:
        return multihit_ir(levels, 0, False)
    finally:
        gpu.kernel_call = kernel_call


def _strip_locations(text: str) -> str:
    import re

    lines = [line for line in text.splitlines() if not line.startswith("#loc")]
    return re.sub(r" loc\([^)]*\)", "", "\n".join(lines))


@pytest.mark.skipif(INTERPRETED, reason="compiles the kernel's IR (outside the interpreter)")
@pytest.mark.parametrize("levels", [0, 2])
def test_triangle_kernel_ir_has_no_analytic_code(levels):
    """``ANALYTIC = 0`` (triangle-only scenes) generates no shape code: no square root and, without instances,
    no read of the direction rows (17-19) of the ray block; ``ANALYTIC = 15`` compiles the shapes."""
    pytest.importorskip("triton")
    triangles = _strip_locations(_kernel_ir(levels, 0))
    shapes = _strip_locations(_kernel_ir(levels, 15))
    assert "sqrt" not in triangles and "tt.precise_sqrt" in shapes
    if levels == 0:
        assert "c17_i32" not in triangles and "c17_i32" in shapes
