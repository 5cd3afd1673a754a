"""Result fields: the smooth re-intersection only under differentiation, in forward and reverse mode alike."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt


def _scene():
    rng = np.random.default_rng(0)
    centre = rng.uniform(-1.0, 1.0, (24, 1, 3))
    vertices = (centre + 0.4 * rng.standard_normal((24, 3, 3))).reshape(-1, 3).astype(np.float32)
    origin = np.tile(np.float32([[0.0, 0.0, -4.0]]), (64, 1))
    target = rng.uniform(-1.0, 1.0, (64, 3)).astype(np.float32)
    return jnp.asarray(vertices), rt.Ray(origin, target - origin)


def test_forward_mode_equals_reverse_mode():
    vertices, rays = _scene()
    intersector = rt.Intersector(rt.tags.triangle_data, backend="portable")

    def fields(v):
        hit = intersector.intersect(rays, rt.build_primitive_structure(rt.TriangleGeometry(v)))
        found = hit.type != 0
        u = hit.triangle_barycentric_coord
        return jnp.stack([jnp.sum(jnp.where(found, hit.distance, 0.0)), jnp.sum(u[:, 0] + 2 * u[:, 1])])

    # Each mode as one compiled program (eagerly, each operation of the build and its derivatives compiles on
    # its own).
    forward = jax.jit(jax.jacfwd(fields))(vertices)
    reverse = jax.jit(jax.jacrev(fields))(vertices)
    np.testing.assert_allclose(forward, reverse, rtol=1e-5, atol=1e-6)
    assert np.abs(np.asarray(forward)).sum() > 0
    # The values do not depend on the mode: the exact ones of the traversal's test.
    np.testing.assert_array_equal(jax.jit(fields)(vertices), fields(vertices))


def test_geometry_id_of_one_and_several_geometries():
    vertices, rays = _scene()
    one = rt.build_primitive_structure(rt.TriangleGeometry(vertices))
    two = rt.build_primitive_structure([rt.TriangleGeometry(vertices[:36]), rt.TriangleGeometry(vertices[36:])])
    intersector = rt.Intersector(backend="portable")
    a, b = intersector.intersect(rays, one), intersector.intersect(rays, two)
    assert a.geometry_id.dtype == b.geometry_id.dtype == jnp.int32
    np.testing.assert_array_equal(a.geometry_id, np.where(np.asarray(a.type) != 0, 0, -1))
    hit = np.asarray(b.type) != 0
    assert set(np.asarray(b.geometry_id)[hit]) == {0, 1}
    np.testing.assert_array_equal(np.asarray(b.geometry_id)[~hit], -1)
    np.testing.assert_array_equal(
        np.asarray(a.primitive_id),
        np.asarray(b.primitive_id) + 12 * np.asarray(b.geometry_id) * (np.asarray(b.geometry_id) > 0),
    )
