"""The benchmark itself: for each scene, build and trace with every tracer and measure speed and error."""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from jaxrt.bench import rays as ray_sets
from jaxrt.bench.peers import Embree, embree_unavailable_reason
from jaxrt.bench.reference import Hits, error_stats, occlusion_mismatches, reference_hits
from jaxrt.bench.scenes import Scene
from jaxrt.bench.timing import Timing, timed
from jaxrt.bench.tracer import Jaxrt

__all__ = ["BenchConfig", "RAY_KINDS", "bench_scene"]

#: Ray sets by name: ``fn(scene, n_rays, seed) -> RayBatch``.
RAY_KINDS: dict[str, Callable[[Scene, int, int], ray_sets.RayBatch]] = {
    "primary": lambda scene, n, seed: ray_sets.primary_rays(scene.vertices, n, eye=scene.eye, target=scene.target),
    "diffuse": lambda scene, n, seed: ray_sets.diffuse_rays(scene.vertices, scene.indices, n, seed=seed),
}


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """What one bench run measures (the command-line flags)."""

    scenes: tuple[str, ...]
    n_triangles: int
    n_rays: int
    reference_rays: int
    repeats: int
    build_repeats: int
    reference: str = "numpy"
    ray_kinds: tuple[str, ...] = ("primary", "diffuse")
    embree: bool = True
    backend: str = "auto"
    also_portable: bool = False
    seed: int = 0
    data_dir: str | None = None


def _log(verbose: bool, message: str) -> None:
    if verbose:
        print(message, flush=True)


def bench_scene(scene: Scene, config: BenchConfig, *, verbose: bool = False) -> dict[str, Any]:
    """Measure every tracer on one scene; returns a JSON-ready record (see ``jaxrt.bench.report``)."""
    record: dict[str, Any] = {
        "scene": scene.name,
        "description": scene.description,
        "triangles": scene.triangle_count,
        "vertices": int(len(scene.vertices)),
        "build": {},
        "rays": {},
    }
    count = scene.triangle_count
    jaxrt = Jaxrt(scene.vertices, scene.indices, backend=config.backend)
    timing, _ = timed(jaxrt.build, config.build_repeats)
    record["build"]["jaxrt"] = timing.as_dict(count, "mprims_s")
    _log(verbose, f"  jaxrt build {timing.median_s * 1e3:.1f} ms (first call {timing.first_s:.2f} s)")
    portable = None
    if config.also_portable and config.backend != "portable":
        portable = Jaxrt(scene.vertices, scene.indices, backend="portable")
        portable.structure = jaxrt.structure  # the same tree: only the traversal differs
    embree = None
    if config.embree:
        reason = embree_unavailable_reason()
        if reason is None:
            embree = Embree(scene.vertices, scene.indices)
            timing, _ = timed(embree.build, config.build_repeats)
            record["build"]["embree"] = timing.as_dict(count, "mprims_s")
            _log(verbose, f"  embree build {timing.median_s * 1e3:.1f} ms")
        else:
            record["build"]["embree"] = {"skipped": reason}

    for kind in config.ray_kinds:
        batch = RAY_KINDS[kind](scene, config.n_rays, config.seed)
        rng = np.random.default_rng(config.seed + 1)
        subset = np.sort(rng.choice(len(batch), size=min(config.reference_rays, len(batch)), replace=False))
        checked = batch.take(subset)
        start = time.perf_counter()
        reference = reference_hits(scene.vertices, scene.indices, checked, method=config.reference)
        entry: dict[str, Any] = {
            "count": len(batch),
            "reference": {
                "method": config.reference,
                "rays": len(checked),
                "hits": int((reference.primitive >= 0).sum()),
                "seconds": time.perf_counter() - start,
            },
            "tracers": {},
        }
        _log(
            verbose,
            f"  {kind}: reference ({config.reference}, {len(checked):,} rays) {entry['reference']['seconds']:.1f} s",
        )

        device_rays = batch.to_jaxrt()
        closest, result = timed(functools.partial(jaxrt.closest, device_rays), config.repeats)
        hits = Jaxrt.hits(result)
        occlusion, result = timed(functools.partial(jaxrt.any_hit, device_rays), config.repeats)
        occluded = Jaxrt.occluded(result)
        entry["tracers"]["jaxrt"] = _tracer_entry(scene, batch, subset, reference, closest, hits, occlusion, occluded)
        _log(verbose, f"  {kind}: jaxrt {closest.median_s:.2f} s closest, {occlusion.median_s:.2f} s any-hit")
        if portable is not None:
            closest, result = timed(functools.partial(portable.closest, device_rays), config.repeats)
            hits = Jaxrt.hits(result)
            occlusion, result = timed(functools.partial(portable.any_hit, device_rays), config.repeats)
            occluded = Jaxrt.occluded(result)
            entry["tracers"]["portable"] = _tracer_entry(
                scene, batch, subset, reference, closest, hits, occlusion, occluded
            )
            _log(verbose, f"  {kind}: portable {closest.median_s:.2f} s closest, {occlusion.median_s:.2f} s any-hit")

        if embree is not None:
            closest, hits = timed(functools.partial(embree.closest, batch), config.repeats)
            occlusion, occluded = timed(functools.partial(embree.any_hit, batch), config.repeats)
            entry["tracers"]["embree"] = _tracer_entry(
                scene, batch, subset, reference, closest, hits, occlusion, occluded
            )
            entry["tracers"]["embree"]["trace_threads"] = Embree.trace_threads
            _log(verbose, f"  {kind}: embree {closest.median_s:.3f} s closest, {occlusion.median_s:.3f} s any-hit")
        record["rays"][kind] = entry
    return record


def _tracer_entry(
    scene: Scene,
    batch: ray_sets.RayBatch,
    subset: np.ndarray,
    reference: Hits,
    closest: Timing,
    hits: Hits,
    occlusion: Timing,
    occluded: np.ndarray,
) -> dict[str, Any]:
    """Speed over the whole batch; errors on the reference subset."""
    n = len(batch)
    checked = Hits(hits.distance[subset], hits.primitive[subset])
    error = error_stats(scene.vertices, scene.indices, batch.take(subset), checked, reference)
    error["any_hit_mismatch"] = occlusion_mismatches(occluded[subset], reference)
    return {
        "closest": closest.as_dict(n),
        "any_hit": occlusion.as_dict(n),
        "hit_fraction": float((hits.primitive >= 0).mean()),
        "error": error,
    }
