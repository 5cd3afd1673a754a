"""Each shared leaf formula (:mod:`jaxrt._src.formulas`) gives the same results on JAX, Numba and Triton.

Every formula gets the same float32 inputs on every backend: random values, and hard cases (rays through the
shared edges and vertices of a triangle fan, axis-parallel rays starting on slab planes, geometry about 1e4 to
1e5 from the origin, degenerate triangles, empty boxes, grazing rays, zero radii). JAX runs jitted and vmapped,
Numba in a compiled loop, Triton in its interpreter (``TRITON_INTERPRET=1``, set before Triton is imported, so
in a subprocess; skipped where Triton is not installed).

Results are compared bit for bit (floats as floats: ``-0 == +0``, NaN where NaN), with two stated exceptions,
both about multiply-adds, which the backends evaluate differently on purpose:

- ``sub_product`` and ``sum_of_products`` (the sheared vertex and the plane distance of the watertight test)
  are contracted into fused multiply-adds by XLA on the CPU, and so by the Numba instance (which must reproduce
  the portable path there), and left unfused by the Triton kernel (compiled without contraction, as on the
  GPU). JAX and Numba agree bit for bit; Triton agrees bit for bit with the unfused float32 expression.
- ``dot3`` is ``jnp.dot`` in JAX, which XLA may contract or reorder, and ``(ax bx + ay by) + az bz`` unfused in
  Numba and Triton (the analytic shapes and the closest point of a triangle). Numba and Triton agree bit for
  bit; JAX agrees with them within the bounds of :data:`SHAPE_RTOL` (same decisions) and, for the closest
  point, within 8 ulps of the coordinates, except on degenerate inputs (:data:`DEGENERATE_ROWS`).
"""

from __future__ import annotations

import functools
import linecache
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt._src import formulas
from jaxrt._src.primitives.box import FAR_SCALE, PARALLEL_RECIPROCAL

F32 = np.float32
#: Formulas whose JAX instance evaluates ``dot3`` with ``jnp.dot`` (see the module docstring).
DOT_FORMULAS = {("analytic", "sphere"), ("analytic", "disk"), ("analytic", "capped_cylinder"), ("sphere", "ray_sphere")}
POINT_FORMULAS = {("point_triangle", "closest_on_triangle"), ("sphere", "closest_on_sphere")}
#: Formulas with an XLA-contracted multiply-add (see the module docstring).
CONTRACTED = {("triangle", "sheared_vertex"), ("triangle", "plane_distance")}


# --- inputs ----------------------------------------------------------------------------------------------------


def _fan(rng: np.random.Generator, offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A triangle fan around a centre vertex, far from the origin by ``offset``, and rays from a point above it
    aimed exactly at its vertices and edge midpoints: ``(origins, directions, triangles (n, 3, 3))`` where each
    ray is paired with each triangle of the fan."""
    k = 6
    angles = np.arange(k) * 2 * np.pi / k + 0.3
    rim = np.stack([np.cos(angles), np.sin(angles), 0.1 * np.sin(3 * angles)], -1) * 2.5
    centre = np.zeros(3)
    shift = np.array([offset, -0.37 * offset, 0.61 * offset])
    tris = np.stack([[centre, rim[i], rim[(i + 1) % k]] for i in range(k)]) + shift
    targets = np.concatenate([[centre], rim, (rim + np.roll(rim, -1, 0)) / 2, rim / 2]) + shift
    eye = shift + np.array([0.31, -0.22, 7.0])
    origin = np.repeat(eye[None], len(targets), 0)
    direction = targets - eye
    pair_o = np.repeat(origin, k, 0)
    pair_d = np.repeat(direction, k, 0)
    pair_t = np.tile(tris, (len(targets), 1, 1))
    return pair_o.astype(F32), pair_d.astype(F32), pair_t.astype(F32)


def _triangle_rays(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Origins, directions and triangles: random, the fans near and far, axis-parallel and degenerate."""
    n = 256
    o = rng.normal(size=(n, 3)) * 2
    t = rng.normal(size=(n, 3, 3)) * 2
    d = t.mean(1) + rng.normal(size=(n, 3)) * 0.5 - o  # about half of them hit
    d[:32, 0] = 0  # axis-parallel rays
    d[16:32, 1] = 0
    t[32:48, 2] = t[32:48, 0] + 2.0 * (t[32:48, 1] - t[32:48, 0])  # collinear (degenerate) triangles
    t[48:56, 1] = t[48:56, 0]  # repeated vertices
    parts = [(o, d, t)] + [_fan(rng, offset) for offset in (0.0, 1.3e4, 9.7e4)]
    return tuple(np.concatenate([p[i] for p in parts]).astype(F32) for i in range(3))


def _sheared(o, d, t):
    """The stage inputs of the watertight test, as the JAX primitives compute them."""
    from jaxrt._src.primitives import triangle

    def one(o, d, t):
        ray = triangle.shear_ray(o, d)
        rel = t - o
        comp = [triangle._component(rel, k) for k in (ray.kx, ray.ky, ray.kz)]
        return ray, comp

    ray, comp = jax.jit(jax.vmap(one))(o, d, t)
    return ray, [np.asarray(c) for c in comp]


def _inputs() -> dict[tuple[str, str], tuple[np.ndarray, ...]]:
    """The inputs of every formula tested: ``(module, function) -> arrays`` of one length."""
    rng = np.random.default_rng(7)
    cases: dict[tuple[str, str], tuple[np.ndarray, ...]] = {}

    # Boxes: random, far from the origin, empty, and axis-parallel rays starting on slab planes.
    n = 512
    lo = rng.normal(size=(n, 3)) * 3
    hi = lo + rng.random((n, 3)) * 2
    o = rng.normal(size=(n, 3)) * 3
    lo[64:128] += 4.2e4
    hi[64:128] += 4.2e4
    o[64:128] += 4.2e4 + rng.normal(size=(64, 3))
    d = (lo + hi) / 2 + rng.normal(size=(n, 3)) * 1.5 - o  # about half of the rays hit their box
    d[np.arange(128, 256), rng.integers(0, 3, 128)] = 0
    on_plane = np.arange(128, 192)
    o[on_plane, 1] = lo[on_plane, 1]  # on a slab plane, moving in it
    d[on_plane, 1] = 0
    o[192:224, 0] = hi[192:224, 0]
    lo[224:240], hi[224:240] = np.inf, -np.inf  # empty boxes
    lo, hi, o = lo.astype(F32), hi.astype(F32), o.astype(F32)
    d = d.astype(F32)
    from jaxrt._src.numerics import safe_reciprocal

    inv = np.asarray(safe_reciprocal(jnp.asarray(d)))
    full = lambda x, dtype=F32: np.full(n, x, dtype)  # noqa: E731
    for axis in range(3):
        cases[("box", f"slab_axis:{axis}")] = (lo[:, axis], hi[:, axis], o[:, axis], inv[:, axis], full(PARALLEL_RECIPROCAL))  # fmt: skip
    plain = np.all(np.abs(inv) < PARALLEL_RECIPROCAL, axis=1)
    cases[("box", "slab_distances")] = (lo[plain, 0], hi[plain, 0], o[plain, 0], inv[plain, 0])
    slabs = jax.jit(jax.vmap(formulas.instance("box", "jax").slab_axis))
    near_far = [np.asarray(x) for axis in range(3) for x in slabs(lo[:, axis], hi[:, axis], o[:, axis], inv[:, axis], full(PARALLEL_RECIPROCAL))]  # fmt: skip
    t_min = np.where(rng.random(n) < 0.2, rng.random(n), 0).astype(F32)
    t_max = np.where(rng.random(n) < 0.3, rng.random(n) * 5, np.inf).astype(F32)
    cases[("box", "box_hit")] = (*near_far, lo[:, 0], hi[:, 0], t_min, t_max, full(FAR_SCALE))

    # The watertight test, stage by stage, on the JAX stage inputs.
    o, d, t = _triangle_rays(rng)
    m = len(o)
    cases[("triangle", "shear_axes")] = (d[:, 0], d[:, 1], d[:, 2])
    ray, (rx, ry, rz) = _sheared(o, d, t)
    pick = lambda k: np.choose(np.asarray(k), d.T)  # noqa: E731
    cases[("triangle", "shear")] = (pick(ray.kx), pick(ray.ky), pick(ray.kz))
    shear = np.asarray(ray.shear)
    sheared = []
    for v in range(3):
        args = (rx[:, v], ry[:, v], rz[:, v], shear[:, 0], shear[:, 1], shear[:, 2])
        cases[("triangle", f"sheared_vertex:{v}")] = args
        sheared.append([np.asarray(x) for x in jax.jit(jax.vmap(formulas.instance("triangle", "jax").sheared_vertex))(*args)])  # fmt: skip
    (ax, ay, az), (bx, by, bz), (cx, cy, cz) = sheared
    cases[("triangle", "edge_functions")] = (ax, ay, bx, by, cx, cy)
    e = [np.asarray(x) for x in jax.jit(jax.vmap(formulas.instance("triangle", "jax").edge_functions))(ax, ay, bx, by, cx, cy)]  # fmt: skip
    cases[("triangle", "edges_inside")] = tuple(e)
    det = e[0] + e[1] + e[2]
    cases[("triangle", "facing_accepts")] = (det, rng.integers(-1, 2, m).astype(np.int32))
    cases[("triangle", "plane_distance")] = (*e, az, bz, cz, det)
    tt = rng.normal(size=m).astype(F32)
    cases[("triangle", "in_interval")] = (tt, np.where(rng.random(m) < 0.5, tt, 0).astype(F32), np.where(rng.random(m) < 0.5, tt, 1).astype(F32))  # fmt: skip

    # Analytic shapes: rays aimed near each shape (hits, misses, grazing), origins inside, zero radii, far away.
    n = 512
    p = rng.normal(size=(n, 3)) * 2
    q = p + rng.normal(size=(n, 3))
    radius = rng.random(n) * 1.5 + 0.05
    radius[:16] = 0
    o = rng.normal(size=(n, 3)) * 6
    o[16:48] = p[16:48] + rng.normal(size=(32, 3)) * 0.1  # inside
    aim = p + rng.normal(size=(n, 3)) * radius[:, None]
    d = aim - o
    d[48:80] *= rng.random((32, 1)) * 3 + 0.01  # unnormalised directions
    d[80:112, 2] = 0
    shift = np.where(np.arange(n)[:, None] >= n - 64, 3.1e4, 0)
    p, q, o = p + shift, q + shift, o + shift
    normal = rng.normal(size=(n, 3))
    normal[112:128] = d[112:128]  # a ray along the disk's normal
    normal[128:144] = np.cross(d[128:144], rng.normal(size=(16, 3)))  # a ray in the disk's plane direction
    q[144:160] = p[144:160]  # zero-length cylinders
    t_min = np.zeros(n, F32)
    t_max = np.where(rng.random(n) < 0.2, rng.random(n) * 8, np.inf).astype(F32)
    vec = lambda x: tuple(x.astype(F32).T)  # noqa: E731
    ray = (*vec(o), *vec(d), t_min, t_max)
    cases[("analytic", "sphere")] = (*vec(p), radius.astype(F32), *ray)
    cases[("analytic", "disk")] = (*vec(p), *vec(normal), radius.astype(F32), *ray)
    cases[("analytic", "capped_cylinder")] = (*vec(p), *vec(q), radius.astype(F32), *ray)
    # Built-in spheres: the same rays, and bad radii (negative, NaN, infinite: never a hit).
    bad = radius.astype(F32)
    bad[16:20], bad[20:24], bad[24:28] = -1.0, np.nan, np.inf
    cases[("sphere", "ray_sphere")] = (*vec(p), bad, *ray)
    point = p + rng.normal(size=(n, 3)) * 2
    point[:8] = p[:8]  # at the centre
    point[8:40] = p[8:40] + rng.normal(size=(32, 3)) * 0.1  # inside
    cases[("sphere", "closest_on_sphere")] = (*vec(point), *vec(p), radius.astype(F32))

    # The closest point of a triangle: every Voronoi region, degenerate triangles, points far away.
    n = 512
    tri = rng.normal(size=(n, 3, 3))
    tri[:32, 2] = tri[:32, 0] + 0.5 * (tri[:32, 1] - tri[:32, 0])  # collinear
    tri[32:48, 1] = tri[32:48, 0]  # a zero-length edge
    tri[48:56, 1] = tri[48:56, 2] = tri[48:56, 0]  # a point
    point = tri.mean(1) + rng.normal(size=(n, 3)) * 2
    point[56:88] = tri[56:88, 0]  # on a vertex
    point[88:120] = (tri[88:120, 1] + tri[88:120, 2]) / 2  # on an edge
    far = np.arange(n) >= n - 64
    point[far] += 1.7e4
    tri[far] += 1.7e4
    cases[("point_triangle", "closest_on_triangle")] = (*vec(point), *vec(tri[:, 0]), *vec(tri[:, 1]), *vec(tri[:, 2]))  # fmt: skip
    return cases


# --- backends --------------------------------------------------------------------------------------------------


def _function(module: str, key: str, backend: str):
    return getattr(formulas.instance(module, backend), key.split(":")[0])


def run_jax(module: str, key: str, args: tuple[np.ndarray, ...]) -> list[np.ndarray]:
    out = jax.jit(jax.vmap(_function(module, key, "jax")))(*args)
    return [np.asarray(x) for x in (out if isinstance(out, tuple) else (out,))]


def _loop_source(n_in: int, n_out: int) -> str:
    ins = [f"a{i}" for i in range(n_in)]
    outs = [f"o{i}" for i in range(n_out)]
    body = f"        r = fn({', '.join(f'{a}[i]' for a in ins)})\n"
    if n_out == 1:
        body += "        o0[i] = r\n"
    else:
        body += "".join(f"        {o}[i] = r[{k}]\n" for k, o in enumerate(outs))
    return f"def run({', '.join(ins + outs)}):\n    for i in range(a0.shape[0]):\n{body}"


def run_numba(module: str, key: str, args: tuple[np.ndarray, ...], like: list[np.ndarray]) -> list[np.ndarray]:
    import numba

    namespace = {"fn": _function(module, key, "numba")}
    exec(_loop_source(len(args), len(like)), namespace)
    outs = [np.empty_like(x) for x in like]
    numba.njit(namespace["run"])(*args, *outs)
    return outs


def _triton_kernel_source(n_in: int, n_out: int) -> str:
    ins = [f"p{i}" for i in range(n_in)]
    outs = [f"q{i}" for i in range(n_out)]
    loads = "".join(f"    a{i} = tl.load(p{i} + lane)\n" for i in range(n_in))
    call = f"    r = fn({', '.join(f'a{i}' for i in range(n_in))})\n"
    if n_out == 1:
        call += "    r = (r,)\n"
    stores = "".join(f"    tl.store(q{k} + lane, r[{k}].to(q{k}.dtype.element_ty))\n" for k in range(n_out))
    return f"def kernel({', '.join(ins + outs)}, N: tl.constexpr):\n    lane = tl.arange(0, N)\n{loads}{call}{stores}"


def run_triton(module: str, key: str, args: tuple[np.ndarray, ...], like: list[np.ndarray]) -> list[np.ndarray]:
    """One formula in Triton's interpreter, on arrays padded to a power of two (the process must have
    ``TRITON_INTERPRET=1`` set before importing Triton)."""
    import triton
    import triton.language as tl

    n = len(args[0])
    size = 1 << max(n - 1, 1).bit_length()
    padded = [np.concatenate([a, np.repeat(a[-1:], size - n)]) for a in args]
    source = _triton_kernel_source(len(args), len(like))
    filename = f"<test_formulas {module}.{key}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    namespace = {"fn": _function(module, key, "triton"), "tl": tl}
    exec(compile(source, filename, "exec"), namespace)
    kernel = triton.jit(namespace["kernel"])
    # The interpreter's loads and stores need integer and float pointers; booleans travel as int8.
    from test_gpu_instanced import _HostArray  # a NumPy array the interpreter takes for a tensor

    outs = [np.empty(size, np.int8 if x.dtype == bool else x.dtype) for x in like]
    kernel[(1,)](*(_HostArray(a) for a in padded), *(_HostArray(o) for o in outs), N=size)
    return [o[:n].astype(x.dtype) for o, x in zip(outs, like, strict=True)]


# --- the comparisons -------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict:
    """Every formula's inputs and its outputs on JAX, Numba and (where installed) Triton."""
    cases = _inputs()
    out: dict = {}
    for (module, key), args in cases.items():
        ref = run_jax(module, key, args)
        out[(module, key)] = {"args": args, "jax": ref, "numba": run_numba(module, key, args, ref)}
    try:
        import triton  # noqa: F401
    except ImportError:
        return out
    folder = tmp_path_factory.mktemp("formulas")
    np.savez(folder / "in.npz", **{f"{m}|{k}|{i}": a for (m, k), c in out.items() for i, a in enumerate(c["args"])})
    np.savez(folder / "like.npz", **{f"{m}|{k}|{i}": a for (m, k), c in out.items() for i, a in enumerate(c["jax"])})
    env = dict(os.environ, TRITON_INTERPRET="1")
    done = subprocess.run(
        [sys.executable, __file__, str(folder)], env=env, cwd=Path(__file__).parents[1], capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    got = np.load(folder / "out.npz")
    for (module, key), c in out.items():
        c["triton"] = [got[f"{module}|{key}|{i}"] for i in range(len(c["jax"]))]
    return out


def _triton_main(folder: str) -> None:
    """The subprocess: every formula in Triton's interpreter."""
    ins, like = np.load(Path(folder) / "in.npz"), np.load(Path(folder) / "like.npz")
    groups: dict = {}
    for name in ins.files:
        module, key, i = name.split("|")
        groups.setdefault((module, key), {})[int(i)] = ins[name]
    result = {}
    for (module, key), args in groups.items():
        refs = [like[f"{module}|{key}|{i}"] for i in range(sum(n.startswith(f"{module}|{key}|") for n in like.files))]
        outs = run_triton(module, key, tuple(args[i] for i in range(len(args))), refs)
        result.update({f"{module}|{key}|{i}": o for i, o in enumerate(outs)})
    np.savez(Path(folder) / "out.npz", **result)


def _names() -> list[tuple[str, str]]:
    return [
        *(("box", f"slab_axis:{a}") for a in range(3)),
        ("box", "slab_distances"),
        ("box", "box_hit"),
        ("triangle", "shear_axes"),
        ("triangle", "shear"),
        *(("triangle", f"sheared_vertex:{v}") for v in range(3)),
        ("triangle", "edge_functions"),
        ("triangle", "edges_inside"),
        ("triangle", "facing_accepts"),
        ("triangle", "plane_distance"),
        ("triangle", "in_interval"),
        ("analytic", "sphere"),
        ("analytic", "disk"),
        ("analytic", "capped_cylinder"),
        ("point_triangle", "closest_on_triangle"),
        ("sphere", "ray_sphere"),
        ("sphere", "closest_on_sphere"),
    ]


def _equal(a: np.ndarray, b: np.ndarray, what: str) -> None:
    assert a.dtype == b.dtype, (what, a.dtype, b.dtype)
    np.testing.assert_array_equal(a, b, err_msg=what)


def _unfused(module: str, key: str, args: tuple[np.ndarray, ...]) -> list[np.ndarray]:
    """The float32 value of a contracted formula with every operation rounded (NumPy never fuses)."""
    with np.errstate(all="ignore"):
        if key.startswith("sheared_vertex"):
            r_x, r_y, r_z, sx, sy, sz = args
            return [r_x - sx * r_z, r_y - sy * r_z, sz * r_z]
        e0, e1, e2, z0, z1, z2, det = args
        return [(e0 * z0 + e1 * z1 + e2 * z2) / np.where(det == 0, F32(1), det)]


def _ulp(x: np.ndarray) -> np.ndarray:
    return np.spacing(np.abs(x).astype(F32))


@pytest.mark.parametrize("name", _names(), ids=lambda n: f"{n[0]}.{n[1]}")
def test_numba_equals_jax_or_triton(results, name):
    """Numba: bit for bit JAX's values, except ``dot3`` (Triton's, see the module docstring)."""
    c = results[name]
    if name in DOT_FORMULAS | POINT_FORMULAS:
        if "triton" not in c:
            pytest.skip("the unfused dot product is compared with Triton's (Triton is not installed)")
        for k, (a, b) in enumerate(zip(c["numba"], c["triton"], strict=True)):
            _equal(a, b, f"{name} output {k}: numba vs triton")
        return
    for k, (a, b) in enumerate(zip(c["numba"], c["jax"], strict=True)):
        _equal(a, b, f"{name} output {k}: numba vs jax")


@pytest.mark.parametrize("name", [n for n in _names() if n not in DOT_FORMULAS | POINT_FORMULAS], ids=lambda n: f"{n[0]}.{n[1]}")  # fmt: skip
def test_triton_equals_jax(results, name):
    """Triton (interpreted): bit for bit JAX's values, except where JAX contracts: there the unfused
    expression's values (the formulas with ``dot3`` are compared with Numba's above)."""
    c = results[name]
    if "triton" not in c:
        pytest.skip("Triton is not installed")
    contracted = (name[0], name[1].split(":")[0]) in CONTRACTED
    want = _unfused(*name, c["args"]) if contracted else c["jax"]
    for k, (a, b) in enumerate(zip(c["triton"], want, strict=True)):
        _equal(a, b.astype(a.dtype), f"{name} output {k}: triton vs {'unfused' if contracted else 'jax'}")


@pytest.mark.parametrize("name", [n for n in _names() if (n[0], n[1].split(":")[0]) in CONTRACTED], ids=lambda n: f"{n[0]}.{n[1]}")  # fmt: skip
def test_contraction_is_the_only_difference(results, name):
    """Where JAX contracts a multiply-add, its value differs from the unfused one by at most the rounding of the
    product (half an ulp of each product term) plus the rounding of the result."""
    c = results[name]
    args = c["args"]
    want = _unfused(*name, args)
    if name[1].startswith("sheared_vertex"):
        _equal(c["jax"][2], want[2], f"{name}: z (a plain product)")
        # c - a b: the unfused product's rounding (half an ulp of a b), then each result's rounding.
        bounds = [0.5 * _ulp(args[k] * args[2]) for k in (3, 4)]
        pairs = zip(c["jax"][:2], want[:2], bounds, strict=True)
    else:
        # (e0 z0 + e1 z1) + e2 z2: the roundings of up to three products and two sums, each at most half an ulp
        # of S = |e0 z0| + |e1 z1| + |e2 z2|, so 2.5 ulp(S) on either side, divided by det (rounded once more).
        e0, e1, e2, z0, z1, z2, det = args
        scale = np.abs(np.where(det == 0, F32(1), det))
        bounds = [5 * _ulp(np.abs(e0 * z0) + np.abs(e1 * z1) + np.abs(e2 * z2)) / scale]
        pairs = zip(c["jax"], want, bounds, strict=True)
    for got, exact, bound in pairs:
        finite = np.isfinite(exact)
        assert (np.isfinite(got) == finite).all(), name
        error = np.abs(got.astype(np.float64) - exact)[finite]
        bound = (bound + _ulp(np.maximum(np.abs(got), np.abs(exact))))[finite]
        assert (error <= bound).all(), (name, (error / bound).max())


#: JAX against the unfused dot products, relative distance bounds of the shapes' hits: the sphere and the disk
#: within 8 ulps; the capped cylinder's wall solves a quadratic whose coefficients carry ``|q - p|^4`` and
#: cancel, which amplifies a dot product's rounding (124 ulps at most on these inputs): 256 ulps.
SHAPE_RTOL = {
    "sphere": 8 * 2.0**-23,
    "ray_sphere": 8 * 2.0**-23,
    "disk": 8 * 2.0**-23,
    "capped_cylinder": 256 * 2.0**-23,
}
#: Rows of the degenerate cases (zero radii; collinear or repeated triangle vertices), whose values are rounding
#: noise amplified (a root of a zero-radius shape, barycentrics over an area made of rounding): there Numba and
#: Triton agree bit for bit and JAX is not compared.
DEGENERATE_ROWS = {"analytic": 16, "point_triangle": 56, "sphere": 16}


@pytest.mark.parametrize("name", sorted(DOT_FORMULAS | POINT_FORMULAS), ids=lambda n: f"{n[0]}.{n[1]}")
def test_jax_dot_products_agree_with_the_unfused_ones(results, name):
    """``jnp.dot`` against the unfused dot product (Numba's values, equal to Triton's): the same hit decisions
    and distances within :data:`SHAPE_RTOL`; for the closest point of a triangle, the same point within 8 ulps
    of the coordinates' magnitude (barycentrics are compared through the point they give, which is unique even
    where a near-tie of Voronoi regions changes them)."""
    c = results[name]
    skip = DEGENERATE_ROWS[name[0]]
    if name == ("sphere", "closest_on_sphere"):  # the point and the signed distance within 8 ulps of the scale
        scale = np.abs(np.stack(c["args"], 1)).max(1) + np.abs(c["args"][-1])
        for k, (a, b) in enumerate(zip(c["jax"], c["numba"], strict=True)):
            error = np.abs(a.astype(np.float64) - b)
            assert (error <= 8 * np.spacing(scale.astype(F32))).all(), (k, error.max())
        return
    if name in POINT_FORMULAS:
        corners = np.stack(c["args"], 1)[skip:].reshape(-1, 4, 3).astype(np.float64)

        def point(u, v):
            u, v = u[skip:, None].astype(np.float64), v[skip:, None].astype(np.float64)
            return corners[:, 1] + u * (corners[:, 2] - corners[:, 1]) + v * (corners[:, 3] - corners[:, 1])

        error = np.linalg.norm(point(*c["jax"]) - point(*c["numba"]), axis=1)
        bound = 8 * np.spacing(np.abs(corners).max(axis=(1, 2)).astype(F32))
        assert (error <= bound).all(), (error / bound).max()
        return
    hit_j, t_j = (x[skip:] for x in c["jax"][:2])
    hit_n, t_n = (x[skip:] for x in c["numba"][:2])
    _equal(hit_j, hit_n, f"{name}: hit")
    assert hit_n.sum() > 50, name
    np.testing.assert_allclose(t_j[hit_n], t_n[hit_n], rtol=SHAPE_RTOL[name[1]], err_msg=str(name))


def test_watertight_on_shared_edges_and_vertices(results):
    """Rays aimed exactly at the fan's vertices and edge midpoints (near and ~1e5 from the origin) hit at least
    one triangle of the fan on every backend (the edge functions and the inside test are bit-identical)."""
    c = results[("triangle", "edges_inside")]
    n_fan = 6 * (1 + 6 + 6 + 6)
    interior = [0, *range(13, 19)]  # the centre vertex and the spokes' midpoints (the rim is the fan's border)
    for backend in ("jax", "numba", "triton"):
        if backend not in c:
            continue
        inside = c[backend][0][-3 * n_fan :].reshape(3, -1, 6)[:, interior]  # (fan, ray, triangle)
        assert inside.any(axis=2).all(), backend
        assert (inside.sum(axis=2) >= 2).any(), backend  # rays through shared edges hit both sides


def test_numba_vector_slab_test_makes_the_formula_decisions(results):
    """The Numba loop's vector slab test of a node's two boxes (``cpu_kernel._box_pair``, LLVM vector code on the
    rows of ``box_rows``, for rays parallel to no axis) decides as the box formula, with the same entries: each
    ray of the box inputs against its own box and the next ray's."""
    import numba

    from jaxrt._src.traversal import cpu_kernel

    lo, hi, o, inv = (np.stack([results[("box", f"slab_axis:{a}")]["args"][i] for a in range(3)], 1) for i in range(4))
    t_min, t_max = results[("box", "box_hit")]["args"][8:10]
    ray = np.flatnonzero(np.all(np.abs(inv) < PARALLEL_RECIPROCAL, axis=1))  # the vector test's domain
    pairs = np.stack([ray, np.roll(ray, -1)], 1)
    rows = np.empty((len(ray), 12), F32)
    cpu_kernel.box_rows(lo[pairs], hi[pairs], rows)

    @numba.njit
    def pair_test(rows, o, inv, t_min, t_max, out_hit, out_near):
        flat = rows.reshape(-1)
        for r in range(rows.shape[0]):
            h0, n0, h1, n1 = cpu_kernel._box_pair(flat, np.uint64(12 * r), o[r, 0], o[r, 1], o[r, 2], inv[r, 0], inv[r, 1], inv[r, 2], t_min[r], t_max[r], np.float32(FAR_SCALE))  # fmt: skip
            out_hit[r, 0], out_near[r, 0], out_hit[r, 1], out_near[r, 1] = h0, n0, h1, n1

    got_hit = np.empty((len(ray), 2), bool)
    got_near = np.empty((len(ray), 2), F32)
    pair_test(rows, o[ray], inv[ray], t_min[ray], t_max[ray], got_hit, got_near)
    box = formulas.instance("box", "jax")
    for k in range(2):
        b = pairs[:, k]
        slabs = [np.asarray(x) for a in range(3) for x in jax.vmap(box.slab_distances)(lo[b, a], hi[b, a], o[ray, a], inv[ray, a])]  # fmt: skip
        hit, near, _ = jax.vmap(box.box_hit, in_axes=(0,) * 10 + (None,))(*slabs, lo[b, 0], hi[b, 0], t_min[ray], t_max[ray], FAR_SCALE)  # fmt: skip
        hit, near = np.asarray(hit), np.asarray(near)
        _equal(got_hit[:, k], hit, f"box {k}: hit")
        np.testing.assert_array_equal(got_near[hit, k], near[hit], err_msg=f"box {k}: entry")
    assert 20 < got_hit[:, 0].sum() < len(ray) and got_hit[:, 1].any()  # the inputs exercise both outcomes


#: The names a formula may loop or branch on: static options and the loop counters over them.
STATIC_NAMES = {"pieces", "iterations", "approach", "disk", "sphere", "flat", "i", "range"}


def test_formulas_use_the_vocabulary_only():
    """The formula sources follow the vocabulary's rules: no ``/`` and no branch or loop on a value (loops,
    branches and divisions on static options, and ``if any_lane(c):``, are allowed)."""
    import ast
    import inspect

    def static(node) -> bool:
        names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)}
        return names <= STATIC_NAMES and not any(isinstance(n, ast.Attribute) for n in ast.walk(node))

    for module in formulas.FORMULAS:
        tree = ast.parse(inspect.getsource(__import__(f"jaxrt._src.formulas.{module}", fromlist=["x"])))
        for node in ast.walk(tree):
            assert not isinstance(node, (ast.IfExp, ast.BoolOp, ast.While)), (module, node.lineno)
            if isinstance(node, ast.If):
                early_out = isinstance(node.test, ast.Call) and getattr(node.test.func, "id", "") == "any_lane"
                assert early_out or static(node.test), (module, node.lineno)
            if isinstance(node, ast.For):
                assert static(node.iter), (module, node.lineno)
            # (a division of static options, such as 1.0 / pieces, is a constant computed in Python)
            assert not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and not static(node)), (
                module,
                node.lineno,
            )
            assert not (isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.Not, ast.Invert))), module


# --- the curve formula -----------------------------------------------------------------------------------------

#: (basis, control points, curve type, end caps) of the curve formula's cases.
CURVE_CASES = [
    ("catmull_rom", 4, "round", "sphere"),
    ("catmull_rom", 4, "flat", "disk"),
    ("bezier", 3, "round", "disk"),
    ("linear", 2, "round", "sphere"),
    ("bspline", 3, "flat", "sphere"),
]
#: The cases whose JAX instance is compared too (each compiles a large unrolled program).
CURVE_JAX_CASES = CURVE_CASES[:2]
#: Curve distances and parameters: relative bound between the formula and ``curve.intersect`` (8 float32 eps,
#: the distance tolerance of ``tests/reference.py``): XLA contracts and reorders some of ``curve.intersect``'s
#: sums (``_norm2``, ``jnp.dot``, the multiply-adds), the formula's Numba instance none.
CURVE_RTOL = 8 * float(np.finfo(np.float32).eps)
#: Curve parameters: absolute bound (measured up to 8e-6): the test stops Newton within its tolerance of the
#: root (``CurveOptions.tolerance``), and the unconverged iterates amplify rounding differences where the entry
#: is ill conditioned in ``u``; 20 times tighter than the float64 reference's bound on ``u`` (``PARAMETER``
#: of ``tests/test_curves_primitive.py``).
CURVE_U_ATOL = 1e-4


def _curve_case(case, far: float = 0.0, seed: int = 3):
    """A few strands of ``case`` (moved ``far`` from the origin), rays aimed within 1.5 radii of them (grazing
    ones included), and every (ray, segment) pair: ``(geometry, origin, direction, pairs)``."""
    from test_curves_primitive import aimed_rays
    from test_curves_structure import hair

    import jaxrt as rt

    basis, count, curve_type, caps = case
    geometry = hair(seed=seed, strands=3, basis=basis, count=count, curve_type=curve_type, end_caps=caps)
    if far:
        points = np.asarray(geometry.control_points) + np.float32(far) * np.array([1.0, -0.37, 0.61], np.float32)
        geometry = rt.CurveGeometry(points, geometry.radii, geometry.indices, basis=basis, control_point_count=count,
                                    curve_type=curve_type, end_caps=caps)  # fmt: skip
    origin, direction = aimed_rays(np.random.default_rng(seed + 1), geometry, 24)
    return geometry, origin, direction


def _curve_static(case):
    from jaxrt._src.primitives import curve as primitive

    basis, count, curve_type, caps = case
    options = primitive.CurveOptions(pieces=1, iterations=0) if basis == "linear" else primitive.DEFAULT_OPTIONS
    code = {"none": primitive.CAP_NONE, "disk": primitive.CAP_DISK, "sphere": primitive.CAP_SPHERE}[caps]
    types = (primitive.FLAT,) if curve_type == "flat" else (primitive.ROUND,)
    config = dict(curve_types=types, end_caps=(code,), options=options)
    static = (options.pieces, options.iterations, options.approach_iterations, options.tolerance)
    return config, (*static, code == primitive.CAP_DISK, code == primitive.CAP_SPHERE, int(curve_type == "flat"))


def _curve_all(geometry, origin, direction, case, segments=None, flags=None):
    """``curve.intersect`` (the JAX spec), the formula's JAX instance and its Numba instance on every (ray,
    segment) pair: three dicts of ``(R, S)`` arrays ``hit, distance, u, part``."""
    from jaxrt._src.curves import pack_segments
    from jaxrt._src.traversal import cpu, cpu_curves

    if segments is None:
        segments, flags = (np.asarray(a) for a in pack_segments(geometry))
    r, s = len(origin), len(segments)
    ri, si = np.repeat(np.arange(r), s), np.tile(np.arange(s), r)
    pad = -len(ri) % 256  # padded (with the first pair) to share compiled programs between cases
    ri, si = np.concatenate([ri, np.zeros(pad, int)]), np.concatenate([si, np.zeros(pad, int)])
    o, d, seg, fl = origin[ri], direction[ri], np.ascontiguousarray(segments[si]), flags[si].astype(np.int32)
    n = len(o)
    lo, hi = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
    config, static = _curve_static(case)

    spec = _spec(tuple(config.items()))(o, d, seg, fl)
    frame = np.asarray(cpu.curve_frames(jnp.asarray(o), jnp.asarray(d)))
    columns = [seg[:, k, j] for k in range(4) for j in range(4)] + [seg[:, 4, 0], seg[:, 4, 1], seg[:, 4, 2], fl]
    columns += [seg[:, 5, j] for j in range(4)] + [o[:, 0], o[:, 1], o[:, 2]] + [frame[:, j] for j in range(10)]
    out_jax = (
        _jax_segment(static)(*(jnp.asarray(c) for c in columns), lo, hi)
        if case in CURVE_JAX_CASES
        else (np.zeros(n, bool),) * 4
    )
    out_numba = [np.empty(n, bool), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.int64)]
    params = np.asarray(cpu.curve_params(static), np.int64)
    cpu_curves.pairs(seg, fl, o, frame, lo, hi, params, np.float32(np.inf), *out_numba)
    names = ("hit", "distance", "u", "part")
    shape = lambda a: np.asarray(a)[: r * s].reshape(r, s)  # noqa: E731
    return (
        {k: shape(getattr(spec, k)) for k in names},
        {k: shape(a) for k, a in zip(names, out_jax, strict=True)},
        {k: shape(a) for k, a in zip(names, out_numba, strict=True)},
    )


@functools.cache
def _jax_segment(static: tuple):
    segment = formulas.instance("curve", "jax").segment
    return jax.jit(lambda *c: segment(*c, *static))


@functools.cache
def _spec(config: tuple):
    from jaxrt._src.primitives import curve as primitive

    def one(o, d, seg, f):
        ray = primitive.curve_ray(o, d)
        return primitive.intersect(ray, seg, f, jnp.float32(0), jnp.float32(np.inf), **dict(config))

    return jax.jit(jax.vmap(one))


def _assert_same_curve_hits(got: dict, want: dict, what: str) -> None:
    np.testing.assert_array_equal(got["hit"], want["hit"], err_msg=f"{what}: hit")
    hit = want["hit"]
    np.testing.assert_array_equal(got["part"][hit], want["part"][hit], err_msg=f"{what}: part")
    np.testing.assert_allclose(got["distance"], want["distance"], rtol=CURVE_RTOL, atol=0, err_msg=f"{what}: t")
    np.testing.assert_allclose(got["u"][hit], want["u"][hit], rtol=0, atol=CURVE_U_ATOL, err_msg=f"{what}: u")


@pytest.mark.parametrize("case", CURVE_CASES, ids=lambda c: "-".join(map(str, c)))
def test_curve_formula_equals_the_jax_spec(case):
    """The curve formula's Numba instance (and in :data:`CURVE_JAX_CASES` its JAX instance) against
    ``curve.intersect`` on every (ray, segment) pair of a few strands: the same hits and parts, distances within :data:`CURVE_RTOL`, parameters within
    :data:`CURVE_U_ATOL`."""
    geometry, origin, direction = _curve_case(case)
    spec, on_jax, on_numba = _curve_all(geometry, origin, direction, case)
    assert spec["hit"].sum() > 10
    if case in CURVE_JAX_CASES:
        _assert_same_curve_hits(on_jax, spec, "jax")
    _assert_same_curve_hits(on_numba, spec, "numba")


def test_curve_formula_hard_cases():
    """Far from the origin (about 1e3 and 1e4; the rays of :func:`_curve_case` pass within 1.5 radii of the
    centre lines, so many graze the tubes) and degenerate segments (all control points equal, zero radius, a
    zero start tangent): the formula makes the spec's decisions."""
    case = ("catmull_rom", 4, "round", "sphere")
    for far in (1.3e3, 1.1e4):
        geometry, origin, direction = _curve_case(case, far=far, seed=5)
        spec, on_jax, on_numba = _curve_all(geometry, origin, direction, case)
        assert spec["hit"].sum() > 5, far
        _assert_same_curve_hits(on_numba, spec, f"numba at {far}")
        _assert_same_curve_hits(on_jax, spec, f"jax at {far}")
    from jaxrt._src.curves import pack_segments

    geometry, origin, direction = _curve_case(case, seed=7)
    segments, flags = (np.array(a) for a in pack_segments(geometry))
    segments[0, :4, :3] = 0.0  # a point (every control point at the base point)
    segments[1, :4, 3] = 0.0  # zero radius
    segments[2, 1, :] = segments[2, 0, :]  # a zero start tangent
    spec, on_jax, on_numba = _curve_all(geometry, origin, direction, case, segments, flags)
    _assert_same_curve_hits(on_numba, spec, "degenerate")
    _assert_same_curve_hits(on_jax, spec, "degenerate, jax")


def test_curve_formula_against_the_float64_reference(monkeypatch):
    """The Numba instance on every (ray, segment) pair against the float64 reference of ``jaxrt.bench.curves``,
    with the bounds of ``tests/test_curves_primitive.py`` (its ``compare``, fed the formula's answers)."""
    import test_curves_primitive

    for case in (CURVE_CASES[0], CURVE_CASES[4]):
        geometry, origin, direction = _curve_case(case, seed=11)
        _, _, on_numba = _curve_all(geometry, origin, direction, case)
        hits = _Hits(**on_numba)
        monkeypatch.setattr(test_curves_primitive, "run", functools.partial(_answer, hits))
        counts = test_curves_primitive.compare(geometry, origin, direction)
        assert counts["hits"] > 10


def test_curve_formula_in_triton_interpreter(tmp_path):
    """The curve formula's Triton instance (Triton's interpreter, in a fresh process) equals its Numba instance
    bit for bit on a round and a flat case (both leave every multiply-add unfused; 32 pairs each, hits
    included)."""
    pytest.importorskip("triton")
    from jaxrt._src.curves import pack_segments
    from jaxrt._src.traversal import cpu, cpu_curves

    for case in CURVE_JAX_CASES:
        geometry, origin, direction = _curve_case(case)
        segments, flags = (np.asarray(a) for a in pack_segments(geometry))
        # Pairs of the first rays with every segment, those that hit first.
        r, s = 8, len(segments)
        ri, si = np.repeat(np.arange(r), s), np.tile(np.arange(s), r)
        _, _, numba_all = _curve_all(geometry, origin[:r], direction[:r], case)
        order = np.argsort(~numba_all["hit"].reshape(-1), kind="stable")[:32]
        ri, si = ri[order], si[order]
        o, d, seg, fl = origin[ri], direction[ri], np.ascontiguousarray(segments[si]), flags[si].astype(np.int32)
        frame = np.asarray(cpu.curve_frames(jnp.asarray(o), jnp.asarray(d)))
        _, static = _curve_static(case)
        n = len(o)
        want = [np.empty(n, bool), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.int64)]
        params = np.asarray(cpu.curve_params(static), np.int64)
        lo, hi = np.zeros(n, np.float32), np.full(n, np.inf, np.float32)
        cpu_curves.pairs(seg, fl, o, frame, lo, hi, params, np.float32(np.inf), *want)
        assert want[0].sum() >= 3
        columns = [seg[:, k, j] for k in range(4) for j in range(4)] + [seg[:, 4, 0], seg[:, 4, 1], seg[:, 4, 2], fl]
        columns += [seg[:, 5, j] for j in range(4)] + [o[:, 0], o[:, 1], o[:, 2]] + [frame[:, j] for j in range(10)]
        columns += [lo, hi]
        arrays = {f"arr_{i}": np.ascontiguousarray(c) for i, c in enumerate(columns)}
        np.savez(tmp_path / "in.npz", static=np.asarray(static, np.float64), **arrays)
        env = dict(os.environ, TRITON_INTERPRET="1")
        done = subprocess.run(
            [sys.executable, __file__, "--curve", str(tmp_path)], env=env, cwd=Path(__file__).parents[1],
            capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
        got = np.load(tmp_path / "out.npz")
        np.testing.assert_array_equal(got["arr_0"].astype(bool), want[0], err_msg=f"{case}: hit")
        np.testing.assert_array_equal(got["arr_1"], want[1], err_msg=f"{case}: distance")
        np.testing.assert_array_equal(got["arr_2"][want[0]], want[2][want[0]], err_msg=f"{case}: u")
        np.testing.assert_array_equal(got["arr_3"][want[0]], want[3][want[0]], err_msg=f"{case}: part")


def _triton_curve_main(folder: str) -> None:
    """The subprocess of :func:`test_curve_formula_in_triton_interpreter`: the curve formula's ``segment`` in
    Triton's interpreter, one lane per pair."""
    import triton
    import triton.language as tl
    from test_gpu_instanced import _HostArray

    data = np.load(Path(folder) / "in.npz")
    columns = [data[f"arr_{i}"] for i in range(39)]
    pieces, iterations, approach, tolerance, disk, sphere, flat = data["static"].tolist()
    n = len(columns[0])
    size = 1 << max(n - 1, 1).bit_length()
    columns = [np.concatenate([c, np.repeat(c[-1:], size - n)]) for c in columns]
    args = ", ".join(f"p{i}" for i in range(39))
    loads = "".join(f"    a{i} = tl.load(p{i} + lane)\n" for i in range(39))
    call = ", ".join(f"a{i}" for i in range(39))
    source = (
        f"def kernel({args}, q0, q1, q2, q3, N: tl.constexpr, PIECES: tl.constexpr, ITERATIONS: tl.constexpr, "
        "APPROACH: tl.constexpr, TOLERANCE: tl.constexpr, DISK: tl.constexpr, SPHERE: tl.constexpr, "
        f"FLAT: tl.constexpr):\n    lane = tl.arange(0, N)\n{loads}"
        f"    hit, t, u, part = fn({call}, PIECES, ITERATIONS, APPROACH, TOLERANCE, DISK, SPHERE, FLAT)\n"
        "    tl.store(q0 + lane, hit.to(tl.int8))\n    tl.store(q1 + lane, t)\n    tl.store(q2 + lane, u)\n"
        "    tl.store(q3 + lane, part.to(tl.int32))\n"
    )
    filename = "<test_formulas curve.segment>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    namespace = {"fn": formulas.instance("curve", "triton").segment, "tl": tl}
    exec(compile(source, filename, "exec"), namespace)
    outs = [np.zeros(size, np.int8), np.zeros(size, np.float32), np.zeros(size, np.float32), np.zeros(size, np.int32)]
    triton.jit(namespace["kernel"])[(1,)](
        *(_HostArray(np.ascontiguousarray(c)) for c in columns), *(_HostArray(o) for o in outs), N=size,
        PIECES=int(pieces), ITERATIONS=int(iterations), APPROACH=int(approach), TOLERANCE=float(tolerance),
        DISK=bool(disk), SPHERE=bool(sphere), FLAT=int(flat),
    )  # fmt: skip
    np.savez(Path(folder) / "out.npz", *(o[:n] for o in outs))


class _Hits:
    def __init__(self, hit, distance, u, part):
        self.hit, self.distance, self.u, self.part = hit, distance, u, part


def _answer(hits: _Hits, *args, **kwargs) -> _Hits:
    """Stands in for ``test_curves_primitive.run``: the formula's answers, computed beforehand."""
    return hits


if __name__ == "__main__":
    if sys.argv[1] == "--curve":
        _triton_curve_main(sys.argv[2])
    else:
        _triton_main(sys.argv[1])
