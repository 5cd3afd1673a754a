"""The shading helpers of ``rt.shading``: values against closed forms, gradients, jit and vmap.

The traced helpers (ambient occlusion, the one-bounce estimator) use one scene shape (two quads, 4 triangles)
and one point count, so their traversals compile once for the module.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxrt as rt

shading = rt.shading


def icosahedron() -> tuple[np.ndarray, np.ndarray]:
    """The regular icosahedron (outward winding): by symmetry its smooth vertex normals are radial."""
    t = (1.0 + 5.0**0.5) / 2.0
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t]]
        + [[t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
        np.float32,
    )
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2]]
    f += [[10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11]]
    f += [[6, 2, 10], [8, 6, 7], [9, 8, 1]]
    return v, np.array(f, np.int32)


def test_vertex_normals_are_radial_on_the_icosahedron_and_differentiable():
    vertices, faces = icosahedron()
    normals = shading.vertex_normals(vertices, faces)
    radial = vertices / np.linalg.norm(vertices, axis=-1, keepdims=True)
    np.testing.assert_allclose(normals, radial, atol=1e-6)
    with jax.enable_x64(True):
        check_grads(
            jax.jit(lambda v: shading.vertex_normals(v, faces)), (vertices.astype(np.float64),), order=1, modes="rev"
        )


def test_interpolate_matches_numpy_and_gives_zero_for_misses():
    rng = np.random.default_rng(0)
    vertices, faces = icosahedron()
    attribute = rng.normal(size=(12, 2)).astype(np.float32)
    primitive = np.array([0, 7, -1, 19, -1])
    bary = rng.uniform(0, 0.5, (5, 2)).astype(np.float32)
    got = shading.interpolate(attribute, faces, primitive, bary)
    corners = attribute[faces[np.maximum(primitive, 0)]]
    weights = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], -1)
    expected = np.where((primitive >= 0)[:, None], np.einsum("nk,nkc->nc", weights, corners), 0.0)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)
    scalar = shading.interpolate(attribute[:, 0], faces, primitive, bary)
    np.testing.assert_allclose(scalar, expected[:, 0], rtol=1e-6, atol=1e-6)
    # At a vertex the attribute is that vertex's value.
    at_v1 = shading.interpolate(attribute, faces, np.array([3]), np.array([[1.0, 0.0]]))
    np.testing.assert_allclose(at_v1[0], attribute[faces[3, 1]], rtol=1e-6)
    with jax.enable_x64(True):
        check_grads(
            jax.jit(lambda a, b: shading.interpolate(a, faces, primitive, b)),
            (attribute.astype(np.float64), bary.astype(np.float64)),
            order=1,
        )
        gradient = jax.grad(lambda b: shading.interpolate(attribute, faces, primitive, b).sum())(bary)
        assert (np.asarray(gradient)[primitive < 0] == 0).all()


def test_interpolate_normals_are_unit_and_zero_without_nan_for_misses():
    vertices, faces = icosahedron()
    normals = shading.vertex_normals(vertices, faces)
    primitive = np.array([2, -1, 11])
    bary = np.array([[0.2, 0.3], [0.0, 0.0], [0.5, 0.5]], np.float32)
    got = np.asarray(shading.interpolate_normals(normals, faces, primitive, bary))
    np.testing.assert_allclose(np.linalg.norm(got[[0, 2]], axis=-1), 1.0, rtol=1e-6)
    assert (got[1] == 0).all()
    gradient = jax.grad(lambda n, b: shading.interpolate_normals(n, faces, primitive, b).sum(), argnums=(0, 1))
    for g in gradient(normals, bary):
        assert np.isfinite(np.asarray(g)).all()


def test_texture_lookup_is_bilinear_with_clamped_edges():
    texture = np.arange(12, dtype=np.float32).reshape(3, 4)
    centres = np.array([[(c + 0.5) / 4, (r + 0.5) / 3] for r in range(3) for c in range(4)], np.float32)
    np.testing.assert_allclose(shading.texture_lookup(texture, centres), texture.reshape(-1), atol=1e-5)
    between = shading.texture_lookup(texture, np.array([[0.25, 0.5], [0.5, 1.0 / 3.0]], np.float32))
    np.testing.assert_allclose(between, [texture[1, :2].mean(), texture[:2, 1:3].mean()], atol=1e-5)
    outside = shading.texture_lookup(texture, np.array([[-1.0, -1.0], [2.0, 2.0]], np.float32))
    np.testing.assert_allclose(outside, [texture[0, 0], texture[-1, -1]])
    colour = np.stack([texture, -texture], -1)
    assert shading.texture_lookup(colour, centres).shape == (12, 2)
    with jax.enable_x64(True):
        uv = np.array([[0.3, 0.4], [0.71, 0.2]])
        check_grads(jax.jit(shading.texture_lookup), (texture.astype(np.float64), uv), order=1)


def test_face_forward_flips_towards_the_viewer():
    normals = jnp.array([[0.0, 0, 1], [0, 0, 1]])
    directions = jnp.array([[0.0, 0, -1], [0, 0.1, 1]])
    np.testing.assert_array_equal(shading.face_forward(normals, directions), [[0, 0, 1], [0, 0, -1]])


@pytest.mark.parametrize("model", [shading.phong, shading.blinn_phong])
def test_phong_models_closed_forms_and_gradients(model):
    n = jnp.array([0.0, 0.0, 1.0])
    # Light and viewer along the normal: diffuse 1, specular lobe 1.
    assert float(model(n, n, n, albedo=0.5, specular=0.25, shininess=8.0)) == pytest.approx(0.75)
    # Light below the horizon: nothing, and no specular either.
    assert float(model(n, -n, n, albedo=1.0, specular=1.0)) == 0.0
    # Mirror configuration at 45 degrees: Phong's lobe is 1; Blinn-Phong's half vector is the normal.
    light, view = jnp.array([1.0, 0, 1]), jnp.array([-1.0, 0, 1])
    value = float(model(n, light, view, albedo=1.0, specular=1.0, shininess=50.0))
    assert value == pytest.approx(1.0 + 2**-0.5, rel=1e-5)

    # Gradients are finite everywhere, including where the lobe is exactly 0 (w.r.t. the shininess too).
    def shade(normal, shininess):
        return model(normal, light, jnp.array([1.0, 0, 1]), albedo=0.7, specular=0.3, shininess=shininess)

    normals = jnp.array([[0.0, 0, 1], [0, 0.6, 0.8], [-1.0, 0, 0], [1.0, 0, 0]])
    gradients = jax.vmap(jax.grad(shade, argnums=(0, 1)), in_axes=(0, None))(normals, 16.0)
    for g in gradients:
        assert np.isfinite(np.asarray(g)).all()
    assert float(gradients[1][2]) == 0.0  # light behind the surface: constant 0
    with jax.enable_x64(True):
        check_grads(jax.jit(shade), (jnp.array([0.1, 0.2, 0.97]), 16.0), order=1)
    assert float(jax.jit(shade)(normals[0], 4.0)) == pytest.approx(float(shade(normals[0], 4.0)))


def test_lambert_keeps_its_signature():
    normals = jnp.array([[0.0, 0, 1], [0, 0, -1]])
    np.testing.assert_allclose(shading.lambert(normals, [0.0, 0, 2], albedo=0.5), [0.5, 0.0])


def test_pinhole_rays_jitter_stays_inside_the_pixel():
    width, height = 8, 6
    camera = dict(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), fov_degrees=40.0)
    rays = jax.jit(lambda key: shading.pinhole_rays(width, height, key=key, **camera))
    centre = jax.jit(lambda: shading.pinhole_rays(width, height, **camera))()
    key = jax.random.key(3)
    jittered, again = rays(key), rays(key)
    np.testing.assert_array_equal(jittered.direction, again.direction)  # a fixed key, a fixed pattern
    np.testing.assert_allclose(np.linalg.norm(jittered.direction, axis=-1), 1.0, rtol=1e-6)

    # Image-plane coordinates at distance 1: within half a pixel of the centre, and not all at the centre.
    def plane(d):
        return np.asarray(d[..., :2] / -d[..., 2:])

    pixel = 2.0 * np.tan(np.deg2rad(40.0) / 2) / height
    offset = np.abs(plane(jittered.direction) - plane(centre.direction)) / pixel
    assert offset.max() <= 0.5 + 1e-4 and offset.mean() > 0.1
    # Rays are differentiable with respect to the camera.
    grad = jax.jit(jax.grad(lambda eye: shading.pinhole_rays(4, 4, eye=eye, target=(0.0, 0, 0)).direction.sum()))
    assert np.isfinite(np.asarray(grad(jnp.array([0.0, 1.0, 5.0])))).all()


# Two quads as one geometry: the floor y = 0 over [-1, 1]^2 (facing up) and a second quad, either a wall
# x = 0.5 facing -x or the same quad far below the floor (out of the floor's upper hemisphere).
FLOOR = [[-1, 0, -1], [-1, 0, 1], [1, 0, 1], [1, 0, -1]]
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]], np.int32)
WALL = [[0.5, 0, -1], [0.5, 0, 1], [0.5, 2, 1], [0.5, 2, -1]]
BELOW = [[-1, -5, -1], [-1, -5, 1], [-1, -7, 1], [-1, -7, -1]]
LIGHT = np.array([-1.0, 1.0, 0.0]) / np.sqrt(2.0)


def two_quads(second) -> tuple[np.ndarray, rt.PrimitiveAccelerationStructure]:
    vertices = np.array(FLOOR + second, np.float32)
    return vertices, rt.build_primitive_structure(rt.TriangleGeometry(vertices, QUAD_FACES))


def floor_points() -> tuple[jax.Array, jax.Array]:
    x, z = np.meshgrid(np.linspace(-0.8, 0.3, 4), np.linspace(-0.5, 0.5, 4), indexing="ij")
    points = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3).astype(np.float32)
    return jnp.asarray(points), jnp.broadcast_to(jnp.array([0.0, 1.0, 0.0]), points.shape)


def test_one_bounce_diffuse_in_the_open_is_direct_light_plus_sky():
    vertices, structure = two_quads(BELOW)
    points, normals = floor_points()
    key = jax.random.key(0)
    irradiance, sky = 2.0, 0.25
    value = shading.one_bounce_diffuse(
        key,
        structure,
        vertices,
        QUAD_FACES,
        points,
        normals,
        light_direction=LIGHT,
        light_irradiance=irradiance,
        sky=sky,
    )
    expected = irradiance / np.pi * LIGHT[1] + sky  # every bounce ray escapes to the sky
    np.testing.assert_allclose(value, expected, rtol=1e-5)
    visibility = shading.ambient_occlusion(key, structure, points, normals, samples=8)
    np.testing.assert_array_equal(visibility, 1.0)


def test_one_bounce_diffuse_near_a_wall_adds_its_light_and_is_differentiable():
    vertices, structure = two_quads(WALL)
    points, normals = floor_points()
    key = jax.random.key(0)
    common = dict(light_direction=LIGHT, samples=4)

    def estimate(albedo, irradiance):
        return shading.one_bounce_diffuse(
            key, structure, vertices, QUAD_FACES, points, normals, albedo=albedo, light_irradiance=irradiance, **common
        )

    direct = estimate(0.0, 1.0)
    np.testing.assert_allclose(direct, LIGHT[1] / np.pi, rtol=1e-5)  # the floor is lit, nothing shadows it
    lit = estimate(0.8, 1.0)
    assert (lit >= direct).all() and (lit > direct + 1e-3).any()  # the lit wall adds light to the floor
    occluded = shading.ambient_occlusion(key, structure, points, normals, samples=8)
    assert (occluded < 1).any()

    # Affine in the albedo, linear in the irradiance: gradients equal the differences exactly.
    gradient = jax.jit(jax.grad(lambda a, e: estimate(a, e).sum(), argnums=(0, 1)))(0.5, 1.5)
    np.testing.assert_allclose(gradient[0], 1.5 * (lit - direct).sum() / 0.8, rtol=1e-4)
    np.testing.assert_allclose(gradient[1], estimate(0.5, 1.0).sum(), rtol=1e-4)

    # Per-vertex albedo, constant, equals the constant; colours give a channel axis.
    per_vertex = shading.one_bounce_diffuse(
        key, structure, vertices, QUAD_FACES, points, normals, vertex_albedo=jnp.full(8, 0.8), **common
    )
    np.testing.assert_allclose(per_vertex, lit, rtol=1e-5)
    colour = shading.one_bounce_diffuse(
        key,
        structure,
        vertices,
        QUAD_FACES,
        points,
        normals,
        albedo=0.8,
        light_irradiance=jnp.array([1.0, 2.0]),
        **common,
    )
    np.testing.assert_allclose(colour, np.stack([lit, 2 * lit], -1), rtol=1e-5)

    # Invalid points trace nothing and return 0.
    valid = jnp.arange(16) % 2 == 0
    masked = shading.one_bounce_diffuse(
        key, structure, vertices, QUAD_FACES, points, normals, albedo=0.8, valid=valid, **common
    )
    np.testing.assert_allclose(masked, jnp.where(valid, lit, 0.0), rtol=1e-5)


def test_one_bounce_diffuse_rejects_several_geometries():
    vertices, _ = two_quads(WALL)
    structure = rt.build_primitive_structure(
        [rt.TriangleGeometry(vertices, QUAD_FACES[:2]), rt.TriangleGeometry(vertices, QUAD_FACES[2:])]
    )
    points, normals = floor_points()
    with pytest.raises(ValueError, match="one geometry"):
        shading.one_bounce_diffuse(
            jax.random.key(0), structure, vertices, QUAD_FACES, points, normals, light_direction=LIGHT
        )


def _two_geometries():
    """Two meshes whose triangle 0 differ: a hit on geometry 1 must not read geometry 0's triangle."""
    a_vertices, a_faces = icosahedron()
    rng = np.random.default_rng(5)
    b_vertices = (a_vertices @ np.linalg.qr(rng.normal(size=(3, 3)))[0] + [4.0, 0, 0]).astype(np.float32)
    b_faces = a_faces[::-1].copy()
    return (a_vertices, a_faces), (b_vertices, b_faces)


def test_helpers_read_each_hits_own_geometry():
    (av, af), (bv, bf) = _two_geometries()
    structure = rt.build_primitive_structure([rt.TriangleGeometry(av, af), rt.TriangleGeometry(bv, bf)])
    rng = np.random.default_rng(6)
    target = np.concatenate([np.zeros((32, 3)), np.tile([4.0, 0, 0], (32, 1))]) + rng.normal(scale=0.3, size=(64, 3))
    direction = rng.normal(size=(64, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    rays = rt.Ray(jnp.asarray(target - 5 * direction, jnp.float32), jnp.asarray(direction, jnp.float32))
    hit = rt.Intersector(rt.tags.triangle_data).intersect(rays, structure)
    g, p = np.asarray(hit.geometry_id), np.asarray(hit.primitive_id)
    assert (g == 0).sum() > 10 and (g == 1).sum() > 10
    # float64 reference: each hit's own triangle.
    tri = np.where((g == 1)[:, None, None], bv.astype(np.float64)[bf[p]], av.astype(np.float64)[af[p]])
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    expected = np.where((g >= 0)[:, None], n / np.linalg.norm(n, axis=1, keepdims=True), 0.0)
    got = shading.triangle_normals([av, bv], [af, bf], hit.primitive_id, hit.geometry_id)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    # Interpolating the positions gives the hit points (a per-geometry attribute read by geometry_id).
    points = shading.interpolate([av, bv], [af, bf], hit.primitive_id, hit.triangle_barycentric_coord, hit.geometry_id)
    hits = g >= 0
    np.testing.assert_allclose(np.asarray(points)[hits], np.asarray(shading.hit_points(rays, hit))[hits], atol=1e-4)
    smooth = shading.interpolate_normals(
        [shading.vertex_normals(av, af), shading.vertex_normals(bv, bf)],
        [af, bf],
        hit.primitive_id,
        hit.triangle_barycentric_coord,
        hit.geometry_id,
    )
    assert np.allclose(np.linalg.norm(np.asarray(smooth)[hits], axis=1), 1.0, atol=1e-5)
    # Under jit (no value check) the result is the same.
    jitted = jax.jit(shading.triangle_normals)([av, bv], [af, bf], hit.primitive_id, hit.geometry_id)
    np.testing.assert_allclose(jitted, expected, atol=1e-6)


def test_helpers_refuse_ambiguous_geometry_ids():
    (av, af), (bv, bf) = _two_geometries()
    with pytest.raises(ValueError, match="triangle_normals: 2 geometries were given but no geometry_id"):
        shading.triangle_normals([av, bv], [af, bf], jnp.array([0]))
    with pytest.raises(ValueError, match="triangle_normals: geometry_id holds 1 but only 1 geometry was given"):
        shading.triangle_normals(av, af, jnp.array([0, 0]), jnp.array([0, 1]))
    with pytest.raises(ValueError, match="interpolate: geometry_id holds 2 but only 2 geometries"):
        shading.interpolate([av, bv], [af, bf], jnp.array([0]), jnp.zeros((1, 2)), jnp.array([2]))
    with pytest.raises(TypeError, match="interpolate_normals: give one geometry's arrays or one sequence"):
        shading.interpolate_normals([av, bv], af, jnp.array([0]), jnp.zeros((1, 2)))
    # Inside jit nothing raises: an id naming no given geometry reads as a miss.
    jitted = jax.jit(lambda g: shading.triangle_normals(av, af, jnp.array([0, 0]), g))(jnp.array([0, 1]))
    assert np.asarray(jitted)[1].tolist() == [0.0, 0.0, 0.0] and np.linalg.norm(jitted[0]) > 0.99
    # A single geometry keeps working without geometry_id.
    single = shading.triangle_normals(av, af, jnp.array([3, -1]))
    assert np.isclose(np.linalg.norm(single[0]), 1.0) and np.asarray(single[1]).tolist() == [0.0, 0.0, 0.0]


def test_hit_points_mark_misses_with_inf_and_no_nan_gradient():
    structure = rt.build_primitive_structure(rt.TriangleGeometry([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    origin = jnp.array([[0.2, 0.2, 1.0], [5, 5, 1], [0.1, 0.1, -1.0]])  # the third starts below, going away

    def points(o, **kw):
        rays = rt.Ray(o, jnp.array([[0.0, 0, -1], [0, 0, -1], [0, 0, -1]]))
        return shading.hit_points(rays, rt.Intersector().intersect(rays, structure), **kw)

    got = np.asarray(points(origin))
    np.testing.assert_allclose(got[0], [0.2, 0.2, 0.0], atol=1e-7)
    assert np.isinf(got[1:]).all() and not np.isnan(got).any()  # a miss at the origin is not the point 0
    np.testing.assert_array_equal(np.asarray(points(origin, miss_value=0.0))[1:], 0.0)
    grad = jax.grad(lambda o: jnp.sum(points(o, miss_value=0.0)))(origin)
    np.testing.assert_allclose(grad, [[1.0, 1, 0], [0, 0, 0], [0, 0, 0]], atol=1e-6)
