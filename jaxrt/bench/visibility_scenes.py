"""Small scenes whose pixel integrals are known exactly, for checking visibility-aware gradients.

Every scene is a few flat-shaded triangles seen by a 16 x 16 pinhole camera, with shading that is constant
(or affine in the image plane) on each visible region, so that each pixel's integral is a sum of areas of
convex polygons (clipped with Sutherland-Hodgman) times the shading at their centroids: float64, exact up to
rounding. Central differences of these exact images are the reference that the estimator's gradients are
compared with (``tests/test_visibility_gradients.py``, ``python -m jaxrt.bench.visibility``).

Scenes (parameters in brackets):

- ``silhouette``: an octahedron (colour 1) against the background (0.2) [vertex offsets, translation,
  rotation];
- ``occlusion``: an octahedron in front of a triangle whose shading varies with its barycentrics, part of
  whose outline the octahedron hides [octahedron translation and rotation, the triangle's x, y vertices, a
  translation of the camera (eye and target)];
- ``shadow``: an octahedron above a ground plane that fills the image, lit by a directional light: its shadow
  edge on the plane is secondary visibility [vertex offsets, translation, rotation];
- ``shadow_point``: the same lit by a point light [vertex offsets, translation, rotation, the light's
  position];
- ``instanced_far``: an octahedron with one colour per face (every edge a discontinuity), placed by an
  ``rt.Instances`` transform 3,700 units from the origin, camera with it [the instance's rotation and
  translation, object-space vertex offsets].
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt

SIZE = 16
OCTAHEDRON = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
OCTAHEDRON_FACES = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int32
)
FACE_COLOURS = np.array([0.9, 0.7, 0.5, 0.35, 0.6, 0.8, 0.45, 1.0])
FAR = np.array([3000.0, -1000.0, 2000.0])


def rotation_matrix(rotation):
    """Rodrigues' formula (numpy or jax arrays), smooth at the zero rotation."""
    xp = jnp if isinstance(rotation, jax.Array) else np
    angle = xp.sqrt(xp.sum(rotation**2) + 1e-30)
    k = xp.array([[0.0, -rotation[2], rotation[1]], [rotation[2], 0.0, -rotation[0]], [-rotation[1], rotation[0], 0.0]])
    a = xp.sinc(angle / np.pi)
    b = 0.5 * xp.sinc(angle / (2 * np.pi)) ** 2
    return xp.eye(3) + a * k + b * (k @ k)


# ---------------------------------------------------------------- exact pixel integrals (numpy, float64)


@dataclasses.dataclass(frozen=True)
class Camera:
    eye: np.ndarray
    target: np.ndarray
    fov_degrees: float = 40.0
    up: tuple = (0.0, 1.0, 0.0)

    def jax(self) -> rt.PinholeCamera:
        return rt.PinholeCamera(SIZE, SIZE, eye=self.eye, target=self.target, up=self.up, fov_degrees=self.fov_degrees)

    def frame(self):
        forward = self.target - self.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        right /= np.linalg.norm(right)
        return forward, right, np.cross(right, forward), np.tan(np.radians(self.fov_degrees) / 2)

    def project(self, points: np.ndarray) -> np.ndarray:
        forward, right, up, scale = self.frame()
        d = points - self.eye
        z = d @ forward
        return np.stack([(d @ right / z / scale + 1) * SIZE / 2, (1 - d @ up / z / scale) * SIZE / 2], -1)

    def ray(self, x: np.ndarray) -> np.ndarray:
        forward, right, up, scale = self.frame()
        px = (2 * x[..., 0] / SIZE - 1) * scale
        py = (1 - 2 * x[..., 1] / SIZE) * scale
        return forward + px[..., None] * right + py[..., None] * up


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _oriented(poly: np.ndarray) -> np.ndarray:
    return poly if _area(poly) >= 0 else poly[::-1]


def _turn(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def hull(points: np.ndarray) -> np.ndarray:
    """Convex hull (monotone chain), positive orientation."""
    pts = sorted(map(tuple, points))

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2 and _turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return _oriented(np.array(lower[:-1] + upper[:-1]))


def clip(poly: np.ndarray, clipper: np.ndarray) -> np.ndarray:
    """``poly`` clipped by the convex ``clipper`` (both positively oriented): Sutherland-Hodgman."""
    out = poly
    for i in range(len(clipper)):
        if len(out) == 0:
            break
        a, b = clipper[i], clipper[(i + 1) % len(clipper)]
        edge = b - a
        side = edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0])
        result = []
        for j in range(len(out)):
            p, q, sp, sq = out[j], out[(j + 1) % len(out)], side[j], side[(j + 1) % len(out)]
            if sp >= 0:
                result.append(p)
            if (sp >= 0) != (sq >= 0):
                result.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(result).reshape(-1, 2)
    return out


def _centroid(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = cross.sum() / 2
    return np.array([((x + np.roll(x, -1)) * cross).sum(), ((y + np.roll(y, -1)) * cross).sum()]) / (6 * a)


def integrate(poly: np.ndarray, value: Callable[[np.ndarray], float] | float) -> np.ndarray:
    """``(SIZE, SIZE)``: each pixel's integral over ``poly`` of ``value`` (a constant, or a function of the
    image position that is affine there: its value at the clipped piece's centroid times its area)."""
    image = np.zeros((SIZE, SIZE))
    if len(poly) < 3 or _area(poly) <= 0:
        return image
    lo, hi = np.floor(poly.min(0)).astype(int), np.floor(poly.max(0)).astype(int)
    for row in range(max(lo[1], 0), min(hi[1], SIZE - 1) + 1):
        for col in range(max(lo[0], 0), min(hi[0], SIZE - 1) + 1):
            square = np.array([[col, row], [col, row + 1], [col + 1, row + 1], [col + 1, row]], np.float64)
            piece = clip(poly, _oriented(square))
            if len(piece) < 3:
                continue
            area = _area(piece)
            if area <= 0:
                continue
            image[row, col] = area * (value if np.isscalar(value) else value(_centroid(piece)))
    return image


def _front_faces(world: np.ndarray, eye: np.ndarray) -> list[int]:
    """Faces of a convex mesh (outward orientation fixed here) that face ``eye``."""
    centre = world.mean(0)
    front = []
    for f, (i, j, k) in enumerate(OCTAHEDRON_FACES):
        n = np.cross(world[j] - world[i], world[k] - world[i])
        c = (world[i] + world[j] + world[k]) / 3
        if np.dot(n, c - centre) < 0:
            n = -n
        if np.dot(n, eye - c) > 0:
            front.append(f)
    return front


# ---------------------------------------------------------------- scenes


@dataclasses.dataclass(frozen=True)
class Scene:
    """A scene: its parameters, the estimator's image and the exact image of the same parameters."""

    name: str
    params: dict  # name -> float64 numpy array (the point where gradients are taken)
    camera: Camera
    render: Callable  # (params (jax), key, samples_per_pixel, edge_samples, shadow_edge_samples) -> image
    exact: Callable  # params (numpy) -> (SIZE, SIZE) image

    def weights(self) -> np.ndarray:
        """The loss ``sum(weights * image)``: smooth, uneven pixel weights."""
        rows, cols = np.mgrid[0:SIZE, 0:SIZE]
        return 1.0 + 0.5 * np.sin(0.7 * cols) * np.cos(0.5 * rows) + 0.3 * cols / SIZE


def _posed(params, base):
    """World vertices: ``base + offsets`` rotated about their centre and translated."""
    xp = jnp if isinstance(params["translation"], jax.Array) else np
    local = base + params["vertices"]
    centre = xp.asarray(base).mean(0)
    return (local - centre) @ rotation_matrix(params["rotation"]).T + centre + params["translation"]


def _silhouette() -> Scene:
    base = 0.55 * OCTAHEDRON + np.array([0.1, -0.05, 0.0])
    camera = Camera(np.array([0.0, 0.0, 3.0]), np.zeros(3))
    params = {
        "vertices": np.zeros((6, 3)),
        "translation": np.array([0.05, 0.02, 0.1]),
        "rotation": np.array([0.3, 0.4, 0.1]),
    }
    intersector = rt.Intersector()

    def render(p, key, spp, edges, shadows):
        v = _posed(p, base)
        s = rt.build_primitive_structure(rt.TriangleGeometry(v, OCTAHEDRON_FACES))

        def shade(rays):
            return jnp.where(intersector.intersect(rays, s).type != 0, 1.0, 0.2)

        mesh = rt.SilhouetteMesh(v, OCTAHEDRON_FACES)
        return rt.pixel_integral(shade, camera.jax(), key, samples_per_pixel=spp, meshes=[mesh], edge_samples=edges)

    def exact(p):
        return 0.2 + integrate(hull(camera.project(_posed(p, base))), 0.8)

    return Scene("silhouette", params, camera, render, exact)


def _occlusion() -> Scene:
    base = 0.35 * OCTAHEDRON + np.array([0.35, 0.25, 0.6])
    camera = base_camera = Camera(np.array([0.0, 0.0, 3.0]), np.zeros(3))
    back = np.array([[-0.9, -0.8, -0.5], [0.9, -0.4, -0.5], [0.2, 0.9, -0.5]])
    params = {
        "translation": np.array([0.0, 0.0, 0.0]),
        "rotation": np.array([0.2, -0.3, 0.5]),
        "back_xy": np.zeros((3, 2)),
        "vertices": np.zeros((6, 3)),
        "camera": np.array([0.02, -0.03, 0.1]),  # moves the eye and the target (the view stays along -z)
    }
    intersector = rt.Intersector(rt.tags.triangle_data)
    faces = np.concatenate([OCTAHEDRON_FACES, np.array([[6, 7, 8]])])

    def back_vertices(p):
        xp = jnp if isinstance(p["back_xy"], jax.Array) else np
        return back + xp.concatenate([p["back_xy"], xp.zeros((3, 1))], axis=1)

    def render(p, key, spp, edges, shadows):
        v = jnp.concatenate([_posed(p, base), back_vertices(p)])
        s = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))

        def shade(rays):
            hits = intersector.intersect(rays, s)
            u, w = hits.triangle_barycentric_coord[..., 0], hits.triangle_barycentric_coord[..., 1]
            value = jnp.where(hits.primitive_id == 8, 0.3 + 0.5 * u + 0.2 * w, 0.9)
            return jnp.where(hits.type != 0, value, 0.1)

        mesh = rt.SilhouetteMesh(v, faces)
        moved = rt.PinholeCamera(
            SIZE, SIZE, eye=camera.eye + p["camera"], target=camera.target + p["camera"], fov_degrees=camera.fov_degrees
        )
        return rt.pixel_integral(shade, moved, key, samples_per_pixel=spp, meshes=[mesh], edge_samples=edges)

    def exact(p):
        camera = Camera(base_camera.eye + p["camera"], base_camera.target + p["camera"])
        b = back_vertices(p)
        front = hull(camera.project(_posed(p, base)))
        behind = _oriented(camera.project(b))

        def shading(x):  # on the (fronto-parallel) back triangle: affine in the image position
            d = camera.ray(x)
            point = camera.eye + d * (b[0, 2] - camera.eye[2]) / d[2]
            m = np.stack([b[1] - b[0], b[2] - b[0]], 1)[:2]
            u, w = np.linalg.solve(m, (point - b[0])[:2])
            return 0.3 + 0.5 * u + 0.2 * w - 0.1

        hidden = clip(behind, front)
        return 0.1 + integrate(behind, shading) - integrate(hidden, shading) + integrate(front, 0.8)

    return Scene("occlusion", params, camera, render, exact)


LIGHT = np.array([0.4, 1.0, 0.3]) / np.linalg.norm([0.4, 1.0, 0.3])
GROUND = -0.6
LIGHT_POSITION = np.array([0.5, 1.4, 0.4])


def _shadow(point: bool = False) -> Scene:
    base = 0.3 * OCTAHEDRON + np.array([0.0, -0.1, 0.0])
    camera = Camera(np.array([0.0, 1.2, 2.2]), np.array([0.0, GROUND, 0.0]))
    plane = np.array([[-20, GROUND, -20], [20, GROUND, -20], [20, GROUND, 20], [-20, GROUND, 20]], np.float64)
    params = {
        "vertices": np.zeros((6, 3)),
        "translation": np.array([0.05, 0.0, -0.05]),
        "rotation": np.array([0.2, 0.5, -0.1]),
    }
    if point:
        params["light"] = LIGHT_POSITION.copy()
    faces = np.concatenate([OCTAHEDRON_FACES, np.array([[6, 8, 7], [6, 9, 8]])])
    intersector = rt.Intersector()
    occluded = rt.Intersector(accept_any_intersection=True)

    def render(p, key, spp, edges, shadows):
        v = jnp.concatenate([_posed(p, base), jnp.asarray(plane)])
        s = rt.build_primitive_structure(rt.TriangleGeometry(v, faces))

        def shade(rays):
            hits = intersector.intersect(rays, s)
            on_plane = hits.primitive_id >= 8
            x = rays.origin + jnp.where(hits.type != 0, hits.distance, 0.0)[:, None] * rays.direction
            mask = jnp.where(on_plane, 0xFF, 0)
            if point:  # towards the light, up to it
                shadow_rays = rt.Ray(x, p["light"] - x, 1e-6, 1.0, mask)
            else:
                shadow_rays = rt.Ray(x, jnp.broadcast_to(jnp.asarray(LIGHT), x.shape), 1e-6, jnp.inf, mask)
            lit = occluded.intersect(shadow_rays, s).type == 0
            return jnp.where(on_plane, jnp.where(lit, 0.8, 0.3), jnp.where(hits.type != 0, 1.0, 0.0))

        mesh = rt.SilhouetteMesh(_posed(p, base), OCTAHEDRON_FACES)
        light = rt.PointLight(p["light"]) if point else rt.DirectionalLight(jnp.asarray(LIGHT))
        return rt.pixel_integral(
            shade,
            camera.jax(),
            key,
            samples_per_pixel=spp,
            meshes=[mesh],
            edge_samples=edges,
            lights=[light],
            shadow_edge_samples_per_light=shadows,
            trace=lambda rays: intersector.intersect(rays, s),
        )

    def exact(p):
        v = _posed(p, base)
        front = hull(camera.project(v))
        if point:
            light = p["light"]
            on_ground = light + (v - light) * ((GROUND - light[1]) / (v[:, 1] - light[1]))[:, None]
        else:
            on_ground = v - ((v[:, 1] - GROUND) / LIGHT[1])[:, None] * LIGHT
        shadow = hull(camera.project(on_ground))
        both = clip(shadow, front)
        return 0.8 + integrate(front, 0.2) + integrate(shadow, -0.5) - integrate(both, -0.5)

    return Scene("shadow_point" if point else "shadow", params, camera, render, exact)


def _instanced_far() -> Scene:
    base = 0.5 * OCTAHEDRON
    camera = Camera(FAR + np.array([0.3, 0.4, 3.0]), FAR + np.array([0.0, 0.1, 0.0]))
    params = {
        "rotation": np.array([0.4, -0.2, 0.3]),
        "translation": np.array([0.1, 0.05, 0.0]),
        "vertices": np.zeros((6, 3)),
    }
    intersector = rt.Intersector(rt.tags.instancing)
    colours = FACE_COLOURS

    def transform(p):
        xp = jnp if isinstance(p["rotation"], jax.Array) else np
        return xp.concatenate([rotation_matrix(p["rotation"]), (FAR + p["translation"])[:, None]], axis=1)

    def render(p, key, spp, edges, shadows):
        v = jnp.asarray(base) + p["vertices"]
        m = transform(p)
        blas = rt.build_primitive_structure(rt.TriangleGeometry(v, OCTAHEDRON_FACES))
        s = rt.build_instance_structure([blas], rt.Instances([0], m[None]))

        def shade(rays):
            hits = intersector.intersect(rays, s)
            return jnp.where(hits.type != 0, jnp.asarray(colours)[jnp.maximum(hits.primitive_id, 0)], 0.15)

        mesh = rt.SilhouetteMesh(v, OCTAHEDRON_FACES, transform=m, all_edges=True)
        return rt.pixel_integral(shade, camera.jax(), key, samples_per_pixel=spp, meshes=[mesh], edge_samples=edges)

    def exact(p):
        m = transform(p)
        world = (base + p["vertices"]) @ m[:, :3].T + m[:, 3]
        image = np.full((SIZE, SIZE), 0.15)
        for f in _front_faces(world, camera.eye):
            image += integrate(_oriented(camera.project(world[OCTAHEDRON_FACES[f]])), colours[f] - 0.15)
        return image

    return Scene("instanced_far", params, camera, render, exact)


def scenes() -> dict[str, Scene]:
    """Every scene by name."""
    return {s.name: s for s in (_silhouette(), _occlusion(), _shadow(), _shadow(point=True), _instanced_far())}


def flatten(params: dict) -> tuple[np.ndarray, Callable[[np.ndarray], dict]]:
    """The parameters as one vector, and the map back (numpy)."""
    names = sorted(params)  # jax's order of dict keys
    shapes = [np.shape(params[n]) for n in names]
    sizes = [int(np.prod(s)) for s in shapes]
    vector = np.concatenate([np.ravel(params[n]) for n in names])

    def unflatten(x):
        out, start = {}, 0
        for n, shape, size in zip(names, shapes, sizes, strict=True):
            out[n] = x[start : start + size].reshape(shape)
            start += size
        return out

    return vector, unflatten


def exact_gradient(scene: Scene, step: float = 1e-6) -> dict:
    """Central differences of ``sum(weights * exact image)`` with respect to every parameter."""
    weights = scene.weights()
    vector, unflatten = flatten(scene.params)
    grad = np.zeros_like(vector)
    for i in range(len(vector)):
        up, down = vector.copy(), vector.copy()
        up[i] += step
        down[i] -= step
        grad[i] = (np.sum(weights * scene.exact(unflatten(up))) - np.sum(weights * scene.exact(unflatten(down)))) / (
            2 * step
        )
    return unflatten(grad)


def estimator_gradient(scene: Scene, key, samples_per_pixel: int, edge_samples: int, shadow_edge_samples: int = 0):
    """``jax.grad`` of ``sum(weights * pixel_integral image)`` (a jitted function of the parameters and key)."""
    weights = jnp.asarray(scene.weights())

    def loss(p, k):
        return jnp.sum(weights * scene.render(p, k, samples_per_pixel, edge_samples, shadow_edge_samples))

    return jax.jit(jax.grad(loss))
