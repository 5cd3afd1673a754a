"""Visibility-aware gradients (edge sampling) against central differences of exact pixel integrals, in float64.

The scenes (``jaxrt.bench.visibility_scenes``) are flat-shaded triangles whose pixel integrals are sums of
convex-polygon areas, computed exactly in numpy; their central differences are the reference. The estimator
is ``jax.grad`` of ``sum(weights * rt.pixel_integral(...))`` with a fixed key. For each parameter group
(vertex positions, a translation, a rotation; the triangle's vertices behind the occluder; the instance
transform's rotation and translation) the gradient vector must be within 5% of the reference, and every
component whose reference is at least 1% of the group's largest must have its sign.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt

SAMPLES_PER_PIXEL = 4
EDGE_SAMPLES = 8192
SHADOW_EDGE_SAMPLES = 4096
TOLERANCE = 0.05


def _check(name: str, estimate: dict, reference: dict) -> None:
    for group, ref in reference.items():
        ref = np.ravel(ref)
        est = np.ravel(np.asarray(estimate[group]))
        scale = np.abs(ref).max()
        assert scale > 0, (name, group)
        error = np.linalg.norm(est - ref) / np.linalg.norm(ref)
        assert error <= TOLERANCE, f"{name}/{group}: relative error {error:.3f}\nest {est}\nref {ref}"
        significant = np.abs(ref) >= 0.01 * scale
        wrong = significant & (np.sign(est) != np.sign(ref))
        assert not wrong.any(), f"{name}/{group}: sign differs at {np.flatnonzero(wrong)}\nest {est}\nref {ref}"


@pytest.mark.parametrize("name", ["silhouette", "occlusion", "shadow", "shadow_point", "instanced_far"])
def test_gradients_match_central_differences(name):
    with jax.enable_x64(True):
        from jaxrt.bench import visibility_scenes

        scene = visibility_scenes.scenes()[name]
        reference = visibility_scenes.exact_gradient(scene)
        shadows = SHADOW_EDGE_SAMPLES if name.startswith("shadow") else 0
        grad = visibility_scenes.estimator_gradient(scene, None, SAMPLES_PER_PIXEL, EDGE_SAMPLES, shadows)
        params = {k: jnp.asarray(v) for k, v in scene.params.items()}
        if name == "silhouette":  # jit of vmap over keys: two independent estimates, each within tolerance
            keys = jax.random.split(jax.random.key(0), 2)
            batched = jax.vmap(grad, in_axes=(None, 0))(params, keys)
            for i in range(2):
                _check(f"{name}[{i}]", jax.tree_util.tree_map(lambda a, i=i: a[i], batched), reference)
        else:
            _check(name, grad(params, jax.random.key(0)), reference)
        # Plain autodiff (no edge samples) misses the boundary term: far from the reference.
        if name == "silhouette":
            plain = visibility_scenes.estimator_gradient(scene, None, SAMPLES_PER_PIXEL, 0, 0)(
                params, jax.random.key(0)
            )
            assert np.allclose(np.asarray(plain["translation"]), 0.0)  # constant shading: no area term at all


def test_boundary_term_value_and_derivative():
    """The boundary image is exactly 0; its derivative is the sum of weight * jump * (normal . velocity)."""
    with jax.enable_x64(True):
        camera = rt.PinholeCamera(4, 3, eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0))
        normal = jnp.array([[1.0, 0.0], [0.6, 0.8], [0.0, -1.0]])
        weight = jnp.array([0.5, 2.0, 1.5])
        jump = jnp.array([[1.0, -2.0], [0.25, 3.0], [2.0, 1.0]])

        def image(shift):
            position = jnp.array([[0.5, 0.5], [3.2, 2.9], [3.2, 2.1]]) + shift
            samples = rt.visibility.EdgeSamples(position, normal, weight)
            return rt.visibility.boundary_term(camera, samples, jump)

        shift = jnp.zeros((3, 2))
        velocity = jnp.array([[1.0, 2.0], [-1.0, 0.5], [0.3, 0.7]])
        value, tangent = jax.jvp(image, (shift,), (velocity,))
        assert value.shape == (3, 4, 2) and not np.any(np.asarray(value))
        expected = np.zeros((3, 4, 2))
        rate = np.asarray(weight)[:, None] * np.asarray(jump) * np.sum(np.asarray(normal * velocity), -1)[:, None]
        for (col, row), r in zip([(0, 0), (3, 2), (3, 2)], rate, strict=True):
            expected[row, col] += r
        np.testing.assert_allclose(np.asarray(tangent), expected, rtol=1e-12)
        cotangent = jnp.arange(24.0).reshape(3, 4, 2)
        (pulled,) = jax.vjp(image, shift)[1](cotangent)
        np.testing.assert_allclose(float(jnp.sum(pulled * velocity)), float(jnp.sum(cotangent * tangent)), rtol=1e-12)


def test_camera_projection_inverts_rays():
    with jax.enable_x64(True):
        camera = rt.PinholeCamera(7, 5, eye=(0.3, 1.0, 4.0), target=(0.0, -0.2, 0.1), fov_degrees=50.0)
        positions = jnp.array([[0.0, 0.0], [3.5, 2.5], [6.9, 4.2], [1.25, 3.75]])
        rays = camera.rays(positions)
        back, depth = camera.project(rays.origin + 2.5 * rays.direction)
        np.testing.assert_allclose(np.asarray(back), np.asarray(positions), atol=1e-12)
        assert np.all(np.asarray(depth) > 0)
        reference = rt.shading.pinhole_rays(7, 5, eye=(0.3, 1.0, 4.0), target=(0.0, -0.2, 0.1), fov_degrees=50.0)
        centres = camera.rays(jnp.stack(jnp.meshgrid(jnp.arange(7) + 0.5, jnp.arange(5) + 0.5), -1))
        np.testing.assert_allclose(np.asarray(centres.direction), np.asarray(reference.direction), atol=1e-6)


def test_silhouette_mesh_edges_and_errors():
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    mesh = rt.SilhouetteMesh(vertices, faces)
    assert mesh.edges.shape == (5, 2)
    assert int(np.sum(np.asarray(mesh.always))) == 4  # the four boundary edges; the diagonal is shared
    assert int(np.sum(np.asarray(rt.SilhouetteMesh(vertices, faces, all_edges=True).always))) == 5
    with pytest.raises(ValueError, match="indices must be in"):
        rt.SilhouetteMesh(vertices, faces + 2)
    with pytest.raises(ValueError, match="vertices must have shape"):
        rt.SilhouetteMesh(vertices[:, :2], faces)
    with pytest.raises(ValueError, match="transform must have shape"):
        rt.SilhouetteMesh(vertices, faces, transform=np.eye(3))
    with pytest.raises(ValueError, match="width must be a positive int"):
        rt.PinholeCamera(0, 4, eye=(0, 0, 1), target=(0, 0, 0))
    with pytest.raises(ValueError, match="eye must have shape"):
        rt.PinholeCamera(4, 4, eye=(0, 1), target=(0, 0, 0))
    camera = rt.PinholeCamera(4, 4, eye=(0, 0, 1), target=(0, 0, 0))
    with pytest.raises(ValueError, match="no trace function"):
        rt.pixel_integral(lambda r: r.direction[:, 0], camera, jax.random.key(0), lights=[rt.DirectionalLight(1)])
    with pytest.raises(ValueError, match="edge_samples must be an int >= 0"):
        rt.pixel_integral(lambda r: r.direction[:, 0], camera, jax.random.key(0), edge_samples=-1)
    with pytest.raises(ValueError, match="meshes is empty"):
        rt.pixel_integral(lambda r: r.direction[:, 0], camera, jax.random.key(0), edge_samples=16)
