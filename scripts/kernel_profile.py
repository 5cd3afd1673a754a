"""Trace one ray set with one tracer a few times, so that a profiler can capture one warm launch.

Made for Nsight Compute: the tracer runs ``--calls`` times (the first compiles), each call synchronised, so that
``ncu --launch-skip 1 --launch-count 1 -k regex:NAME`` captures a warm launch of the kernel named NAME
(``trace_kernel``, ``trace_wide_kernel``; Warp's query kernels are named ``closest`` and ``anyhit``):

    ncu --clock-control none -k regex:trace --launch-skip 1 --launch-count 1 --set full -o bunny \
        python scripts/kernel_profile.py --scene bunny --rays primary --tracer binary --meshes .meshes

Tracers: ``binary`` (the kernel on the structure's binary nodes, rays read as given: what ``intersect``
launches), ``wide4`` / ``wide1`` (the 4-wide layout with leaf clusters of at most 4 / 1 triangles),
``high`` (the binary kernel on the clustering tree), ``warp-sah`` / ``warp-lbvh`` (NVIDIA Warp's
``mesh_query_ray`` on its SAH / LBVH tree, as ``python -m jaxrt.bench.gpu --peers`` times it).

``--report DIR`` instead reads the CSV pages that ``ncu --import R --page raw --csv`` wrote to ``DIR/*.csv``
and prints one table row per profile (registers, occupancy, issue, stalls, caches).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import sys
from pathlib import Path

TRACERS = ("binary", "wide4", "wide1", "high", "warp-sah", "warp-lbvh")

#: The raw metrics the report prints, with their column names (Nsight Compute 2025 names).
REPORT_METRICS = {
    "gpu__time_duration.sum": "µs",
    "launch__registers_per_thread": "regs",
    "launch__block_size": "block",
    "launch__occupancy_limit_registers": "blocks/SM by regs",
    "launch__occupancy_limit_blocks": "blocks/SM by limit",
    "sm__maximum_warps_per_active_cycle_pct": "theor. occ. %",
    "sm__warps_active.avg.pct_of_peak_sustained_active": "achieved occ. %",
    "smsp__thread_inst_executed_per_inst_executed.ratio": "threads/instr",
    "smsp__inst_executed.sum": "warp instrs",
    "smsp__issue_active.avg.pct_of_peak_sustained_active": "issue busy %",
    "smsp__average_warp_latency_per_inst_issued.ratio": "cycles/issue per warp",
    "smsp__average_warps_issue_stalled_long_scoreboard_per_issue_active.ratio": "stall long sb",
    "smsp__average_warps_issue_stalled_short_scoreboard_per_issue_active.ratio": "stall short sb",
    "smsp__average_warps_issue_stalled_wait_per_issue_active.ratio": "stall wait",
    "smsp__average_warps_issue_stalled_math_pipe_throttle_per_issue_active.ratio": "stall math",
    "smsp__average_warps_issue_stalled_lg_throttle_per_issue_active.ratio": "stall lg",
    "smsp__average_warps_issue_stalled_branch_resolving_per_issue_active.ratio": "stall branch",
    "smsp__average_warps_issue_stalled_no_instruction_per_issue_active.ratio": "stall no instr",
    "smsp__average_warps_issue_stalled_not_selected_per_issue_active.ratio": "not selected",
    "l1tex__t_sector_hit_rate.pct": "L1 hit %",
    "lts__t_sector_hit_rate.pct": "L2 hit %",
    "dram__throughput.avg.pct_of_peak_sustained_elapsed": "DRAM %",
    "smsp__sass_inst_executed_op_local_ld.sum": "local loads",
    "smsp__sass_inst_executed_op_global_ld.sum": "global loads",
}


def _run(args) -> None:
    import jax
    import numpy as np

    import jaxrt as rt
    from jaxrt.bench import gpu as bench

    scene = bench._load_scene(args.scene, args.triangles, args.meshes)
    batch = bench._rays(args.rays, scene, args.n)
    any_hit = args.rays == "shadow"
    if args.tracer.startswith("warp"):
        wp, build, closest, anyhit = bench._warp_tracer(scene, args.tracer.split("-")[1])
        mesh = build()
        o = wp.array(batch.origin, dtype=wp.vec3)
        d = wp.array(batch.direction, dtype=wp.vec3)
        far = wp.array(np.where(np.isinf(batch.max_distance), np.float32(1e30), batch.max_distance), dtype=float)
        out = wp.zeros(len(batch), dtype=int)
        for _ in range(args.calls):
            if any_hit:
                wp.launch(anyhit, len(batch), inputs=[mesh.id, o, d, far, out])
            else:
                wp.launch(closest, len(batch), inputs=[mesh.id, o, d, far, out, wp.zeros(len(batch), dtype=float)])
            wp.synchronize()
        print(f"{args.scene} {args.rays} {args.tracer}: hits {int((out.numpy() >= (1 if any_hit else 0)).sum())}")
        return
    from jaxrt._src.traversal import gpu

    quality = "high" if args.tracer == "high" else "fast"
    structure = jax.jit(lambda v, i: rt.build_primitive_structure(rt.TriangleGeometry(v, i), quality=quality))(
        scene.vertices, scene.indices
    )
    options = gpu.DEFAULT_OPTIONS
    if args.tracer.startswith("wide"):
        options = dataclasses.replace(options, node_width=4, leaf_size=int(args.tracer[4:]))
    n = len(batch)
    launch = bench.kernel_launch(structure, bench._device_rays(batch), any_hit, options)
    for _ in range(args.calls):
        out = jax.block_until_ready(launch())
    visited = np.asarray(out[2])[:n]
    print(
        f"{args.scene} {args.rays} {args.tracer}: hits {int((np.asarray(out[1])[:n] >= 0).sum())}, "
        f"nodes visited mean {visited.mean():.1f} max {visited.max()}"
    )


def _report(folder: Path) -> None:
    """One row per ``*.csv`` raw page in ``folder``: the :data:`REPORT_METRICS` of its first kernel."""
    names = list(REPORT_METRICS)
    print("| profile | " + " | ".join(REPORT_METRICS.values()) + " |")
    print("|---" * (len(names) + 1) + "|")
    for path in sorted(folder.glob("*.csv")):
        rows = [r for r in csv.reader(path.read_text().splitlines()) if r]
        header = next((i for i, r in enumerate(rows) if "Kernel Name" in r), None)
        if header is None or header + 2 >= len(rows):
            print(f"| {path.stem} | (no kernel profiled) |")
            continue
        columns = rows[header]
        values = rows[header + 2]  # the line after the header holds the units
        cell = {c: v for c, v in zip(columns, values, strict=False)}
        print(f"| {path.stem} | " + " | ".join(cell.get(m, "–").replace(",", "") for m in names) + " |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="bunny")
    parser.add_argument("--rays", default="primary", choices=("primary", "diffuse", "shadow"))
    parser.add_argument("--tracer", default="binary", choices=TRACERS)
    parser.add_argument("--meshes", help="folder holding the mesh files (else the shared data folder)")
    parser.add_argument("--n", type=int, default=1 << 20, help="rays (2**20)")
    parser.add_argument("--triangles", type=int, default=1 << 20, help="triangles of a procedural scene")
    parser.add_argument("--calls", type=int, default=3)
    parser.add_argument("--report", metavar="DIR", help="print the table of the CSV pages in DIR instead")
    args = parser.parse_args(argv)
    if args.report:
        _report(Path(args.report))
    else:
        _run(args)


if __name__ == "__main__":
    sys.exit(main())
