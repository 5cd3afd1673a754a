"""glTF animation as keyframe motion: channel sampling by hand, the staged InterpolationTest and
AnimatedMorphSphere files, and a trace of the morphing sphere against a float64 brute force at its keyframes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from reference import brute_force

import jaxrt as rt
from jaxrt._src.io.gltf_motion import sample_channel

pytest.importorskip("pygltflib")

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
INTERPOLATION = DATA / "gltf-interpolation-test" / "InterpolationTest.gltf"
MORPH = DATA / "gltf-animated-morph-sphere" / "AnimatedMorphSphere.gltf"


def test_sample_channel_step_linear_cubic_and_slerp():
    inputs = np.array([0.0, 1.0, 3.0])
    values = np.array([[0.0], [2.0], [4.0]])
    times = np.array([-1.0, 0.5, 1.0, 2.0, 5.0])
    np.testing.assert_allclose(sample_channel(inputs, values, "STEP", times, "translation")[:, 0], [0, 0, 2, 2, 4])
    np.testing.assert_allclose(sample_channel(inputs, values, "LINEAR", times, "translation")[:, 0], [0, 1, 2, 3, 4])
    # Hermite with zero tangents between 0 and 2 over [0, 1]: 2 (3 s^2 - 2 s^3) at s = 0.5 is 1.
    cubic = np.zeros((9, 1))
    cubic[1::3, 0] = values[:, 0]
    np.testing.assert_allclose(sample_channel(inputs, cubic, "CUBICSPLINE", np.array([0.5]), "translation"), [[1.0]])
    # Slerp halfway from the identity to a quarter turn about z is an eighth turn.
    quarter = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]
    half = sample_channel(
        np.array([0.0, 1.0]), np.array([[0.0, 0, 0, 1], quarter]), "LINEAR", np.array([0.5]), "rotation"
    )
    np.testing.assert_allclose(half, [[0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)]], atol=1e-12)


@pytest.mark.skipif(not INTERPOLATION.is_file(), reason="InterpolationTest.gltf is not staged")
def test_interpolation_test_nodes_follow_their_channels():
    import pygltflib

    motion = rt.io.load_gltf_motion(INTERPOLATION, keyframes=9)
    assert motion.structure.has_instance_motion and motion.motion.start_time == 0.0
    gltf = pygltflib.GLTF2().load(str(INTERPOLATION))
    by_name = {a.name: a for a in gltf.animations}
    # "Linear Translation" moves node 10 linearly through its keys; its world transform carries it.
    channel = by_name["Linear Translation"].channels[0]
    node = channel.target.node
    from jaxrt._src.io.gltf import _accessor, _read_buffers

    buffers = _read_buffers(gltf, INTERPOLATION)
    sampler = by_name["Linear Translation"].samplers[channel.sampler]
    inputs = _accessor(gltf, buffers, sampler.input, "input").astype(np.float64)
    outputs = _accessor(gltf, buffers, sampler.output, "output").astype(np.float64)
    matrices = dict(zip(motion.nodes, (m for _, m in motion.placements), strict=True))[node]
    parent = np.eye(4)  # the node is a scene root in this file
    expected = np.stack([np.interp(motion.times, inputs, outputs[:, a]) for a in range(3)], -1)
    static = np.asarray(gltf.nodes[node].translation or [0.0, 0, 0])
    assert not np.allclose(expected, static)
    np.testing.assert_allclose((parent @ matrices)[:, :3, 3], expected, atol=1e-6)


@pytest.mark.skipif(not MORPH.is_file(), reason="AnimatedMorphSphere.gltf is not staged")
def test_morph_sphere_traces_its_morphed_triangles_at_each_keyframe():
    motion = rt.io.load_gltf_motion(MORPH, keyframes=5)
    assert [s.motion is not None for s in motion.structure.primitive_structures] == [True]
    static = rt.io.load_gltf(MORPH)
    first = motion.triangles[0]
    assert not np.allclose(first[0], first[2]), "the morph weights should move the vertices"
    # At time 0 every morph weight is 0: the mesh is the static loader's.
    np.testing.assert_allclose(first[0], static.mesh_triangles[0], atol=1e-6)
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(32, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    origin = (-5.0 * directions).astype(np.float32)
    direction = (directions + 0.1 * rng.normal(size=directions.shape)).astype(np.float32)
    intersector = rt.Intersector(rt.tags.instancing, rt.tags.instance_motion, rt.tags.primitive_motion)
    ks = np.repeat(np.arange(len(motion.times)), origin.shape[0])
    times = motion.times[ks].astype(np.float32)
    rays = rt.Ray(np.tile(origin, (len(motion.times), 1)), np.tile(direction, (len(motion.times), 1)), time=times)
    hit = intersector.intersect(rays, motion.structure)
    distance = np.asarray(hit.distance).reshape(len(motion.times), -1)
    for k in range(len(motion.times)):
        ref = brute_force(origin, direction, np.zeros(32), np.full(32, np.inf), motion.world_triangles(k))
        near = np.where(ref.certain | ref.possible, ref.distance, np.inf).min(axis=1)
        certain = np.where(ref.certain, ref.distance, np.inf).min(axis=1)
        assert np.isfinite(certain).sum() >= 16
        hit_k = np.isfinite(distance[k])
        np.testing.assert_array_equal(hit_k[np.isfinite(certain)], True)
        np.testing.assert_allclose(distance[k][hit_k], near[hit_k], rtol=1e-4)
