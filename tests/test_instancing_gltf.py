"""glTF scenes as instance structures: a synthetic file checked by hand, the staged sample files, and cycles."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import data_dir

import jaxrt as rt

pytest.importorskip("pygltflib")

DATA = data_dir()  # $JAXRT_DATA_DIR, else shared/data beside the repository
SIMPLE = DATA / "gltf-simple-instancing" / "SimpleInstancing.gltf"
ENGINE = DATA / "gltf-2cylinderengine-hierarchy" / "2CylinderEngine.glb"


def _write_gltf(path: Path, nodes: list[dict], scene_nodes: list[int]) -> Path:
    """A file with one mesh (two triangles as a strip, unindexed) and one indexed triangle list mesh."""
    strip = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    tri = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0]], np.float32)
    indices = np.array([0, 1, 2], np.uint16)
    translations = np.array([[0, 0, 0], [5, 0, 0], [0, 5, 0]], np.float32)
    rotations = np.array([[0, 0, 0, 1], [0, 0, 0.7071068, 0.7071068], [0, 0, 0, 1]], np.float32)
    blob = strip.tobytes() + tri.tobytes() + indices.tobytes() + b"\0\0" + translations.tobytes() + rotations.tobytes()
    offsets = np.cumsum([0, strip.nbytes, tri.nbytes, indices.nbytes + 2, translations.nbytes])
    views = [
        dict(buffer=0, byteOffset=int(offsets[0]), byteLength=strip.nbytes),
        dict(buffer=0, byteOffset=int(offsets[1]), byteLength=tri.nbytes),
        dict(buffer=0, byteOffset=int(offsets[2]), byteLength=indices.nbytes),
        dict(buffer=0, byteOffset=int(offsets[3]), byteLength=translations.nbytes),
        dict(buffer=0, byteOffset=int(offsets[4]), byteLength=rotations.nbytes),
    ]
    accessors = [
        dict(bufferView=0, componentType=5126, count=4, type="VEC3", min=[0, 0, 0], max=[1, 1, 0]),
        dict(bufferView=1, componentType=5126, count=3, type="VEC3", min=[0, 0, 0], max=[0, 1, 1]),
        dict(bufferView=2, componentType=5123, count=3, type="SCALAR"),
        dict(bufferView=3, componentType=5126, count=3, type="VEC3"),
        dict(bufferView=4, componentType=5126, count=3, type="VEC4"),
    ]
    document = dict(
        asset=dict(version="2.0"),
        extensionsUsed=["EXT_mesh_gpu_instancing"],
        scene=0,
        scenes=[dict(nodes=scene_nodes)],
        nodes=nodes,
        meshes=[
            dict(primitives=[dict(attributes=dict(POSITION=0), mode=5)]),
            dict(primitives=[dict(attributes=dict(POSITION=1), indices=2)]),
        ],
        accessors=accessors,
        bufferViews=views,
        buffers=[
            dict(byteLength=len(blob), uri="data:application/octet-stream;base64," + base64.b64encode(blob).decode())
        ],
    )
    path.write_text(json.dumps(document))
    return path


def _synthetic_nodes() -> list[dict]:
    gpu = {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": 3, "ROTATION": 4}}}
    return [
        dict(children=[1, 2], translation=[0, 0, -10]),  # the root moves everything 10 down
        dict(mesh=0, scale=[2, 2, 2]),  # the strip, scaled
        dict(children=[3], matrix=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 20, 0, 0, 1]),  # column-major: x + 20
        dict(mesh=1, extensions=gpu),  # three copies of the triangle
        dict(mesh=0, scale=[0, 0, 0]),  # not in the scene: never loaded
    ]


def _expected_world_triangles() -> np.ndarray:
    # glTF strips: triangle i is (v_i, v_{i+1+i%2}, v_{i+2-i%2}), so both keep the first one's winding.
    strip = 2 * np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0], [0, 1, 0]]], np.float64)
    tri = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0]], np.float64)
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.float64)  # 90 degrees about z
    copies = [tri, tri @ rot.T + [5, 0, 0], tri + [0, 5, 0]]
    out = [t + [0, 0, -10] for t in strip] + [c + [20, 0, -10] for c in copies]
    return np.stack(out)


def _aimed(triangles: np.ndarray, rays: int, seed: int):
    rng = np.random.default_rng(seed)
    area = np.linalg.norm(np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]), axis=1)
    target = rng.choice(np.flatnonzero(area > 1e-6 * area.max()), rays)
    point = np.einsum("rk,rkj->rj", rng.dirichlet([2, 2, 2], rays), triangles[target])
    normal = np.cross(triangles[target, 1] - triangles[target, 0], triangles[target, 2] - triangles[target, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    origin = point + normal * rng.uniform(2, 6, (rays, 1)) * np.sign(rng.uniform(-1, 1, (rays, 1)))
    origin += rng.normal(size=(rays, 3)) * 0.5
    return origin.astype(np.float32), (point - origin).astype(np.float32)


def _compare_with_baked(scene, rays: int = 128, seed: int = 0) -> np.ndarray:
    """Trace the instanced scene and a baked copy of its world triangles; they agree on hits and distances."""
    world = scene.world_triangles()
    origin, direction = _aimed(world, rays, seed)
    ray = rt.Ray(origin, direction)
    instanced = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(scene.levels)).intersect(ray, scene.structure)
    baked = rt.Intersector().intersect(
        ray, rt.build_primitive_structure(rt.TriangleGeometry(world.reshape(-1, 3).astype(np.float32)))
    )
    hit = np.asarray(instanced.type) != 0
    np.testing.assert_array_equal(hit, np.asarray(baked.type) != 0)
    np.testing.assert_allclose(
        np.asarray(instanced.distance)[hit], np.asarray(baked.distance)[hit], rtol=1e-4, atol=1e-4
    )
    assert hit.mean() > 0.9
    return np.asarray(instanced.instance_count)


def test_synthetic_hierarchy_with_gpu_instancing(tmp_path):
    path = _write_gltf(tmp_path / "scene.gltf", _synthetic_nodes(), [0])
    for hierarchy in (True, False):
        scene = rt.io.load_gltf(path, hierarchy=hierarchy)
        np.testing.assert_allclose(scene.world_triangles(), _expected_world_triangles(), atol=1e-6)
        assert (scene.triangle_count, scene.instanced_triangle_count) == (3, 5)
        assert scene.meshes[0] is not None and scene.meshes[0].primitive_count == 2
        # root -> node 2 -> node 3 (GPU instances): three levels; flat: one.
        assert scene.levels == (3 if hierarchy else 1)
        counts = _compare_with_baked(scene, rays=32)
        # The strip sits one level higher than the GPU-instanced triangles.
        assert set(counts.tolist()) <= ({0, 2, 3} if hierarchy else {0, 1}) and counts.max() == scene.levels


def test_node_cycles_are_rejected_by_name(tmp_path):
    nodes = [dict(children=[1]), dict(children=[2], mesh=1), dict(children=[1])]
    path = _write_gltf(tmp_path / "cycle.gltf", nodes, [0])
    with pytest.raises(ValueError, match=r"cycle \(1 -> 2 -> 1\): node 1 is its own ancestor"):
        rt.io.load_gltf(path)


def test_missing_file_and_empty_scene(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        rt.io.load_gltf(tmp_path / "absent.gltf")
    path = _write_gltf(tmp_path / "empty.gltf", [dict(name="lonely")], [0])
    with pytest.raises(ValueError, match="has no triangles"):
        rt.io.load_gltf(path)


@pytest.mark.skipif(not SIMPLE.is_file(), reason="staged glTF sample data is absent")
def test_simple_instancing_sample():
    scene = rt.io.load_gltf(SIMPLE)
    assert (scene.triangle_count, scene.instanced_triangle_count, scene.levels) == (12, 1500, 2)
    assert len(scene.placements) == 125
    counts = _compare_with_baked(scene)
    assert set(counts.tolist()) <= {0, 2}


@pytest.mark.slow
@pytest.mark.skipif(not ENGINE.is_file(), reason="staged glTF sample data is absent")
def test_engine_hierarchy_sample():
    # The staged data's manifest: 75,730 distinct triangles, 121,496 with node reuse.
    flat = rt.io.load_gltf(ENGINE, hierarchy=False)
    assert (flat.triangle_count, flat.instanced_triangle_count, flat.levels) == (75730, 121496, 1)
    trimesh = pytest.importorskip("trimesh")
    reference = trimesh.load(ENGINE, force="scene").to_geometry()
    world = flat.world_triangles().reshape(-1, 3)
    np.testing.assert_allclose([world.min(0), world.max(0)], reference.bounds, rtol=1e-5, atol=1e-4)
    _compare_with_baked(flat, rays=64, seed=1)
    nested = rt.io.load_gltf(ENGINE, hierarchy=True)
    assert nested.levels > 2 and nested.instanced_triangle_count == 121496
    np.testing.assert_allclose(nested.world_triangles(), flat.world_triangles())
    counts = _compare_with_baked(nested, rays=64, seed=1)
    assert counts.max() > 2
