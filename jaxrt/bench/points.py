"""``python -m jaxrt.bench.points`` (also ``python -m jaxrt.bench --points``): point queries, speed against error.

Per scene, a fixed set of query points (half near the surface: a random point of a random triangle moved by
a Gaussian of 1% of the bounding-box diagonal; half uniform in the bounding box grown by 10%), then:

- ``closest_point``, ``signed_distance`` (fast winding-number sign) and ``winding_number`` (fast and exact),
  each in Mpoints/s (median of warm runs; the first, compiling run excluded);
- errors on a subset against a float64 NumPy brute force over every triangle: the largest distance error
  relative to the bounding-box diagonal, the points whose primitive is not a nearest one (beyond a tie
  tolerance), and the points whose inside/outside sign differs from the float64 exact winding number;
- the CPU peer on the same points: Open3D's ``RaycastingScene`` (``compute_closest_points`` and
  ``compute_signed_distance``, whose sign comes from ray parity) when ``open3d`` imports;
- with ``--peers``, NVIDIA Warp's ``wp.Mesh`` on the default JAX device (``mesh_query_point_no_sign`` for the
  closest point, ``mesh_query_point_sign_winding_number`` for the signed distance) when ``warp`` imports.

Flags: ``--scenes``, ``--points``, ``--reference-points``, ``--repeats``, ``--data-dir``, ``--quick``,
``--peers``, ``--grid N [N ...]`` (dense ``rt.sdf_grid`` rows of ``N^3`` points), ``--backend`` (the walk: ``auto``, ``portable``, ``cpu``, ``gpu``), ``--json PATH``,
``--variants a,b,c`` (``all``: every one): with the GPU walk, also each variant of the point kernels
(:data:`jaxrt._src.traversal.triton_points.VARIANTS`) in the same process, the default variant first, on the
same points held on the device; each variant's nearest leaves are checked against the default's (the count
that differ) and its fast winding numbers too (the largest difference).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

import jaxrt as rt
from jaxrt._src.traversal.points import resolve
from jaxrt.bench.report import machine_info
from jaxrt.bench.scenes import PROCEDURAL, SHARED_MESHES, load_scene
from jaxrt.bench.timing import progress, timed

__all__ = ["main", "query_points", "reference_closest", "reference_winding", "bench_points"]

_DEFAULTS = dict(points=1 << 16, reference_points=1024, repeats=3)
_QUICK = dict(points=1 << 10, reference_points=128, repeats=1)
#: Triangles per NumPy chunk of the brute force (bounds its memory).
_CHUNK = 1 << 21


def query_points(vertices: np.ndarray, indices: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` float32 points: half near the surface, half uniform in the grown bounding box."""
    rng = np.random.default_rng(seed)
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    diagonal = float(np.linalg.norm(hi - lo))
    near = n // 2
    tri = vertices[indices[rng.integers(0, len(indices), near)]].astype(np.float64)
    r1, r2 = rng.random((2, near, 1))
    s = np.sqrt(r1)
    surface = (1 - s) * tri[:, 0] + s * (1 - r2) * tri[:, 1] + s * r2 * tri[:, 2]
    surface += rng.normal(scale=0.01 * diagonal, size=surface.shape)
    grow = 0.1 * (hi - lo)
    uniform = rng.uniform(lo - grow, hi + grow, (n - near, 3))
    return np.concatenate([surface, uniform]).astype(np.float32)


def reference_closest(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float64 brute force: ``(distance (n,), distance to every triangle (n, T))``; zero-area triangles
    (which the builder leaves out) are ``inf``."""
    tri = np.asarray(triangles, np.float64)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    t32 = np.asarray(triangles, np.float32)
    e1, e2 = (t32[:, 1] - t32[:, 0]).astype(np.float64), (t32[:, 2] - t32[:, 0]).astype(np.float64)
    area = (np.cross(e1, e2) != 0).any(axis=-1)
    nn = np.sum(n * n, axis=-1)
    safe = np.where(nn > 0, nn, 1)
    rows = []
    step = max(1, _CHUNK // max(1, len(tri)))
    for start in range(0, len(points), step):
        p = np.asarray(points[start : start + step], np.float64)[:, None, :]
        proj = p - (np.sum((p - a) * n, axis=-1) / safe)[..., None] * n
        inside = np.broadcast_to(nn > 0, proj.shape[:-1]).copy()
        for e0, e1_ in ((a, b), (b, c), (c, a)):
            inside &= np.sum(np.cross(e1_ - e0, proj - e0) * n, axis=-1) >= 0
        best = np.where(inside, np.linalg.norm(p - proj, axis=-1), np.inf)
        for e0, e1_ in ((a, b), (b, c), (c, a)):
            ab = e1_ - e0
            den = np.sum(ab * ab, axis=-1)
            t = np.clip(np.sum((p - e0) * ab, axis=-1) / np.where(den > 0, den, 1), 0, 1)
            best = np.minimum(best, np.linalg.norm(p - (e0 + t[..., None] * ab), axis=-1))
        rows.append(np.where(area, best, np.inf))
    every = np.concatenate(rows)
    return every.min(axis=1), every


def reference_winding(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Float64 exact generalized winding numbers (every triangle's solid angle)."""
    tri = np.asarray(triangles, np.float64)
    out = []
    step = max(1, _CHUNK // max(1, len(tri)))
    for start in range(0, len(points), step):
        v = tri[None] - np.asarray(points[start : start + step], np.float64)[:, None, None, :]
        a, b, c = v[..., 0, :], v[..., 1, :], v[..., 2, :]
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.sum(a * np.cross(b, c), axis=-1)
        den = la * lb * lc + np.sum(a * b, -1) * lc + np.sum(a * c, -1) * lb + np.sum(b * c, -1) * la
        out.append(np.sum(2 * np.arctan2(det, den), axis=1) / (4 * np.pi))
    return np.concatenate(out)


def _open3d_scene(vertices: np.ndarray, indices: np.ndarray):
    try:
        import open3d as o3d
    except Exception:  # not installed, or its shared libraries are missing
        return None
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(indices.astype(np.uint32)))
    return scene, o3d


def _warp_peer(vertices: np.ndarray, indices: np.ndarray, points: np.ndarray, repeats: int) -> dict[str, Any] | None:
    """Warp's mesh point queries on the same points (``None`` when ``warp`` does not import)."""
    try:
        import warp as wp
    except Exception:  # not installed, or its library is missing
        return None
    wp.config.quiet = True
    wp.init()
    device = "cuda" if jax.default_backend() == "gpu" else "cpu"

    @wp.kernel
    def closest(mesh: wp.uint64, p: wp.array(dtype=wp.vec3), distance: wp.array(dtype=float)):  # fmt: skip
        i = wp.tid()
        q = wp.mesh_query_point_no_sign(mesh, p[i], 1.0e30)
        distance[i] = wp.inf
        if q.result:
            distance[i] = wp.length(p[i] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))

    @wp.kernel
    def signed(mesh: wp.uint64, p: wp.array(dtype=wp.vec3), distance: wp.array(dtype=float)):  # fmt: skip
        i = wp.tid()
        q = wp.mesh_query_point_sign_winding_number(mesh, p[i], 1.0e30, 2.0, 0.5)
        distance[i] = wp.inf
        if q.result:
            distance[i] = q.sign * wp.length(p[i] - wp.mesh_eval_position(mesh, q.face, q.u, q.v))

    with wp.ScopedDevice(device):
        mesh = wp.Mesh(
            wp.array(vertices.astype(np.float32), dtype=wp.vec3),
            wp.array(indices.reshape(-1).astype(np.int32), dtype=wp.int32),
            support_winding_number=True,
        )
        query = wp.array(points.astype(np.float32), dtype=wp.vec3)
        out: dict[str, Any] = {"device": device}
        for name, kernel in (("closest", closest), ("signed", signed)):
            result = wp.zeros(len(points), dtype=float)

            def run(kernel=kernel, result=result):
                wp.launch(kernel, len(points), inputs=[mesh.id, query, result])
                wp.synchronize()
                return None

            timing, _ = timed(run, repeats)
            out[name] = timing.as_dict(len(points), "mpoints_s")
            out[f"{name}_values"] = result.numpy()
    return out


def bench_points(
    name: str, sizes: dict[str, Any], data_dir: str | None, seed: int, peers: bool = False, backend: str = "auto"
) -> dict[str, Any]:
    """Speeds and errors of the point queries on one scene (see the module docstring); ``backend``: the walk
    (``rt.closest_point``'s argument)."""
    scene = load_scene(name, n_triangles=sizes.get("triangles", 100_000), seed=seed, data_dir=data_dir)
    vertices, indices = scene.vertices, scene.indices
    triangles = vertices[indices]
    structure = jax.block_until_ready(rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices)))
    points = query_points(vertices, indices, sizes["points"], seed)
    n, repeats = len(points), sizes["repeats"]
    diagonal = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
    out: dict[str, Any] = {"scene": name, "triangles": len(indices), "points": n, "diagonal": diagonal}
    out["backend"] = backend
    b = backend

    t_closest, closest = timed(lambda: rt.closest_point(points, structure, backend=b), repeats)
    t_signed, signed = timed(lambda: rt.signed_distance(points, structure, backend=b), repeats)
    t_wind, _ = timed(lambda: rt.winding_number(points, structure, backend=b), repeats)
    m = min(n, sizes["reference_points"])
    subset = np.concatenate([points[: m // 2], points[n // 2 : n // 2 + m - m // 2]])  # near and uniform
    t_exact, exact = timed(lambda: rt.winding_number(subset, structure, exact=True, backend=b), min(repeats, 1))
    out["closest_point"] = t_closest.as_dict(n, "mpoints_s")
    out["signed_distance"] = t_signed.as_dict(n, "mpoints_s")
    out["winding_fast"] = t_wind.as_dict(n, "mpoints_s")
    out["winding_exact"] = t_exact.as_dict(m, "mpoints_s")

    ref, every = reference_closest(subset, triangles)
    got = rt.closest_point(subset, structure, backend=b)
    distance = np.asarray(got.distance, np.float64)
    prim = np.asarray(got.primitive_id)
    tie = 1e-6 * diagonal
    out["max_distance_error_rel"] = float(np.max(np.abs(distance - ref)) / diagonal)
    out["wrong_primitive"] = int(np.sum(every[np.arange(m), prim] > ref + tie))
    winding = reference_winding(subset, triangles)
    fast_inside = np.asarray(rt.contains(subset, structure, backend=b))
    out["sign_disagree_fast"] = int(np.sum(fast_inside != (winding >= 0.5)))
    out["sign_disagree_exact"] = int(np.sum((np.asarray(exact) >= 0.5) != (winding >= 0.5)))
    out["max_winding_error_fast"] = float(
        np.max(np.abs(np.asarray(rt.winding_number(subset, structure, backend=b)) - winding))
    )
    out["reference_points"] = m

    peer = _open3d_scene(vertices, indices)
    if peer is not None:
        o3d_scene, o3d = peer
        query = o3d.core.Tensor(points)
        t_peer, answer = timed(lambda: o3d_scene.compute_closest_points(query), repeats)
        t_peer_sd, peer_sd = timed(lambda: o3d_scene.compute_signed_distance(query), repeats)
        out["open3d_closest"] = t_peer.as_dict(n, "mpoints_s")
        out["open3d_signed"] = t_peer_sd.as_dict(n, "mpoints_s")
        peer_distance = np.linalg.norm(answer["points"].numpy().astype(np.float64) - points, axis=-1)
        out["open3d_max_distance_diff_rel"] = float(
            np.max(np.abs(peer_distance - np.asarray(closest.distance))) / diagonal
        )
        sd = np.asarray(signed)
        out["open3d_sign_disagree"] = int(np.sum((peer_sd.numpy() < 0) != (sd < 0)))
    warp = _warp_peer(vertices, indices, points, repeats) if peers else None
    if warp is not None:
        out["warp_device"] = warp["device"]
        out["warp_closest"] = warp["closest"]
        out["warp_signed"] = warp["signed"]
        out["warp_max_distance_diff_rel"] = float(
            np.max(np.abs(warp["closest_values"] - np.asarray(closest.distance))) / diagonal
        )
        out["warp_sign_disagree"] = int(np.sum((warp["signed_values"] < 0) != (np.asarray(signed) < 0)))
    if sizes.get("variants"):
        if resolve(b, structure, "bench") == "gpu":
            out["variants"] = bench_variants(sizes["variants"], points, structure, repeats, b)
        else:
            out["variants_skipped"] = "the variants are the GPU kernels'; this run walks elsewhere"
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    bounds = np.stack([lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)])
    for r in sizes.get("grids") or ():
        t_grid, grid = timed(lambda r=r: rt.sdf_grid(structure, bounds, r, backend=b), min(repeats, 2))
        out[f"grid_{r}"] = dict(t_grid.as_dict(r**3, "mpoints_s"), resolution=r)
        # A sample of the grid against signed_distance at the same points.
        rng = np.random.default_rng(seed)
        index = rng.integers(0, r, (min(256, r**3), 3))
        axes = [np.linspace(bounds[0, a], bounds[1, a], r) for a in range(3)]
        sample = np.stack([axes[a][index[:, a]] for a in range(3)], axis=-1).astype(np.float32)
        want = np.asarray(rt.signed_distance(sample, structure, backend=b))
        got = np.asarray(grid)[index[:, 0], index[:, 1], index[:, 2]]
        out[f"grid_{r}"]["max_diff_rel"] = float(np.max(np.abs(got - want)) / diagonal)
    return out


def bench_variants(names: Sequence[str], points: np.ndarray, structure: Any, repeats: int, backend: str):
    """Speeds of the point kernels' variants ``names`` (``["all"]``: every one) on ``points`` (moved to the
    device once), the default variant first, and how each variant's nearest leaves and fast winding numbers
    differ from the default's. Each variant is selected by :data:`triton_points.VARIANT` with JAX's caches
    cleared (so the queries trace again); the default is restored afterwards."""
    from jaxrt._src.traversal import triton_points

    default = triton_points.VARIANT
    names = list(triton_points.VARIANTS) if list(names) == ["all"] else list(names)
    for name in names:
        triton_points.variant(name)  # unknown names fail before any timing
    order = [default] + [name for name in names if name != default]
    device_points = jax.device_put(points)
    n = len(points)
    out: dict[str, Any] = {}
    want_leaf = want_wind = None
    try:
        for name in order:
            triton_points.VARIANT = name
            jax.clear_caches()
            p = device_points
            t_closest, closest = timed(lambda p=p: rt.closest_point(p, structure, backend=backend), repeats)
            t_signed, _ = timed(lambda p=p: rt.signed_distance(p, structure, backend=backend), repeats)
            t_wind, wind = timed(lambda p=p: rt.winding_number(p, structure, backend=backend), repeats)
            leaf, wind = np.asarray(closest.primitive_id), np.asarray(wind, np.float64)
            if want_leaf is None:
                want_leaf, want_wind = leaf, wind
            diff = np.abs(wind - want_wind)
            out[name] = {
                "closest_point": t_closest.as_dict(n, "mpoints_s"),
                "signed_distance": t_signed.as_dict(n, "mpoints_s"),
                "winding_fast": t_wind.as_dict(n, "mpoints_s"),
                "leaf_mismatch": int(np.sum(leaf != want_leaf)),
                "winding_max_diff": float(np.max(np.where(np.isnan(diff), 0, diff))),
                "winding_nan_mismatch": int(np.sum(np.isnan(wind) != np.isnan(want_wind))),
            }
    finally:
        triton_points.VARIANT = default
        jax.clear_caches()
    return out


def format_table(results: dict[str, Any]) -> str:
    """The results as a fixed-width table."""
    lines = [
        f"{'scene':8} {'tris':>9} {'points':>7} {'query':18} {'jaxrt Mpt/s':>11} {'Open3D Mpt/s':>12}  errors",
    ]
    warp_lines = []
    for r in results["scenes"]:
        peer = lambda key, r=r: f"{r[key]['mpoints_s']:12.3f}" if key in r else f"{'-':>12}"  # noqa: E731
        head = f"{r['scene']:8} {r['triangles']:9,} {r['points']:7,}"
        blank = " " * len(head)
        m = r["reference_points"]
        lines.append(
            f"{head} {'closest_point':18} {r['closest_point']['mpoints_s']:11.3f} {peer('open3d_closest')}  "
            f"max |d - d64| {r['max_distance_error_rel']:.1e} diag, wrong primitive {r['wrong_primitive']}/{m}"
        )
        lines.append(
            f"{blank} {'signed_distance':18} {r['signed_distance']['mpoints_s']:11.3f} {peer('open3d_signed')}  "
            f"sign vs exact float64 winding: {r['sign_disagree_fast']}/{m} differ"
            + (f"; Open3D signs differ on {r['open3d_sign_disagree']}/{r['points']}" if "open3d_signed" in r else "")
        )
        lines.append(
            f"{blank} {'winding (fast)':18} {r['winding_fast']['mpoints_s']:11.3f} {'-':>12}  "
            f"max |w - w64| {r['max_winding_error_fast']:.3f}"
        )
        lines.append(
            f"{blank} {'winding (exact)':18} {r['winding_exact']['mpoints_s']:11.4f} {'-':>12}  "
            f"sign: {r['sign_disagree_exact']}/{m} differ (on {m} points)"
        )
        if "warp_closest" in r:
            warp_lines.append(
                f"{r['scene']:8} Warp ({r['warp_device']}): closest_point {r['warp_closest']['mpoints_s']:.3f} Mpt/s "
                f"(jaxrt {r['closest_point']['mpoints_s']:.3f}; max |d - d_warp| "
                f"{r['warp_max_distance_diff_rel']:.1e} diag), signed_distance {r['warp_signed']['mpoints_s']:.3f} "
                f"Mpt/s (jaxrt {r['signed_distance']['mpoints_s']:.3f}; signs differ on "
                f"{r['warp_sign_disagree']}/{r['points']})"
            )
        for key in sorted(k for k in r if k.startswith("grid_")):
            g = r[key]
            lines.append(
                f"{blank} {'sdf_grid ' + str(g['resolution']) + '^3':18} {g['mpoints_s']:11.3f} {'-':>12}  "
                f"{g['median_s']:.2f} s; max |grid - signed_distance| {g['max_diff_rel']:.1e} diag (256 cells)"
            )
    lines.extend(warp_lines)
    for r in results["scenes"]:
        for name, v in r.get("variants", {}).items():
            lines.append(
                f"{r['scene']:8} variant {name:14} closest {v['closest_point']['mpoints_s']:8.3f}  signed "
                f"{v['signed_distance']['mpoints_s']:8.3f}  winding {v['winding_fast']['mpoints_s']:8.3f} Mpt/s "
                f"(device points); leaves != default {v['leaf_mismatch']}, max |w - w_default| "
                f"{v['winding_max_diff']:.1e}"
            )
    for name, why in results.get("skipped", {}).items():
        lines.append(f"{name}: skipped ({why})")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.points", description=__doc__.split("\n\n")[0])
    names = sorted(set(PROCEDURAL) | set(SHARED_MESHES))
    parser.add_argument("--scenes", nargs="+", choices=names, default=["bunny", "dragon"])
    parser.add_argument("--points", type=int, help=f"query points (default {_DEFAULTS['points']:,})")
    parser.add_argument("--reference-points", type=int, help="points checked against the float64 brute force")
    parser.add_argument("--repeats", type=int, help="warm runs per measurement")
    parser.add_argument("--triangles", type=int, help="triangles of procedural scenes (default 100,000)")
    parser.add_argument("--data-dir", help="shared mesh folder (default: $JAXRT_DATA_DIR or ../shared/data)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="tiny sizes and one repeat: a smoke test")
    parser.add_argument("--peers", action="store_true", help="also NVIDIA Warp's mesh point queries (if installed)")
    parser.add_argument(
        "--grid", type=int, nargs="+", metavar="N", help="also rt.sdf_grid of N^3 points (bounds: +10%%)"
    )
    parser.add_argument(
        "--backend", choices=("auto", "portable", "cpu", "gpu"), default="auto", help="the walk (default: auto)"
    )
    parser.add_argument(
        "--variants",
        metavar="A,B,C",
        help="also time these GPU point-kernel variants ('all': every one) against the default, same process",
    )
    parser.add_argument("--json", metavar="PATH", help="also write every number and the machine info to PATH")
    return parser


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the point-query table, print it, and write the JSON file if asked; returns the results."""
    args = _parser().parse_args(argv)
    given = {k: getattr(args, k) for k in ("points", "reference_points", "repeats", "triangles")}
    sizes = {**(_QUICK if args.quick else _DEFAULTS), **{k: v for k, v in given.items() if v is not None}}
    sizes["grids"] = list(args.grid or ())
    sizes["variants"] = [v for v in (args.variants or "").split(",") if v]
    config = dict(sizes, seed=args.seed, backend=args.backend)
    results: dict[str, Any] = {"machine": machine_info(), "config": config, "scenes": []}
    results["skipped"] = {}
    for name in progress(args.scenes, desc="scenes"):
        try:
            row = bench_points(name, sizes, args.data_dir, args.seed, peers=args.peers, backend=args.backend)
            results["scenes"].append(row)
        except FileNotFoundError as error:
            results["skipped"][name] = str(error)
        if args.json:  # after every scene, so that a run cut short keeps the scenes it finished
            _write(args.json, results)
    print(format_table(results))
    if args.json:
        print(f"wrote {args.json}")
    return results


def _write(path: str, results: dict[str, Any]) -> None:
    with open(path, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
    sys.exit(0)
