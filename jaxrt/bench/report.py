"""Machine information, the readable table and the JSON file of a bench run."""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

import jax
import numpy as np

import jaxrt

__all__ = ["machine_info", "format_table", "write_json"]


def _version(package: str) -> str | None:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return None


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _git_commit() -> str | None:
    """The commit of the jaxrt checkout, with ``+dirty`` when it has uncommitted changes (``None`` outside git)."""
    folder = Path(jaxrt.__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=folder, capture_output=True, text=True, timeout=5, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "."],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return commit + ("+dirty" if dirty else "")


def machine_info() -> dict[str, Any]:
    """Versions, device and CPU of this machine, and its load average (other work skews timings)."""
    device = jax.devices()[0]
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = os.cpu_count()
    return {
        "jaxrt_version": jaxrt.__version__,
        "jaxrt_commit": _git_commit(),
        "jax_version": jax.__version__,
        "jaxlib_version": _version("jaxlib"),
        "backend": jax.default_backend(),
        "device_kind": device.device_kind,
        "device_count": jax.device_count(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": affinity,
        "cpu_model": _cpu_model(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy_version": np.__version__,
        "embreex_version": _version("embreex"),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
    }


def _rate(entry: dict[str, Any], key: str, digits: int = 3) -> str:
    return f"{entry[key]:9.{digits}f}" if key in entry else f"{'-':>9}"


def _sci(x: float) -> str:
    return f"{x:8.1e}"


def format_table(results: dict[str, Any]) -> str:
    """The run as a plain-text table: build speed, trace speed and errors per scene, ray set and tracer."""
    machine, config = results["machine"], results["config"]
    load = machine.get("load_average")
    end_load = results.get("load_average_end")
    lines = [
        f"jaxrt {machine['jaxrt_version']} ({machine['jaxrt_commit']}) bench on {machine['backend']} "
        f"({machine['device_kind']}), jax {machine['jax_version']}, {machine['cpu_count']} CPUs ({machine['cpu_model']})",
    ]
    if load:
        lines.append(f"1-min load average at start {load[0]:.1f}" + (f", at end {end_load[0]:.1f}" if end_load else ""))
    lines.append(
        f"{config['n_rays']:,} rays per set; speed is the median of {config['repeats']} warm runs after a warm-up; "
        f"errors on {config['reference_rays']:,} rays against the float64 reference '{config['reference']}'"
    )
    if machine.get("embreex_version"):
        lines.append(
            f"Embree via embreex {machine['embreex_version']}: traces on 1 thread (embreex holds the GIL), builds with TBB"
        )
    lines += ["", "Build (median of warm builds)"]
    lines.append(
        f"{'scene':<8} {'triangles':>10} {'jaxrt ms':>9} {'Mprims/s':>9} {'compile s':>9} {'embree ms':>10} {'Mprims/s':>9}"
    )
    for scene in results["scenes"]:
        ours = scene["build"]["jaxrt"]
        peer = scene["build"].get("embree", {})
        peer_ms = f"{peer['median_s'] * 1e3:10.1f}" if "median_s" in peer else f"{'-':>10}"
        lines.append(
            f"{scene['scene']:<8} {scene['triangles']:>10,} {ours['median_s'] * 1e3:9.1f} {ours['mprims_s']:9.2f} "
            f"{ours['compile_s']:9.2f} {peer_ms} {_rate(peer, 'mprims_s', 2)}"
        )
    lines += [
        "",
        "Trace: Mrays/s (closest / any-hit); compile s of the first call; errors vs the reference:",
        "hit/miss and non-tie primitive mismatches, ties, relative distance error (max, p99; 'own': against the",
        "float64 distance of the tracer's own primitive), any-hit answers that disagree with the reference",
    ]
    header = (
        f"{'scene':<8} {'rays':<8} {'tracer':<7} {'closest':>9} {'any-hit':>9} {'compile s':>11} {'hits':>5} "
        f"{'hit/miss':>8} {'prim':>5} {'ties':>5} {'max rel':>8} {'p99 rel':>8} {'own max':>8} {'any':>4}"
    )
    lines.append(header)
    for scene in results["scenes"]:
        for kind, entry in scene["rays"].items():
            for name, tracer in entry["tracers"].items():
                error = tracer["error"]
                compile_s = "-"
                if name in ("jaxrt", "portable"):
                    compile_s = f"{tracer['closest']['compile_s']:.1f}/{tracer['any_hit']['compile_s']:.1f}"
                lines.append(
                    f"{scene['scene']:<8} {kind:<8} {name:<7} {tracer['closest']['mrays_s']:9.3f} "
                    f"{tracer['any_hit']['mrays_s']:9.3f} {compile_s:>11} {tracer['hit_fraction']:5.2f} "
                    f"{error['hit_mismatch']:8d} {error['primitive_mismatch']:5d} {error['ties']:5d} "
                    f"{_sci(error['distance_max_rel'])} {_sci(error['distance_p99_rel'])} "
                    f"{_sci(error['own_primitive_max_rel'])} {error['any_hit_mismatch']:4d}"
                )
    if results.get("skipped"):
        lines += ["", "Skipped: " + "; ".join(f"{k} ({v})" for k, v in results["skipped"].items())]
    lines.append(f"Total {results.get('total_s', 0.0):.0f} s")
    return "\n".join(lines)


def write_json(results: dict[str, Any], path: str | os.PathLike[str]) -> None:
    """Write ``results`` as indented JSON (infinities as strings, which JSON lacks)."""

    def clean(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: clean(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [clean(v) for v in value]
        if isinstance(value, float) and not np.isfinite(value):
            return str(value)
        return value

    Path(path).write_text(json.dumps(clean(results), indent=2) + "\n")
