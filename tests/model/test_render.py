"""Renderer physics: analytic diffuse shading, mirror-geometry highlights, polarization, shadows, interpolation."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.capture.scenes import icosphere
from sellip.model.pbrdf import PBRDFParams
from sellip.model.render import (
    Camera,
    Light,
    ParamMesh,
    Renderer,
    flash_light,
    pixel_rays,
    render_stokes,
    subpixel_offsets,
)

WIDTH, HEIGHT, FOCAL = 160, 128, 1000.0
RADIUS, DISTANCE = 0.05, 0.9
FLASH_CAM = np.array([0.0, 0.05, 0.0])


def _uniform_params(count, eta=1.5, rho_d=(0.5, 0.3, 0.2), rho_s=0.0, sigma_s=0.3, rho_ss=(0.0, 0.0, 0.0),
                    sigma_ss=0.5) -> PBRDFParams:
    def full(value, channels=None):
        shape = (count,) if channels is None else (count, channels)
        return np.broadcast_to(np.asarray(value, np.float64), shape).copy()

    return PBRDFParams(eta=full(eta), rho_d=full(rho_d, 3), rho_s=full(rho_s), sigma_s=full(sigma_s),
                       rho_ss=full(rho_ss, 3), sigma_ss=full(sigma_ss))


def _sphere(subdivisions=6, **params) -> ParamMesh:
    d, faces = icosphere(subdivisions)
    return ParamMesh(vertices=RADIUS * d, faces=faces, normals=d.copy(), params=_uniform_params(len(d), **params))


def _camera() -> Camera:
    """Camera at (0, 0, -0.9) looking along +z at the sphere centred on the origin."""
    k = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
    return Camera(k, np.eye(3), np.array([0.0, 0.0, DISTANCE]), WIDTH, HEIGHT)


def _fresnel(cos_theta, eta):
    """Air-side intensity coefficients (R_s, R_p) of a dielectric, written out independently."""
    sin2 = 1 - cos_theta ** 2
    cos_t = np.sqrt(1 - sin2 / eta ** 2)
    r_s = ((cos_theta - eta * cos_t) / (cos_theta + eta * cos_t)) ** 2
    r_p = ((eta * cos_theta - cos_t) / (eta * cos_theta + cos_t)) ** 2
    return r_s, r_p


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sphere_hits(camera: Camera, pixels: np.ndarray):
    """Exact ray-sphere intersections for pixel centres (N, 2): points (N, 3) and normals (N, 3)."""
    origin = camera.center
    k = camera.intrinsics
    dirs = _unit(np.stack([(pixels[:, 0] - k[0, 2]) / k[0, 0], (pixels[:, 1] - k[1, 2]) / k[1, 1],
                           np.ones(len(pixels))], -1)) @ camera.rotation
    b = dirs @ origin
    t = -b - np.sqrt(b * b - (origin @ origin - RADIUS ** 2))
    points = origin + t[:, None] * dirs
    return points, points / RADIUS


def _disc_pixels(camera, low, high):
    """Integer pixels whose rays hit the sphere at a fraction in [low, high) of the apparent radius."""
    apparent = FOCAL * RADIUS / np.sqrt(DISTANCE ** 2 - RADIUS ** 2)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    r = np.hypot(u - camera.intrinsics[0, 2], v - camera.intrinsics[1, 2]) / apparent
    keep = (r >= low) & (r < high)
    return np.stack([u[keep], v[keep]], -1).astype(np.float64)


def test_diffuse_sphere_s0_matches_analytic_value():
    camera = _camera()
    light = flash_light(camera, FLASH_CAM)
    result = render_stokes(_sphere(eta=1.5), camera, light, supersample=1)
    pixels = _disc_pixels(camera, 0.0, 0.8)[::37]
    points, normals = _sphere_hits(camera, pixels)
    to_light = light.position - points
    dist = np.linalg.norm(to_light, axis=-1)
    to_light /= dist[:, None]
    to_camera = _unit(camera.center - points)
    cos_i, cos_o = np.sum(normals * to_light, -1), np.sum(normals * to_camera, -1)
    rs_i, rp_i = _fresnel(cos_i, 1.5)
    rs_o, rp_o = _fresnel(cos_o, 1.5)
    t_plus_i, t_minus_i = 1 - (rs_i + rp_i) / 2, -(rs_i - rp_i) / 2
    t_plus_o = 1 - (rs_o + rp_o) / 2
    # Flash light [1, 1, 0, 0] about its axis; the entry transmission's s axis is n x w_i.
    s_axis = _unit(np.cross(normals, to_light))
    axis = _unit(light.axis - np.sum(light.axis * to_light, -1, keepdims=True) * to_light)
    cos_2psi = 2 * np.sum(axis * s_axis, -1) ** 2 - 1
    expected = (cos_i / dist ** 2 * t_plus_o * (t_plus_i + t_minus_i * cos_2psi))[:, None] * np.array([0.5, 0.3, 0.2])
    rendered = result.stokes[pixels[:, 1].astype(int), pixels[:, 0].astype(int), 0, :]
    assert len(pixels) > 50
    np.testing.assert_allclose(rendered, expected, rtol=5e-3)
    assert np.all(result.stokes[0, 0] == 0)  # background is black


def _mirror_point(camera, light):
    """Point on the sphere whose normal bisects the directions to the camera and the light (Newton-free search)."""
    best = _unit(camera.center + light.position)  # start: towards the midpoint of camera and light
    for scale in (0.05, 0.005, 0.0005, 0.00005):
        offsets = np.stack(np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41)), -1).reshape(-1, 2) * scale
        tangent_a = _unit(np.cross(best, [0.0, 0.0, 1.0] if abs(best[2]) < 0.9 else [1.0, 0.0, 0.0]))
        tangent_b = np.cross(best, tangent_a)
        normals = _unit(best + offsets[:, :1] * tangent_a + offsets[:, 1:] * tangent_b)
        points = RADIUS * normals
        half = _unit(_unit(camera.center - points) + _unit(light.position - points))
        best = normals[np.argmax(np.sum(half * normals, -1))]
    return RADIUS * best


def test_highlight_lies_at_the_mirror_point_and_is_co_polarized():
    camera = _camera()
    light = flash_light(camera, FLASH_CAM)
    mesh = _sphere(eta=1.5, rho_d=(0.02, 0.02, 0.02), rho_s=1.0, sigma_s=0.05)
    result = render_stokes(mesh, camera, light, supersample=3)
    i0, i90 = result.analyzers[..., 0, 1], result.analyzers[..., 2, 1]
    peak = np.unravel_index(np.argmax(i0), i0.shape)
    expected_uv = camera.project(_mirror_point(camera, light))
    assert np.hypot(peak[1] - expected_uv[0], peak[0] - expected_uv[1]) < 1.5
    # The flash is polarized along the image x axis, as the 0-degree analyzer: specular stays co-polarized.
    assert i0[peak] > 20 * i90[peak]
    # Away from the highlight the diffuse lobe dominates and the two analyzers are comparable.
    far = (slice(HEIGHT // 2 - 2, HEIGHT // 2 + 2), slice(WIDTH // 2 + 40, WIDTH // 2 + 44))
    assert np.all(i0[far] < 3 * i90[far])


def test_diffuse_polarization_at_the_limb_is_radial_with_the_fresnel_dop():
    """Left half eta 1.3, right half eta 1.7: AoLP radial (p-polarized exit), DoP = |T-/T+|(theta_o, eta)."""
    camera = _camera()
    mesh = _sphere(eta=1.5)
    eta = np.where(mesh.vertices[:, 0] < 0, 1.3, 1.7)
    mesh = ParamMesh(mesh.vertices, mesh.faces, mesh.normals, mesh.params._replace(eta=eta))
    result = render_stokes(mesh, camera, flash_light(camera, FLASH_CAM), supersample=1)
    pixels = _disc_pixels(camera, 0.8, 0.93)
    points, normals = _sphere_hits(camera, pixels)
    side = np.abs(points[:, 0]) > 0.012  # away from the eta seam
    pixels, points, normals = pixels[side], points[side], normals[side]
    stokes = result.stokes[pixels[:, 1].astype(int), pixels[:, 0].astype(int), :, 1]
    aolp = 0.5 * np.arctan2(stokes[:, 2], stokes[:, 1])
    du, dv = pixels[:, 0] - camera.intrinsics[0, 2], pixels[:, 1] - camera.intrinsics[1, 2]
    radial = np.arctan2(-dv, du)  # Stokes frame: x = image right, y = image up
    error = np.angle(np.exp(2j * (aolp - radial))) / 2
    assert np.degrees(np.abs(error)).max() < 1.5
    cos_o = np.sum(normals * _unit(camera.center - points), -1)
    rs, rp = _fresnel(cos_o, np.where(points[:, 0] < 0, 1.3, 1.7))
    expected_dop = (rs - rp) / (2 - rs - rp)
    dop = np.hypot(stokes[:, 1], stokes[:, 2]) / stokes[:, 0]
    np.testing.assert_allclose(dop, expected_dop, rtol=0.03)
    assert expected_dop[points[:, 0] > 0].mean() > 1.5 * expected_dop[points[:, 0] < 0].mean()


def test_flash_shadow_appears_where_the_light_is_occluded():
    """A small sphere in front of a back wall, lit from the side: its shadow falls on the wall."""
    grid = np.stack(np.meshgrid(np.linspace(-0.3, 0.3, 31), np.linspace(-0.3, 0.3, 31)), -1).reshape(-1, 2)
    wall = np.concatenate([grid, np.full((len(grid), 1), 1.0)], 1)
    idx = np.arange(31 * 31).reshape(31, 31)
    wall_faces = np.concatenate([np.stack([idx[:-1, :-1], idx[1:, :-1], idx[:-1, 1:]], -1).reshape(-1, 3),
                                 np.stack([idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1).reshape(-1, 3)])
    ball_d, ball_faces = icosphere(4)
    ball = 0.03 * ball_d + np.array([0.0, 0.0, 0.8])
    vertices = np.concatenate([wall, ball])
    faces = np.concatenate([wall_faces, ball_faces + len(wall)])
    normals = np.concatenate([np.tile([0.0, 0.0, -1.0], (len(wall), 1)), ball_d])
    mesh = ParamMesh(vertices, faces, normals, _uniform_params(len(vertices)))
    k = np.array([[400.0, 0, 80], [0, 400.0, 64], [0, 0, 1]])
    camera = Camera(k, np.eye(3), np.zeros(3), 160, 128)
    light = Light(position=np.array([0.2, 0.0, 0.0]), axis=np.array([1.0, 0.0, 0.0]))
    renderer = Renderer(mesh)
    shadowed = renderer.render(camera, light, supersample=1, shadows=True)
    unshadowed = renderer.render(camera, light, supersample=1, shadows=False)
    # The ball's shadow is centred at x = -0.05 on the wall (radius 0.0375); the camera sees it for x < -0.0375.
    in_shadow = np.round(camera.project(np.array([-0.07, 0.0, 1.0]))).astype(int)
    lit = np.round(camera.project(np.array([0.07, 0.0, 1.0]))).astype(int)
    assert shadowed.stokes[in_shadow[1], in_shadow[0], 0].max() == 0
    assert shadowed.lit[in_shadow[1], in_shadow[0]] == 0 and shadowed.coverage[in_shadow[1], in_shadow[0]] == 1
    assert unshadowed.stokes[in_shadow[1], in_shadow[0], 0].min() > 0
    np.testing.assert_allclose(shadowed.stokes[lit[1], lit[0]], unshadowed.stokes[lit[1], lit[0]])
    assert shadowed.stokes[lit[1], lit[0], 0].min() > 0


def test_per_vertex_parameters_are_interpolated_barycentrically():
    """On a flat square facing the camera, the rendered red/green ratio follows a linear albedo ramp."""
    vertices = np.array([[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.1, 0.1, 1.0], [-0.1, 0.1, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    normals = np.tile([0.0, 0.0, -1.0], (4, 1))
    rho_d = np.stack([0.2 + 2.0 * (vertices[:, 0] + 0.1), np.full(4, 0.4), np.full(4, 0.4)], -1)
    params = _uniform_params(4)._replace(rho_d=rho_d)
    camera = Camera(np.array([[300.0, 0, 40], [0, 300.0, 32], [0, 0, 1]]), np.eye(3), np.zeros(3), 80, 64)
    result = render_stokes(ParamMesh(vertices, faces, normals, params), camera,
                           Light(np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])), supersample=1)
    v, u = np.mgrid[10:54:7, 12:70:7]
    x_world = (u - 40) / 300.0  # the plane is at z = 1
    ratio = result.stokes[v, u, 0, 0] / result.stokes[v, u, 0, 1]
    np.testing.assert_allclose(ratio, (0.2 + 2.0 * (x_world + 0.1)) / 0.4, rtol=1e-4)


def test_supersampling_gives_fractional_coverage_with_the_right_area():
    camera = _camera()
    result = Renderer(_sphere(subdivisions=5)).render(camera, flash_light(camera, FLASH_CAM), supersample=4)
    edge = (result.coverage > 0) & (result.coverage < 1)
    assert edge.sum() > 100
    apparent = FOCAL * RADIUS / np.sqrt(DISTANCE ** 2 - RADIUS ** 2)
    assert result.coverage.sum() == pytest.approx(np.pi * apparent ** 2, rel=0.01)
    assert len(subpixel_offsets(4)) == 16 and np.abs(subpixel_offsets(4)).max() < 0.5


def test_distorted_rays_project_back_to_their_pixels():
    k = np.array([[500.0, 0, 40], [0, 510.0, 30], [0, 0, 1]])
    rotation = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    distortion = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01])
    camera = Camera(k, rotation, np.array([0.01, 0.02, 0.5]), 80, 60, distortion=distortion)
    origin, directions = pixel_rays(camera, supersample=1)
    uv = camera.project(origin + 0.7 * directions[:, :, 0])
    v, u = np.mgrid[0:60, 0:80]
    np.testing.assert_allclose(uv, np.stack([u, v], -1), atol=1e-6)


def test_incident_stokes_option_is_linear_and_agrees_with_the_flash_path():
    """Light.stokes goes through full_mueller; [1, 1, 0, 0] (the default, full_stokes) must agree with it."""
    from dataclasses import replace

    camera = _camera()
    mesh = _sphere(subdivisions=4, eta=1.5, rho_s=0.8, sigma_s=0.15, rho_ss=(0.1, 0.05, 0.02))
    renderer = Renderer(mesh)
    flash = flash_light(camera, FLASH_CAM, polarizer_deg=20.0)
    default = renderer.render(camera, flash, supersample=1).stokes
    doubled = renderer.render(camera, replace(flash, stokes=(2.0, 2.0, 0.0, 0.0)), supersample=1).stokes
    crossed = renderer.render(camera, replace(flash, stokes=(1.0, -1.0, 0.0, 0.0)), supersample=1).stokes
    unpolarized = renderer.render(camera, replace(flash, stokes=(1.0, 0.0, 0.0, 0.0)), supersample=1).stokes
    scale = np.abs(default).max()
    np.testing.assert_allclose(doubled, 2 * default, atol=1e-5 * scale)
    np.testing.assert_allclose(unpolarized, 0.5 * (default + crossed), atol=1e-5 * scale)
    # At the highlight (reflection dominates, polarization kept) the crossed light's AoLP is 90 deg from the flash's.
    peak = np.unravel_index(np.argmax(default[..., 0, 1]), default.shape[:2])
    angle = [0.5 * np.arctan2(s[peak][2, 1], s[peak][1, 1]) for s in (default, crossed)]
    assert np.degrees(abs(np.angle(np.exp(2j * (angle[0] - angle[1]))) / 2)) > 85
