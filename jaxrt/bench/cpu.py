"""``python -m jaxrt.bench.cpu``: the CPU traversal against Embree, thread for thread, in one process.

For each scene, ray set (primary, diffuse) and query (closest, any hit), three tracers take turns on the same
rays, ``--repeats`` rounds, and the best round of each is kept (the machine may be shared: alternating and
keeping the best round compares the tracers under the same load):

- ``kernel``: the compiled traversal alone (:func:`jaxrt._src.traversal.cpu._run` on NumPy arrays: the ray
  order, the leaf, distance and counters, no JAX work around it; the structure's box rows laid out beforehand,
  as a top-level call keeps them);
- ``intersect``: the whole ``Intersector.intersect`` call (ray sanitising, the host callback with its argument
  copies, the result fields), synchronised;
- ``embree``: Embree through embreex (its single-ray loop on one thread);
- ``open3d``: Open3D's ``RaycastingScene`` (Embree underneath) on every core, as a user calls it (left out,
  with the reason printed, where ``open3d`` does not import).

jaxrt runs with each thread count of ``--threads`` (``JAXRT_CPU_THREADS``; default 1 and every core). The
``per core / embree`` column divides the ``intersect`` rate by the thread count and by Embree's one-thread
rate; ``/ open3d`` divides each thread count's ``intersect`` rate by Open3D's (on every core). ``--queries`` adds hit lists: ``k4`` (``max_hits=4``) and ``count`` (``rt.count_intersections``), where
the third tracer is ``portable``, the same call on the portable traversal (``backend="portable"``, which
runs on one thread), in place of Embree (embreex exposes no multi-hit or counting query). ``--quality`` picks the build (``fast``: the LBVH, the default; ``high``: clustering, closer to the
SAH-quality trees Embree builds); several qualities give a row each. Flags: ``--scenes``, ``--rays``,
``--repeats``, ``--threads``, ``--quality``, ``--queries``, ``--jit`` (also ``intersect`` inside ``jax.jit``), ``--data-dir``, ``--json PATH``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax

import jaxrt as rt
from jaxrt.bench.peers import Embree, Open3D, embree_unavailable_reason, open3d_unavailable_reason
from jaxrt.bench.report import machine_info
from jaxrt.bench.scenes import load_scene
from jaxrt.bench.suite import RAY_KINDS

__all__ = ["main", "measure_scene"]


def _best(fn: Callable[[], Any], best: float) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return min(best, time.perf_counter() - start)


#: The queries ``--queries`` picks from: intersector options, or ``None`` for ``rt.count_intersections``.
QUERIES: dict[str, dict[str, Any] | None] = {
    "closest": {},
    "any": {"accept_any_intersection": True},
    "k4": {"max_hits": 4},
    "count": None,
}


def _intersector(query: str, backend: str) -> rt.Intersector:
    if QUERIES[query] is None:
        from jaxrt._src.intersector import _CountingIntersector

        return _CountingIntersector(backend=backend)  # what rt.count_intersections traces with
    return rt.Intersector(backend=backend, **QUERIES[query])


def _query_call(query: str, backend: str, structure: Any, rays: rt.Ray) -> Callable[[], Any]:
    if QUERIES[query] is None:
        return functools.partial(rt.count_intersections, rays, structure, rt.Intersector(backend=backend))
    return functools.partial(_intersector(query, backend).intersect, rays, structure)


def _jit_call(query: str, structure: Any, rays: rt.Ray) -> Callable[[], Any]:
    """``intersect`` inside ``jax.jit``, rays and structure passed as arguments (as the docs advise)."""
    if QUERIES[query] is None:
        intersector = rt.Intersector(backend="cpu")
        traced = jax.jit(lambda r, s: rt.count_intersections(r, s, intersector))
    else:
        traced = jax.jit(_intersector(query, "cpu").intersect)
    return functools.partial(traced, rays, structure)


def _kernel_call(structure: Any, intersector: rt.Intersector, rays: rt.Ray) -> Callable[[], Any]:
    """The compiled traversal alone on host arrays (the arguments the intersector's callback receives, and the
    structure's box rows, which a top-level call lays out once per structure)."""
    from jaxrt._src.pipeline import cpu_kernel_arguments
    from jaxrt._src.traversal import cpu

    params, arrays = cpu_kernel_arguments(structure, rays, intersector)
    boxes = cpu.box_rows(arrays[0], arrays[1])
    return lambda: cpu._run(params, arrays, boxes)


def measure_scene(
    name: str,
    n_rays: int,
    repeats: int,
    threads: Sequence[int],
    data_dir: str | None = None,
    quality: str = "fast",
    queries: Sequence[str] = ("closest", "any"),
    jit: bool = False,
) -> list[dict[str, Any]]:
    """Rows of Mrays/s (best of ``repeats`` alternating rounds) for one scene built with ``quality``, one per
    ray set and query (:data:`QUERIES`); ``jit`` adds ``intersect`` inside ``jax.jit``."""
    scene = load_scene(name, data_dir=data_dir)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices), quality=quality)
    embree = None
    if embree_unavailable_reason() is None:
        embree = Embree(scene.vertices, scene.indices)
        embree.build()
    open3d = None
    if open3d_unavailable_reason() is None:
        open3d = Open3D(scene.vertices, scene.indices)
        open3d.build()
    rows = []
    for kind in ("primary", "diffuse"):
        batch = RAY_KINDS[kind](scene, n_rays, 0)
        rays = batch.to_jaxrt()
        for query in queries:
            kernel = _kernel_call(structure, _intersector(query, "cpu"), rays)
            calls: dict[str, Callable[[], Any]] = {}
            for count in threads:
                calls[f"kernel {count}t"] = kernel
                calls[f"intersect {count}t"] = _query_call(query, "cpu", structure, rays)
                if jit:
                    calls[f"jit {count}t"] = _jit_call(query, structure, rays)
            if query in ("k4", "count"):  # no Embree query to compare: the portable traversal
                calls["portable 1t"] = _query_call(query, "portable", structure, rays)
            elif embree is not None:
                calls["embree 1t"] = functools.partial(embree.any_hit if query == "any" else embree.closest, batch)
            if query in ("closest", "any") and open3d is not None:
                calls["open3d"] = functools.partial(open3d.any_hit if query == "any" else open3d.closest, batch)
            best = dict.fromkeys(calls, float("inf"))
            for round_ in range(repeats + 1):  # round 0 warms up (compiles)
                for key, fn in calls.items():
                    if key.endswith("t"):
                        os.environ["JAXRT_CPU_THREADS"] = key.split()[-1][:-1]
                    seconds = _best(fn, float("inf"))
                    if round_:
                        best[key] = min(best[key], seconds)
            os.environ.pop("JAXRT_CPU_THREADS", None)
            row = {"scene": name, "quality": quality, "rays": kind, "query": query}
            row.update({key: n_rays / s / 1e6 for key, s in best.items()})
            rows.append(row)
    return rows


def _format(row: dict[str, Any], threads: Sequence[int]) -> str:
    parts = [f"{row['scene']:7s} {row['quality']:5s} {row['rays']:8s} {row['query']:8s}"]
    for count in threads:
        parts.append(
            f"kernel {count}t {row[f'kernel {count}t']:5.2f}  intersect {count}t {row[f'intersect {count}t']:5.2f}"
        )
    for count in threads:
        if f"jit {count}t" in row:
            parts.append(f"jit {count}t {row[f'jit {count}t']:5.2f}")
    if "portable 1t" in row:
        parts.append(f"portable 1t {row['portable 1t']:5.2f}")
        parts.append(
            "per core / portable "
            + " ".join(f"{count}t {row[f'intersect {count}t'] / count / row['portable 1t']:.1f}" for count in threads)
        )
    if "embree 1t" in row:
        parts.append(f"embree 1t {row['embree 1t']:5.2f}")
        parts.append(
            "per core / embree "
            + " ".join(f"{count}t {row[f'intersect {count}t'] / count / row['embree 1t']:.2f}" for count in threads)
        )
    if "open3d" in row:
        parts.append(f"open3d {row['open3d']:5.2f}")
        parts.append(
            "/ open3d " + " ".join(f"{count}t {row[f'intersect {count}t'] / row['open3d']:.2f}" for count in threads)
        )
    return " | ".join(parts)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line."""
    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.cpu", description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["sphere", "bunny", "dragon"])
    parser.add_argument("--rays", type=int, default=1 << 16)
    parser.add_argument("--repeats", type=int, default=5, help="alternating rounds; the best is kept (default 5)")
    parser.add_argument("--threads", type=int, nargs="+", help="jaxrt thread counts (default: 1 and every core)")
    parser.add_argument("--quality", nargs="+", default=["fast"], choices=["fast", "high"], help="build quality")
    parser.add_argument(
        "--queries", nargs="+", default=["closest", "any"], choices=list(QUERIES), help="queries (default closest any)"
    )
    parser.add_argument("--jit", action="store_true", help="also time intersect inside jax.jit")
    parser.add_argument("--data-dir", help="shared mesh folder (default: $JAXRT_DATA_DIR or ../shared/data)")
    parser.add_argument("--json", metavar="PATH", help="also write the rows and the machine info to PATH")
    args = parser.parse_args(argv)
    from jaxrt._src.traversal import cpu

    if cpu.unavailable_reason() is not None:
        raise SystemExit(f"python -m jaxrt.bench.cpu: {cpu.unavailable_reason()}")
    os.environ.pop("JAXRT_CPU_THREADS", None)
    threads = args.threads or sorted({1, cpu.threads()})
    if open3d_unavailable_reason() is not None:
        print(f"open3d left out: {open3d_unavailable_reason()}")
    print(f"Mrays/s, {args.rays:,} rays, best of {args.repeats} alternating rounds; load average {os.getloadavg()}")
    rows = []
    for name in args.scenes:
        for quality in args.quality:
            for row in measure_scene(
                name, args.rays, args.repeats, threads, args.data_dir, quality, args.queries, args.jit
            ):
                print(_format(row, threads), flush=True)
                rows.append(row)
    print(f"load average at the end {os.getloadavg()}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": machine_info(), "threads": list(threads), "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
