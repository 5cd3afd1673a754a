"""Smoke tests of ``python -m jaxrt.bench`` (tiny sizes) and of the mesh loader."""

from __future__ import annotations

import gzip
import json

import numpy as np
import pytest

from jaxrt.bench import main
from jaxrt.bench.rays import diffuse_rays, primary_rays, shadow_rays
from jaxrt.bench.scenes import noisy_sphere
from jaxrt.io import load_mesh


def test_quick_bench_writes_expected_json_and_jaxrt_matches_reference(tmp_path):
    path = tmp_path / "bench.json"
    assert main(["--quick", "--scenes", "sphere", "--quiet", "--json", str(path)]) == 0
    results = json.loads(path.read_text())
    assert {"machine", "config", "scenes", "total_s"} <= set(results)
    assert {"jax_version", "backend", "device_kind", "cpu_count"} <= set(results["machine"])
    (scene,) = results["scenes"]
    assert scene["scene"] == "sphere" and scene["triangles"] > 0
    assert {"first_s", "compile_s", "median_s", "mprims_s"} <= set(scene["build"]["jaxrt"])
    assert set(scene["rays"]) == {"primary", "diffuse"}
    for kind, entry in scene["rays"].items():
        assert entry["reference"]["hits"] > 0, kind
        ours = entry["tracers"]["jaxrt"]
        assert ours["closest"]["mrays_s"] > 0 and ours["any_hit"]["mrays_s"] > 0
        error = ours["error"]
        assert error["rays"] == entry["reference"]["rays"]
        assert error["hit_mismatch"] == 0, (kind, error)
        assert error["primitive_mismatch"] == 0, (kind, error)
        assert error["any_hit_mismatch"] == 0, (kind, error)
        assert error["distance_max_rel"] < 1e-4, (kind, error)
        if "embree" in entry["tracers"]:
            assert {"closest", "any_hit", "error"} <= set(entry["tracers"]["embree"])


def test_ray_sets_shapes_and_conventions():
    scene = noisy_sphere(500, seed=1)
    primary = primary_rays(scene.vertices, 64)
    assert primary.origin.shape == (64, 3) and primary.direction.dtype == np.float32
    # Scanline order: the first ray points to the top-left corner, the last row is the bottom one.
    assert primary.direction[0, 1] > primary.direction[-1, 1]
    for batch in (
        primary,
        diffuse_rays(scene.vertices, scene.indices, 64),
        shadow_rays(scene.vertices, scene.indices, 64),
    ):
        np.testing.assert_allclose(np.linalg.norm(batch.direction, axis=1), 1.0, rtol=1e-5)
    assert np.isfinite(shadow_rays(scene.vertices, scene.indices, 8).max_distance).all()


def test_noisy_sphere_is_closed():
    scene = noisy_sphere(300)
    edges = np.sort(scene.indices[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()


_OBJ = "# a quad and a triangle\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3 4\nf 1 2 5\n"


def test_load_mesh_reads_obj_and_gzipped_obj(tmp_path):
    pytest.importorskip("trimesh")
    plain = tmp_path / "tiny.obj"
    plain.write_text(_OBJ)
    packed = tmp_path / "tiny.obj.gz"
    packed.write_bytes(gzip.compress(_OBJ.encode()))
    for path in (plain, packed):
        vertices, indices = load_mesh(path)
        assert vertices.dtype == np.float32 and vertices.shape == (5, 3)
        assert indices.dtype == np.int32 and indices.shape == (3, 3)
        assert indices.min() >= 0 and indices.max() < len(vertices)
        # The quad is split into two triangles covering the unit square.
        areas = np.linalg.norm(np.cross(*(vertices[indices[:, k]] - vertices[indices[:, 0]] for k in (1, 2))), axis=1)
        np.testing.assert_allclose(sorted(areas / 2), [0.5, 0.5, 0.5])


def test_load_mesh_errors(tmp_path):
    pytest.importorskip("trimesh")
    with pytest.raises(FileNotFoundError, match="no such file"):
        load_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "noext"
    bad.write_text(_OBJ)
    with pytest.raises(ValueError, match="no extension"):
        load_mesh(bad)
    huge = tmp_path / "huge.obj"
    huge.write_text("v 0 0 0\nv 1e39 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="not finite in float32"):
        load_mesh(huge)


def test_custom_geometry_bench_reports_analytic_spheres_exactly(tmp_path):
    from jaxrt.bench import custom

    path = tmp_path / "custom.json"
    results = custom.main(["--spheres", "20", "--triangles", "500", "--rays", "256", "--repeats", "0",
                           "--json", str(path)])  # fmt: skip
    assert json.loads(path.read_text())["config"]["spheres"] == 20
    boxes, user, *tessellated = results["spheres"]
    assert boxes["hits"] > 0 and boxes["hit_mismatches"] == 0
    assert boxes["max_rel_error"] < 1e-5  # float32 analytic roots against float64 ones
    assert user["hits"] == boxes["hits"] and user["path"] == "portable"  # a user function: the portable path
    assert len(tessellated) == 3 and all(row["trace"]["mrays_s"] > 0 for row in tessellated)
    # The finest tessellation is closer to the sphere than the coarsest.
    assert tessellated[-1]["median_rel_error"] < tessellated[0]["median_rel_error"]
    hits = {row["case"]: row["hits"] for row in results["filters"]}
    assert (
        hits["opaque, no filter"] == hits["opaque, filter (never called)"] == hits["non-opaque, filter accepting all"]
    )
    assert 0 < hits["non-opaque, alpha filter (~50% rejected)"] <= hits["opaque, no filter"]
    # The same alpha test in an intersection query's loop commits the same hits.
    assert (
        hits["non-opaque, alpha test in an intersection query's loop (~50% rejected)"]
        == hits["non-opaque, alpha filter (~50% rejected)"]
    )


def test_spheres_bench_compares_builtin_spheres_with_boxes(tmp_path):
    from jaxrt.bench import spheres

    path = tmp_path / "spheres.json"
    assert spheres.main(["--quick", "--triangles", "--json", str(path)]) == 0
    builtin, boxes, triangles = json.loads(path.read_text())["rows"]
    assert builtin["geometry"].startswith("built-in") and boxes["geometry"].startswith("boxes")
    for row in (builtin, boxes):
        assert row["hits"] > 0 and row["hit_mismatches"] == 0 and row["max_rel_error"] < 1e-5
    for row in (builtin, boxes, triangles):
        assert row["trace"]["mrays_s"] > 0 and row["nodes_visited_per_ray"] >= 1
    # the same spheres as boxes: the same tree and the same visits
    assert builtin["nodes_visited_per_ray"] == boxes["nodes_visited_per_ray"]
    assert "hit_mismatches" not in triangles  # its errors would be against the spheres
    assert builtin["bytes_per_primitive"] < boxes["bytes_per_primitive"]


def test_cpu_bench_rows_name_every_tracer(capsys):
    """``python -m jaxrt.bench.cpu`` on a tiny scene: a row per ray set and query with the kernel, ``intersect``
    and (``--jit``) ``intersect`` inside ``jax.jit``, Embree where embreex imports, Open3D where open3d does."""
    from jaxrt._src.traversal import cpu
    from jaxrt.bench import cpu as bench_cpu
    from jaxrt.bench.peers import embree_unavailable_reason, open3d_unavailable_reason

    if cpu.unavailable_reason() is not None:
        pytest.skip(cpu.unavailable_reason())
    assert bench_cpu.main(["--scenes", "sphere", "--rays", "256", "--repeats", "1", "--threads", "1", "--jit", "--queries", "closest"]) == 0  # fmt: skip
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("sphere")]
    assert len(lines) == 2  # primary and diffuse rays
    for line in lines:
        assert "kernel 1t" in line and "intersect 1t" in line and "jit 1t" in line
        assert ("embree 1t" in line) == (embree_unavailable_reason() is None)
        assert ("open3d" in line) == (open3d_unavailable_reason() is None)


def test_open3d_peer_agrees_with_embree():
    """Open3D's nearest hits and occlusion answers on the bench's rays equal Embree's (both Embree underneath;
    the shared decisions are hit or miss and, away from ties, the primitive)."""
    from jaxrt.bench.peers import Embree, Open3D, embree_unavailable_reason, open3d_unavailable_reason

    for reason in (open3d_unavailable_reason(), embree_unavailable_reason()):
        if reason is not None:
            pytest.skip(reason)
    scene = noisy_sphere(2_000, seed=1)
    rays = diffuse_rays(scene.vertices, scene.indices, 512, seed=0)
    embree, open3d = Embree(scene.vertices, scene.indices), Open3D(scene.vertices, scene.indices)
    embree.build()
    open3d.build()
    ours, theirs = open3d.closest(rays), embree.closest(rays)
    np.testing.assert_array_equal(np.isfinite(ours.distance), np.isfinite(theirs.distance))
    assert np.mean(ours.primitive == theirs.primitive) > 0.99
    np.testing.assert_allclose(ours.distance[np.isfinite(ours.distance)], theirs.distance[np.isfinite(theirs.distance)], rtol=1e-5)  # fmt: skip
    np.testing.assert_array_equal(open3d.any_hit(rays), embree.any_hit(rays))
