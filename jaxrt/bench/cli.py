"""``python -m jaxrt.bench``: the command line."""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

from jaxrt.bench.reference import REFERENCES
from jaxrt.bench.report import format_table, machine_info, write_json
from jaxrt.bench.scenes import PROCEDURAL, SHARED_MESHES, default_data_dir, load_scene
from jaxrt.bench.suite import RAY_KINDS, BenchConfig, bench_scene
from jaxrt.bench.timing import progress

__all__ = ["main", "parse_args", "DEFAULT_SCENES"]

#: Scenes of a default run (shared meshes only where the data folder is present).
DEFAULT_SCENES = ("sphere", "bunny", "dragon")
_DEFAULTS = dict(triangles=100_000, rays=1 << 16, reference_rays=1 << 14, repeats=3, build_repeats=5)
_QUICK = dict(triangles=2_000, rays=1 << 10, reference_rays=1 << 10, repeats=1, build_repeats=1)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m jaxrt.bench",
        description="jaxrt speed against error, with Embree (embreex) on the same rays and machine as the peer.",
    )
    names = sorted(set(PROCEDURAL) | set(SHARED_MESHES))
    parser.add_argument(
        "--scenes", nargs="+", choices=names, help=f"scenes to run (default: {' '.join(DEFAULT_SCENES)})"
    )
    parser.add_argument(
        "--triangles", type=int, help=f"triangles of procedural scenes (default {_DEFAULTS['triangles']:,})"
    )
    parser.add_argument("--rays", type=int, help=f"rays per ray set (default {_DEFAULTS['rays']:,})")
    parser.add_argument(
        "--reference-rays",
        type=int,
        help=f"rays checked against the reference (default {_DEFAULTS['reference_rays']:,})",
    )
    parser.add_argument("--repeats", type=int, help="warm trace runs per measurement (default 3)")
    parser.add_argument("--build-repeats", type=int, help="warm builds per measurement (default 5)")
    parser.add_argument("--ray-sets", nargs="+", choices=sorted(RAY_KINDS), default=["primary", "diffuse"])
    parser.add_argument(
        "--reference",
        choices=sorted(REFERENCES),
        default="numpy",
        help="float64 reference: 'numpy' (an independent NumPy BVH tracer) or 'jaxrt-x64' (jaxrt under x64)",
    )
    parser.add_argument(
        "--backend",
        choices=["auto", "portable", "gpu", "cpu"],
        default="auto",
        help="jaxrt intersector backend (auto: the GPU kernel on a GPU, the compiled CPU traversal on the CPU)",
    )
    parser.add_argument(
        "--also-portable",
        action="store_true",
        help="also time the portable traversal on the same rays (the 'portable' rows)",
    )
    parser.add_argument("--no-embree", action="store_true", help="skip the Embree peer")
    parser.add_argument("--data-dir", help="shared mesh folder (default: $JAXRT_DATA_DIR or ../shared/data)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="tiny sizes and one repeat: a smoke test")
    parser.add_argument("--json", metavar="PATH", help="also write every number and the machine info to PATH")
    parser.add_argument("--quiet", action="store_true", help="print only the table")
    parser.add_argument(
        "--custom",
        action="store_true",
        help="also run the custom-geometry tables: boxes with functions, filters, multi-hit (jaxrt.bench.custom)",
    )
    parser.add_argument(
        "--points",
        action="store_true",
        help="also run the point-query table: closest point, signed distance, winding number (jaxrt.bench.points)",
    )
    return parser


def parse_args(argv: Sequence[str] | None = None) -> BenchConfig:
    """The :class:`~jaxrt.bench.suite.BenchConfig` for command-line arguments (``--json``/``--quiet`` aside)."""
    args = _parser().parse_args(argv)
    defaults = _QUICK if args.quick else _DEFAULTS

    def pick(value: int | None, key: str) -> int:
        chosen = defaults[key] if value is None else value
        if chosen < 1 and key not in ("repeats", "build_repeats"):
            raise SystemExit(f"python -m jaxrt.bench: --{key.replace('_', '-')} must be positive, got {chosen}")
        return max(0, chosen)

    return BenchConfig(
        scenes=tuple(args.scenes or DEFAULT_SCENES),
        n_triangles=pick(args.triangles, "triangles"),
        n_rays=pick(args.rays, "rays"),
        reference_rays=pick(args.reference_rays, "reference_rays"),
        repeats=pick(args.repeats, "repeats"),
        build_repeats=pick(args.build_repeats, "build_repeats"),
        reference=args.reference,
        ray_kinds=tuple(args.ray_sets),
        embree=not args.no_embree,
        backend=args.backend,
        also_portable=args.also_portable,
        seed=args.seed,
        data_dir=args.data_dir,
    )


def _resolved(backend: str) -> str:
    """The traversal the ``backend`` option runs here (``"gpu"``, ``"cpu"`` or ``"portable"``)."""
    import jaxrt as rt
    from jaxrt._src.pipeline import resolve_backend

    return resolve_backend(rt.Intersector(backend=backend))


def run(config: BenchConfig, *, verbose: bool = True) -> dict[str, Any]:
    """Run the bench described by ``config``; returns the JSON-ready results."""
    start = time.perf_counter()
    results: dict[str, Any] = {
        "machine": machine_info(),
        "config": {
            "scenes": list(config.scenes),
            "n_triangles": config.n_triangles,
            "n_rays": config.n_rays,
            "reference_rays": config.reference_rays,
            "repeats": config.repeats,
            "build_repeats": config.build_repeats,
            "reference": config.reference,
            "ray_sets": list(config.ray_kinds),
            "backend": config.backend,
            "backend_resolved": _resolved(config.backend),
            "also_portable": config.also_portable,
            "seed": config.seed,
        },
        "scenes": [],
        "skipped": {},
    }
    data_dir = config.data_dir if config.data_dir is not None else default_data_dir()
    for name in progress(config.scenes, enabled=not verbose, desc="scenes"):  # --quiet: a bar instead of the log
        if name in SHARED_MESHES and (data_dir is None or not os.path.isdir(data_dir)):
            results["skipped"][name] = "no shared data folder (set --data-dir or JAXRT_DATA_DIR)"
            continue
        try:
            scene = load_scene(name, n_triangles=config.n_triangles, seed=config.seed, data_dir=data_dir)
        except FileNotFoundError as error:
            results["skipped"][name] = str(error)
            continue
        if verbose:
            print(f"{scene.name}: {scene.description}", flush=True)
        results["scenes"].append(bench_scene(scene, config, verbose=verbose))
    results["total_s"] = time.perf_counter() - start
    results["load_average_end"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
    return results


def main(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv``, run, print the table and write the JSON file if asked; returns the exit status."""
    args = _parser().parse_args(argv)
    config = parse_args(argv)
    results = run(config, verbose=not args.quiet)
    if not args.quiet:
        print()
    print(format_table(results))
    if args.json:
        write_json(results, args.json)
        print(f"wrote {args.json}")
    if args.custom:
        from jaxrt.bench import custom

        print()
        custom.main(["--quick"] if args.quick else [])
    if args.points:
        from jaxrt.bench import points

        print()
        extra = ["--triangles", str(config.n_triangles), *(["--data-dir", args.data_dir] if args.data_dir else [])]
        points.main(["--scenes", *config.scenes, *extra, *(["--quick"] if args.quick else [])])
    return 0


if __name__ == "__main__":
    sys.exit(main())
