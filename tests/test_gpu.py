"""The GPU traversal path: packing, dispatch and batching on any machine; the Triton kernel on a CUDA GPU.

Tests marked ``gpu`` run only where JAX's default backend is a GPU and Triton imports; elsewhere they are
skipped. The CPU tests replace the kernel launch by an emulation (the portable traversal on the unpacked
arrays) to check everything around it, and, where Triton is installed, run the kernel itself in Triton's
interpreter.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import edges, icosphere

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.pipeline import resolve_backend as _resolve_backend
from jaxrt._src.primitives import triangle
from jaxrt._src.traversal import gpu, packed

#: Kernel layouts the tests run: the binary nodes, and the 4-wide tree with leaf clusters of 4 and of 1.
KERNEL_LAYOUTS = (
    gpu.KernelOptions(node_width=2),
    gpu.KernelOptions(node_width=4, leaf_size=4),
    gpu.KernelOptions(node_width=4, leaf_size=1),
)
ON_GPU = jax.default_backend() == "gpu" and gpu._import_error() is None
needs_gpu = pytest.mark.skipif(not ON_GPU, reason="needs a CUDA GPU with Triton and jax-triton")


def _sphere(n_theta: int = 9, n_phi: int = 14, seed: int = 0):
    """A small closed, bumpy UV sphere (vertices, indices)."""
    rng = np.random.default_rng(seed)
    theta = np.linspace(0.0, np.pi, n_theta)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, n_phi, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    r = 1.0 + 0.05 * rng.standard_normal(t.shape)
    ring = np.stack([r * np.sin(t) * np.cos(p), r * np.sin(t) * np.sin(p), r * np.cos(t)], -1).reshape(-1, 3)
    vertices = np.concatenate([ring, [[0, 0, 1.0], [0, 0, -1.0]]]).astype(np.float32)
    rows, north, south = n_theta - 2, len(ring), len(ring) + 1
    faces = []
    for j in range(n_phi):
        k = (j + 1) % n_phi
        faces += [[north, j, k], [south, (rows - 1) * n_phi + k, (rows - 1) * n_phi + j]]
        for i in range(rows - 1):
            a, b, c, d = i * n_phi + j, i * n_phi + k, (i + 1) * n_phi + j, (i + 1) * n_phi + k
            faces += [[a, c, b], [b, c, d]]
    return vertices, np.array(faces, np.int32)


def _scene(seed: int = 0):
    """Two geometries: a closed sphere and a random soup (with a degenerate triangle)."""
    rng = np.random.default_rng(seed)
    vertices, faces = _sphere(seed=seed)
    soup = (rng.uniform(-1.2, 1.2, (40, 1, 3)) + 0.25 * rng.standard_normal((40, 3, 3))).astype(np.float32)
    soup[0, 2] = soup[0, 0] + 2.0 * (soup[0, 1] - soup[0, 0])  # collinear: never hit
    geometries = [rt.TriangleGeometry(vertices, faces), rt.TriangleGeometry(soup.reshape(-1, 3))]
    return rt.build_primitive_structure(geometries), vertices


def _rays(n: int, seed: int = 1) -> rt.Ray:
    """Random rays through the scene, some axis-parallel, bounded, reversed (disabled) or zero."""
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-2.5, 2.5, (n, 3)).astype(np.float32)
    direction = (rng.uniform(-0.8, 0.8, (n, 3)) - origin).astype(np.float32)
    axis = rng.integers(0, 3, n // 8)
    direction[: n // 8] = 0.0
    direction[np.arange(n // 8), axis] = np.where(rng.random(n // 8) < 0.5, -1.0, 1.0)
    t_min = np.where(rng.random(n) < 0.2, rng.uniform(0.0, 2.0, n), 0.0).astype(np.float32)
    t_max = np.where(rng.random(n) < 0.2, rng.uniform(0.5, 3.0, n), np.inf).astype(np.float32)
    direction[n // 8 : n // 8 + 3] = 0.0  # zero direction: disabled
    t_max[n // 8 + 3 : n // 8 + 6] = -1.0  # empty interval: disabled
    return rt.Ray(origin, direction, t_min, t_max)


def _assert_same(result, reference, *, distance_rtol: float = 0.0):
    for name in reference:
        got, want = np.asarray(result[name]), np.asarray(reference[name])
        if name in ("distance", "triangle_barycentric_coord") and distance_rtol:
            np.testing.assert_allclose(got, want, rtol=distance_rtol, atol=1e-7, err_msg=name)
        else:
            np.testing.assert_array_equal(got, want, err_msg=name)


def _assert_agree(result, reference, *, any_hit: bool, distance_rtol: float = 0.0):
    """The 4-wide kernel's contract: the binary traversal's hits, up to the choice among ties.

    Nearest hit: the same hit or miss and distance everywhere; where the primitive differs, the two are at
    the same distance (a tie, e.g. a ray through a shared edge). Any hit: the same hit or miss; the hit
    reported is a hit in the ray's interval. Traversal statistics differ (another tree) and are not compared.
    """
    hit = np.asarray(reference.type) != 0
    np.testing.assert_array_equal(np.asarray(result.type), np.asarray(reference.type))
    assert not np.asarray(result.stack_overflow).any()
    distance, want = np.asarray(result.distance), np.asarray(reference.distance)
    if any_hit:
        assert np.isfinite(distance[hit]).all() and np.isinf(distance[~hit]).all()
        return
    np.testing.assert_allclose(distance, want, rtol=distance_rtol, atol=1e-7)
    same = (np.asarray(result.primitive_id) == np.asarray(reference.primitive_id)) & (
        np.asarray(result.geometry_id) == np.asarray(reference.geometry_id)
    )
    for name in ("triangle_barycentric_coord", "triangle_front_facing"):
        if name in reference:
            np.testing.assert_allclose(
                np.asarray(result[name])[same], np.asarray(reference[name])[same], rtol=distance_rtol, atol=1e-6
            )
    print(f"\n{hit.sum()} hits, {(~same).sum()} ties resolved to another primitive")


def _compare(result, reference, layout: gpu.KernelOptions, *, any_hit: bool = False, distance_rtol: float = 0.0):
    """The kernel's result against the portable path's, by the contract of the kernel ``layout``."""
    if layout.node_width == 2:
        _assert_same(result, reference, distance_rtol=distance_rtol)
    else:
        _assert_agree(result, reference, any_hit=any_hit, distance_rtol=distance_rtol)


@pytest.fixture(params=KERNEL_LAYOUTS, ids=lambda o: f"width{o.node_width}-leaf{o.leaf_size}")
def layout(request, monkeypatch, fresh_caches):
    """Run a test with each kernel layout as the default (compiled traces are dropped around it)."""
    monkeypatch.setattr(gpu, "DEFAULT_OPTIONS", request.param)
    return request.param


# ---------------------------------------------------------------------------------------------- CPU tests


def test_pack_nodes_round_trip():
    structure, _ = _scene()
    nodes = packed.pack_nodes(structure.node_lower, structure.node_upper, structure.node_children)
    assert nodes.shape == (structure.capacity - 1, packed.NODE_WIDTH) and nodes.dtype == jnp.float32
    lower, upper, children = packed.unpack_nodes(nodes)
    np.testing.assert_array_equal(lower, structure.node_lower)
    np.testing.assert_array_equal(upper, structure.node_upper)
    np.testing.assert_array_equal(children, structure.node_children)
    np.testing.assert_array_equal(nodes[:, 14:], 0.0)
    # Column groups are per axis: lower0, upper0, lower1, upper1.
    np.testing.assert_array_equal(
        nodes[:, 4:8],
        np.stack(
            [
                structure.node_lower[:, 0, 1],
                structure.node_upper[:, 0, 1],
                structure.node_lower[:, 1, 1],
                structure.node_upper[:, 1, 1],
            ],
            -1,
        ),
    )


def _walk_wide(rows: np.ndarray, capacity: int):
    """Leaf counts and slot boxes reached from the root of packed 4-wide rows (empty slots skipped)."""
    refs = rows[:, 24:28].view(np.int32)
    seen = np.zeros(capacity, np.int64)
    reached, todo, depth, clusters = set(), [(0, 1)], 0, []
    while todo:
        w, level = todo.pop()
        assert w not in reached, "a wide node is referenced twice"
        reached.add(w)
        depth = max(depth, level)
        for k in range(4):
            lower = rows[w, [k, 8 + k, 16 + k]]
            upper = rows[w, [4 + k, 12 + k, 20 + k]]
            if not (lower <= upper).all():
                continue
            if refs[w, k] >= 0:
                todo.append((int(refs[w, k]), level + 1))
            else:
                code = -1 - int(refs[w, k])
                first, count = code >> 2, (code & 3) + 1
                seen[first : first + count] += 1
                clusters.append((first, count, lower, upper))
    return seen, clusters, len(reached), depth


@pytest.mark.parametrize("quality", ["fast", "high"])
@pytest.mark.parametrize("leaf_size", [1, 2, 4])
def test_pack_wide_nodes_covers_every_leaf_once(quality, leaf_size):
    """The 4-wide collapse: every real leaf in exactly one cluster, clusters within their slot boxes, the
    row count and depth within the bounds the kernel's buffers and stack are sized by."""
    structure, _ = _scene()
    rows = np.asarray(
        packed.pack_wide_nodes(
            structure.node_lower, structure.node_upper, structure.node_children, structure.node_range, leaf_size
        )
    )
    assert rows.shape == (packed.wide_node_capacity(structure.capacity), packed.WIDE_NODE_WIDTH)
    seen, clusters, reached, depth = _walk_wide(rows, structure.capacity)
    real = np.asarray(structure.leaf_geometry) >= 0
    np.testing.assert_array_equal(seen[real], 1)
    triangles = np.asarray(structure.leaf_triangle)
    for first, count, lower, upper in clusters:
        assert 1 <= count <= leaf_size
        inside = triangles[first : first + count][real[first : first + count]]
        assert (inside.min(axis=1) >= lower).all() and (inside.max(axis=1) <= upper).all()
    assert reached <= rows.shape[0]
    assert 3 * depth <= packed.wide_stack_size(structure.max_depth)
    if leaf_size > 1:
        assert max(count for _, count, _, _ in clusters) > 1
    with pytest.raises(ValueError, match="leaf_size"):
        packed.pack_wide_nodes(
            structure.node_lower, structure.node_upper, structure.node_children, structure.node_range, 5
        )


def test_pack_triangles_layout():
    structure, _ = _scene()
    rows = np.asarray(packed.pack_triangles(structure.leaf_triangle))
    assert rows.shape == (structure.capacity, packed.TRIANGLE_WIDTH)
    per_axis = rows.reshape(-1, 3, 4)
    np.testing.assert_array_equal(per_axis[:, :, :3], np.swapaxes(np.asarray(structure.leaf_triangle), 1, 2))
    np.testing.assert_array_equal(per_axis[:, :, 3], 0.0)


def test_pack_rays_constants_and_padding():
    origin = jnp.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
    direction = jnp.array([[0.0, 0.0, -2.0], [3.0, -1.0, 0.0]])
    enabled = jnp.array([True, False])
    block = np.asarray(packed.pack_rays(origin, direction, jnp.zeros(2), jnp.full(2, 5.0), enabled, 32))
    assert block.shape == (packed.RAY_ROWS, 32)
    sheared = jax.vmap(triangle.shear_ray)(origin, direction)
    np.testing.assert_array_equal(block[6:9, :2].T, sheared.shear)
    np.testing.assert_array_equal(block[11:14, :2].T, np.stack([sheared.kx, sheared.ky, sheared.kz], -1))
    assert block[10, 0] == 5.0 and block[10, 1] == -np.inf  # a disabled ray's bound is -inf
    np.testing.assert_array_equal(block[14], [1.0] + [0.0] * 31)  # padding columns are disabled


@pytest.mark.skipif(ON_GPU, reason="checks the CPU behaviour")
def test_unavailable_without_gpu():
    reason = gpu.unavailable_reason(rt.Intersector())
    assert reason is not None and "backend" in reason
    from jaxrt._src.traversal import cpu

    # Without a GPU, "auto" takes the compiled CPU traversal where Numba is installed, else the portable one.
    assert _resolve_backend(rt.Intersector()) == ("cpu" if cpu.unavailable_reason() is None else "portable")
    structure, _ = _scene()
    with pytest.raises(ValueError, match="backend='gpu' cannot run"):
        rt.Intersector(backend="gpu").intersect(_rays(8), structure)


def _emulated_kernel(calls, *args, config):
    """The kernel's contract computed by the portable traversal on the packed-then-unpacked nodes (one
    primitive structure, every ray starting at node 0)."""
    from test_gpu_instanced import _Triangles

    from jaxrt._src.traversal import drivers
    from jaxrt._src.traversal.scene import TraversalLayout, TraversalScene

    node_lower, node_upper, node_children, _, leaf_triangle, *instance_arrays = args[:9]
    origin, direction, t_min, t_max, enabled, mask = args[gpu.SCENE_ARGS : gpu.SCENE_ARGS + 6]
    calls.append((origin.shape[0], config))
    if config.roots:  # a batch of scenes: the launch is recorded, the result left to the interpreter tests
        n = origin.shape[0]
        zero = jnp.zeros((n,), jnp.int32)
        return jnp.full((n,), jnp.inf), zero - 1, jnp.zeros((n, config.levels), jnp.int32), zero, zero, zero
    nodes = packed.unpack_nodes(packed.pack_nodes(node_lower, node_upper, node_children))
    scene = TraversalScene(*nodes, leaf_triangle, *instance_arrays)
    layout = TraversalLayout(root=0, primitive_leaves=config.primitive_leaves, levels=0, stack_size=config.stack)
    leaves = _Triangles(leaf_triangle, config.cull)
    fn = functools.partial(drivers.traverse, scene, layout, leaves, any_hit=config.any_hit)
    out = jax.vmap(fn)(origin, direction, t_min, t_max, enabled, mask)
    chain = jnp.zeros((origin.shape[0], 0), jnp.int32)
    return out.distance, out.leaf, chain, out.nodes_visited, out.primitives_tested, out.stack_overflow.astype(jnp.int32)


@pytest.fixture
def fresh_caches():
    gpu._traversal.cache_clear()
    jax.clear_caches()
    yield
    gpu._traversal.cache_clear()
    jax.clear_caches()


@pytest.fixture
def fresh_intersect_traces():
    """Drops the traces of the intersect entry points and the kernel calls around a test, so that the test
    traces the kernel path anew and leaves no trace of its replaced kernel behind. Unlike ``fresh_caches``
    it keeps the session's other compiled programs (structure builds, other tests' traversals)."""

    def drop():
        gpu._traversal.cache_clear()
        pipeline._intersect_jit.clear_cache()
        pipeline._intersect_chunks.clear_cache()

    drop()
    yield
    drop()


def test_gpu_path_plumbing_with_emulated_kernel(monkeypatch, fresh_intersect_traces):
    """Dispatch, packing and the batching rule around the kernel, with the launch emulated on any backend."""
    calls: list[int] = []
    monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    monkeypatch.setattr(gpu, "_kernel", functools.partial(_emulated_kernel, calls))
    structure, _ = _scene()
    rays = _rays(256)
    tags = (rt.tags.triangle_data, rt.tags.stats)
    for options in (dict(accept_any_intersection=True, triangle_cull_mode="back"),):
        fast = rt.Intersector(*tags, backend="gpu", **options)
        assert _resolve_backend(fast) == "gpu"
        _assert_same(
            fast.intersect(rays, structure),
            rt.Intersector(*tags, backend="portable", **options).intersect(rays, structure),
        )
    assert calls, "the kernel path did not run"

    # vmap over ray batches: one launch over the folded batch (4 x 32 rays). The emulation records the ray
    # counts it is traced with; JAX may reuse a trace for shapes seen before, so every count here is new.
    calls.clear()
    batch = jax.tree_util.tree_map(lambda a: a[:128].reshape(4, 32, *a.shape[1:]), rays)
    fast = rt.Intersector(backend="gpu")
    batched = jax.vmap(lambda r: fast.intersect(r, structure))(batch)
    assert 128 in [n for n, _ in calls], calls
    flat = rt.Intersector(backend="portable").intersect(jax.tree_util.tree_map(lambda a: a[:128], rays), structure)
    np.testing.assert_array_equal(np.asarray(batched.primitive_id).reshape(-1), flat.primitive_id)

    # vmap over (rays, structure) pairs: one launch over both scenes' rays, each ray with its own root (the
    # results are checked in the interpreter, tests/test_gpu_instanced.py).
    calls.clear()
    other, _ = _scene(seed=3)
    pair = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), structure, other)
    two = jax.tree_util.tree_map(lambda a: a[:16].reshape(2, 8, *a.shape[1:]), rays)
    jax.vmap(fast.intersect)(two, pair)
    assert [(n, c.roots, c.primitive_leaves) for n, c in calls if n == 16] == [(16, True, 2 * structure.capacity)]

    # grad: through the differentiable re-intersection of the picked triangle.
    vertices, faces = _sphere()

    def mean_distance(v, backend):
        s = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))
        hit = rt.Intersector(backend=backend).intersect(
            rt.Ray(jnp.zeros((16, 3)), jnp.asarray(_rays(16).direction) + 0.1), s
        )
        return jnp.sum(jnp.where(jnp.isfinite(hit.distance), hit.distance, 0.0))

    g_fast = jax.grad(mean_distance)(jnp.asarray(vertices), "gpu")
    g_ref = jax.grad(mean_distance)(jnp.asarray(vertices), "portable")
    np.testing.assert_allclose(g_fast, g_ref, rtol=1e-6, atol=1e-7)
    assert np.abs(np.asarray(g_fast)).sum() > 0


def test_kernel_in_triton_interpreter(monkeypatch, request):
    """The kernel itself (Triton's interpreter, on the CPU) against the portable traversal."""
    pytest.importorskip("triton")
    if os.environ.get("TRITON_INTERPRET") != "1":
        # Triton decides when it is imported whether its own library functions are interpreted, so the
        # interpreted kernel runs in a fresh process.
        command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"{__file__}::{test_kernel_in_triton_interpreter.__name__}"]  # fmt: skip
        env = dict(os.environ, TRITON_INTERPRET="1")
        done = subprocess.run(
            command, env=env, cwd=Path(__file__).parents[1], capture_output=True, text=True, timeout=900
        )
        assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
        return
    request.getfixturevalue("fresh_caches")  # in the interpreter's process only
    from test_gpu_instanced import interpreted_launch

    monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    monkeypatch.setattr(gpu, "_launch", interpreted_launch)
    monkeypatch.setattr(gpu, "MAX_PROGRAMS", 3)  # fewer programs than blocks: the strided loop runs
    structure, _ = _scene()
    rays = _rays(160)
    tags = (rt.tags.triangle_data, rt.tags.stats)
    for kernel_options in KERNEL_LAYOUTS:
        monkeypatch.setattr(gpu, "DEFAULT_OPTIONS", kernel_options)
        gpu._traversal.cache_clear()
        for options in (dict(), dict(accept_any_intersection=True, triangle_cull_mode="front")):
            # The interpreter evaluates every float operation exactly rounded; XLA on the CPU may contract
            # multiply-adds, so distances agree to rounding and leaves exactly (no ray here grazes an edge).
            got = rt.Intersector(*tags, backend="gpu", **options).intersect(rays, structure)
            want = rt.Intersector(*tags, backend="portable", **options).intersect(rays, structure)
            if kernel_options.node_width == 2:
                _assert_same(got, want, distance_rtol=1e-6)
            else:
                _assert_agree(got, want, any_hit="accept_any_intersection" in options, distance_rtol=1e-6)


# ---------------------------------------------------------------------------------------------- GPU tests


@pytest.mark.gpu
@needs_gpu
def test_auto_picks_the_kernel():
    assert gpu.unavailable_reason(rt.Intersector(rt.tags.triangle_data, rt.tags.stats)) is None
    assert _resolve_backend(rt.Intersector()) == "gpu"
    assert _resolve_backend(rt.Intersector(backend="portable")) == "portable"


@pytest.mark.gpu
@needs_gpu
@pytest.mark.parametrize(
    "any_hit, cull, winding",
    # The kernel's cull argument takes 0, +1 (cull "front", clockwise winding) and -1 (counterclockwise).
    [
        (False, "none", "clockwise"),
        (True, "none", "clockwise"),
        (False, "front", "clockwise"),
        (True, "front", "counterclockwise"),
    ],
)
def test_kernel_equals_portable(any_hit, cull, winding, layout):
    structure, _ = _scene()
    rays = _rays(4096)
    tags = (rt.tags.triangle_data, rt.tags.stats)
    options = dict(accept_any_intersection=any_hit, triangle_cull_mode=cull, front_facing_winding=winding)
    got = rt.Intersector(*tags, backend="gpu", **options).intersect(rays, structure)
    want = rt.Intersector(*tags, backend="portable", **options).intersect(rays, structure)
    # XLA may contract multiply-adds in the portable path; the kernel does not: distances agree to rounding.
    _compare(got, want, layout, any_hit=any_hit, distance_rtol=1e-6)
    assert not np.asarray(got.stack_overflow).any()
    disabled = ~np.asarray(jnp.any(rays.direction != 0, -1) & (rays.min_distance <= rays.max_distance))
    assert (np.asarray(got.type)[disabled] == 0).all() and (np.asarray(got.nodes_visited)[disabled] == 0).all()


@pytest.mark.gpu
@needs_gpu
@pytest.mark.parametrize("any_hit", [False, True])
def test_kernel_equals_portable_on_the_high_quality_tree(any_hit, layout):
    rng = np.random.default_rng(3)
    vertices, faces = _sphere()
    soup = (rng.uniform(-1.2, 1.2, (40, 1, 3)) + 0.25 * rng.standard_normal((40, 3, 3))).astype(np.float32)
    geometries = [rt.TriangleGeometry(vertices, faces), rt.TriangleGeometry(soup.reshape(-1, 3))]
    structure = rt.build_primitive_structure(geometries, quality="high")
    rays = _rays(4096)
    tags = (rt.tags.triangle_data, rt.tags.stats)
    got = rt.Intersector(*tags, backend="gpu", accept_any_intersection=any_hit).intersect(rays, structure)
    want = rt.Intersector(*tags, backend="portable", accept_any_intersection=any_hit).intersect(rays, structure)
    _compare(got, want, layout, any_hit=any_hit, distance_rtol=1e-6)


@pytest.mark.gpu
@needs_gpu
def test_watertight_far_from_origin(layout):
    """Rays from inside a closed ellipsoid far from the origin, aimed at its vertices and edge midpoints."""
    vertices, faces = icosphere(5)
    centre = np.array([148376.0, 1234.0, -223423.0])
    scale = np.array([3.0, 2.0, 1.5])
    mesh = (vertices * scale + centre).astype(np.float32)
    targets = np.concatenate([mesh.astype(np.float64), mesh[edges(faces)].astype(np.float64).mean(axis=1)])
    origin = np.broadcast_to(centre, targets.shape).astype(np.float32)
    direction = (targets - origin.astype(np.float64)).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(mesh, faces))
    rays = rt.Ray(origin, direction)
    got = rt.Intersector(backend="gpu").intersect(rays, structure)
    want = rt.Intersector(backend="portable").intersect(rays, structure)
    leaks = int((np.asarray(got.type) == 0).sum())
    portable_leaks = int((np.asarray(want.type) == 0).sum())
    differ = int((np.asarray(got.primitive_id) != np.asarray(want.primitive_id)).sum())
    print(
        f"\nfar ellipsoid, {len(targets)} rays: kernel leaks {leaks}, portable leaks {portable_leaks}, primitives differ {differ}"
    )
    # Without contraction every edge function has the exact sign or is 0 (rounding is monotonic), so no ray
    # leaks, also through a vertex; the portable path's answers depend on how XLA contracts multiply-adds.
    assert leaks == 0
    # Where the two paths pick different triangles, they are ties: rays through a shared vertex or edge.
    ties = np.asarray(got.primitive_id) != np.asarray(want.primitive_id)
    np.testing.assert_allclose(np.asarray(got.distance)[ties], np.asarray(want.distance)[ties], rtol=1e-6)


@pytest.mark.gpu
@needs_gpu
def test_axis_parallel_rays_on_slab_planes(layout):
    """Axis-parallel rays starting exactly on box faces and edges of a cube: no NaN, same answers."""
    lower, upper = -1.0, 1.0
    corners = np.array([[x, y, z] for x in (lower, upper) for y in (lower, upper) for z in (lower, upper)], np.float32)
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ],
        np.int32,
    )
    structure = rt.build_primitive_structure(rt.TriangleGeometry(corners, faces))
    grid = np.linspace(-1.5, 1.5, 13, dtype=np.float32)
    origins, directions = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = np.meshgrid(grid, grid, indexing="ij")
            o = np.zeros((u.size, 3), np.float32)
            o[:, axis] = -2.0 * sign
            o[:, (axis + 1) % 3], o[:, (axis + 2) % 3] = u.ravel(), v.ravel()
            d = np.zeros_like(o)
            d[:, axis] = sign
            origins.append(o)
            directions.append(d)
    rays = rt.Ray(np.concatenate(origins), np.concatenate(directions))
    tags = (rt.tags.triangle_data, rt.tags.stats)
    got = rt.Intersector(*tags, backend="gpu").intersect(rays, structure)
    want = rt.Intersector(*tags, backend="portable").intersect(rays, structure)
    assert not np.isnan(np.asarray(got.distance)).any()
    _compare(got, want, layout)


@pytest.mark.gpu
@needs_gpu
def test_degenerate_triangles_never_hit(layout):
    tri = np.array(
        [[[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 0, 0], [0, 0, 0], [0, 0, 0]], [[0, 1, 0], [0, 1, 0], [1, 1, 0]]],
        np.float32,
    )
    structure = rt.build_primitive_structure(rt.TriangleGeometry(tri.reshape(-1, 3)))
    rng = np.random.default_rng(0)
    target = rng.uniform(-0.5, 2.5, (512, 3)).astype(np.float32)
    target[:256, 2] = 0.0
    origin = (target + rng.normal(size=(512, 3))).astype(np.float32)
    rays = rt.Ray(origin, target - origin)
    got = rt.Intersector(backend="gpu").intersect(rays, structure)
    assert (np.asarray(got.type) == 0).all()


@pytest.mark.gpu
@needs_gpu
def test_composes_with_jit_vmap_grad():
    structure, vertices = _scene()
    rays = _rays(1024)
    fast, slow = rt.Intersector(backend="gpu"), rt.Intersector(backend="portable")
    want = slow.intersect(rays, structure)
    jitted = jax.jit(lambda r, s: fast.intersect(r, s).primitive_id)(rays, structure)
    np.testing.assert_array_equal(jitted, want.primitive_id)
    batch = jax.tree_util.tree_map(lambda a: a.reshape(8, 128, *a.shape[1:]), rays)

    def batched(*fields):
        return jax.vmap(lambda *f: fast.intersect(rt.Ray(*f), structure).primitive_id)(*fields)

    fields = (batch.origin, batch.direction, batch.min_distance, batch.max_distance)
    batched_fn = jax.jit(batched)
    np.testing.assert_array_equal(np.asarray(batched_fn(*fields)).reshape(-1), want.primitive_id)
    hlo = batched_fn.lower(*fields).as_text()
    launches, loops = hlo.count("custom_call @triton_kernel_call"), hlo.count("stablehlo.while")
    print(f"\nvmap over 8 ray batches: {launches} kernel launch(es), {loops} while loop(s) in the HLO")
    assert launches == 1 and loops == 0  # the batch is folded into one launch
    other, _ = _scene(seed=5)
    pair = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), structure, other)
    two = jax.tree_util.tree_map(lambda a: a.reshape(2, 512, *a.shape[1:]), rays)
    pairs_fn = jax.jit(jax.vmap(lambda r, s: fast.intersect(r, s).primitive_id))
    per_pair = pairs_fn(two, pair)
    np.testing.assert_array_equal(per_pair[0], want.primitive_id[:512])
    second = jax.tree_util.tree_map(lambda a: a[1], two)
    np.testing.assert_array_equal(per_pair[1], slow.intersect(second, other).primitive_id)
    leaves, tree = jax.tree_util.tree_flatten((two, pair))
    hlo = jax.jit(lambda *a: pairs_fn(*jax.tree_util.tree_unflatten(tree, a))).lower(*leaves).as_text()
    launches, loops = hlo.count("custom_call @triton_kernel_call"), hlo.count("stablehlo.while")
    print(f"vmap over 2 (rays, structure) pairs: {launches} kernel launch(es), {loops} while loop(s) in the HLO")
    assert launches == 1 and loops == 0  # both scenes in one launch

    _, faces = _sphere()

    def total(v, intersector):
        s = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))
        hit = intersector.intersect(rt.Ray(jnp.zeros((64, 3)), jnp.asarray(_rays(64).direction) + 0.1), s)
        return jnp.sum(jnp.where(jnp.isfinite(hit.distance), hit.distance, 0.0))

    v = jnp.asarray(_sphere()[0])
    np.testing.assert_allclose(jax.grad(total)(v, fast), jax.grad(total)(v, slow), rtol=1e-6, atol=1e-7)


@pytest.mark.gpu
@needs_gpu
def test_gradients_equal_the_portable_paths():
    """Distance and barycentric gradients w.r.t. vertices, origins and directions: kernel and portable agree."""
    _, faces = _sphere()
    rays = _rays(512, seed=3)
    weights = jnp.asarray(np.random.default_rng(4).uniform(0.5, 1.5, (512, 3)), jnp.float32)

    def loss(v, origin, direction, intersector):
        s = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))
        hit = rt.Intersector(rt.tags.triangle_data, backend=intersector).intersect(
            rt.Ray(origin, direction, rays.min_distance, rays.max_distance), s
        )
        distance = jnp.where(jnp.isfinite(hit.distance), hit.distance, 0.0)
        return jnp.sum(weights[:, 0] * distance + jnp.sum(weights[:, 1:] * hit.triangle_barycentric_coord, -1))

    args = (jnp.asarray(_sphere()[0]), rays.origin, rays.direction)
    fast = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3)(*args, "gpu")
    slow = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3)(*args, "portable")
    for name, a, b in zip(("vertices", "origin", "direction"), fast, slow, strict=True):
        assert np.all(np.isfinite(np.asarray(a))), name
        # Same primitive per ray; the recomputed hit is the same JAX code in both, so gradients agree to
        # rounding (the kernel's distance only enters through the straight-through value).
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6, err_msg=name)
        assert np.abs(np.asarray(b)).sum() > 0, name


@pytest.mark.gpu
@needs_gpu
def test_large_batch_walks_blocks_with_a_stride(monkeypatch, fresh_caches):
    """More ray blocks than programs: each program traces several blocks with the same stack scratch."""
    monkeypatch.setattr(gpu, "MAX_PROGRAMS", 5)
    structure, _ = _scene()
    rays = _rays(2048, seed=7)
    got = rt.Intersector(rt.tags.stats, backend="gpu").intersect(rays, structure)
    want = rt.Intersector(rt.tags.stats, backend="portable").intersect(rays, structure)
    _compare(got, want, gpu.DEFAULT_OPTIONS, distance_rtol=1e-6)
