"""Photo-consistency carving (sellip.geometry.carve) on a textured plane photographed from six views: a vertex
floating above the plane finds the plane's depth; one on it, or above a plain plane, gets no target."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.geometry.carve import CarveView, carve_targets, photo_consistency


def _look_at(centre: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    forward = target - centre
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0] if abs(forward[2]) < 0.99 else [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # cam_from_world
    return rotation, -rotation @ centre


def _plane_views(texture, size: int = 200, focal: float = 700.0) -> list[CarveView]:
    """Six photographs of the plane z = 0 (colour ``texture(x, y)`` (N, 3)), each with its own gain (the flash's
    shading), from 0.25 m at elevations 45-75 degrees."""
    intrinsics = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    pixels = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    views = []
    for k, (azimuth, elevation) in enumerate([(0, 45), (60, 60), (120, 75), (180, 50), (240, 65), (300, 55)]):
        az, el = np.radians(azimuth), np.radians(elevation)
        centre = 0.25 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        rotation, translation = _look_at(centre, np.zeros(3))
        rays = (np.linalg.inv(intrinsics) @ pixels.T).T @ rotation  # world directions
        t = -centre[2] / rays[:, 2]
        hit = centre + t[:, None] * rays
        image = (0.6 + 0.15 * k) * texture(hit[:, 0], hit[:, 1])
        views.append(CarveView(image.reshape(size, size, 3), np.ones((size, size), bool), intrinsics, rotation,
                               translation))
    return views


def _cells(x, y):
    """Sharp-edged 3 mm cells in four colours."""
    palette = np.array([[0.2, 0.2, 0.2], [0.8, 0.7, 0.6], [0.5, 0.3, 0.2], [0.3, 0.5, 0.7]])
    ix, iy = np.floor(x / 0.003).astype(np.int64), np.floor(y / 0.003).astype(np.int64)
    return palette[(ix * 7 + iy * 13 + (ix * iy) % 5) % 4]


def test_a_vertex_above_a_textured_plane_finds_its_depth():
    views = _plane_views(_cells)
    vertices = np.array([[0.0005, 0.0012, 0.006], [0.004, -0.002, 0.0], [-0.003, 0.002, 0.0035]])
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    visible = np.ones((3, len(views)), bool)
    targets = carve_targets(vertices, normals, np.arange(3), visible, views, max_depth=0.01, step=0.0005,
                            spacing=0.001)
    assert list(targets.vertex) == [0, 2]  # the one on the plane stays
    np.testing.assert_allclose(targets.depth, [0.006, 0.0035], atol=0.00051)
    assert np.all(targets.score > 0.9) and np.all(targets.score_here < targets.score - 0.15)
    assert np.all((targets.weight > 0) & (targets.weight <= 1))


def test_a_plain_plane_gives_no_target():
    views = _plane_views(lambda x, y: np.full((len(x), 3), 0.5))
    vertices = np.array([[0.0, 0.0, 0.006]])
    score, count, _ = photo_consistency(vertices, np.array([[0.0, 0.0, 1.0]]), np.ones((1, len(views)), bool), views,
                                        np.arange(0, 0.01, 0.0005), spacing=0.001)
    assert np.all(count == 0) and np.all(np.isnan(score))  # no textured patch anywhere
    targets = carve_targets(vertices, np.array([[0.0, 0.0, 1.0]]), np.arange(1), np.ones((1, len(views)), bool),
                            views, max_depth=0.01, step=0.0005, spacing=0.001)
    assert len(targets) == 0


@pytest.mark.parametrize("visible_views", [1, 2])
def test_too_few_views_give_no_target(visible_views):
    views = _plane_views(_cells)
    visible = np.zeros((1, len(views)), bool)
    visible[0, :visible_views] = True
    targets = carve_targets(np.array([[0.0, 0.0, 0.006]]), np.array([[0.0, 0.0, 1.0]]), np.arange(1), visible, views,
                            max_depth=0.01, step=0.0005, spacing=0.001)
    assert len(targets) == 0


def test_the_update_moves_unconfident_vertices_to_their_targets_and_leaves_the_rest():
    """A 4 cm sphere whose fit is unsure everywhere (confidence 0): with carving targets 5 mm deep on a cap of about
    30 vertices the cap sinks by more than half of that in one update (smoothed at its edge), the far side does not
    move (the whole mesh is not dragged in: nothing else holds its offset), and nothing folds."""
    from sellip.capture.scenes import icosphere
    from sellip.geometry.carve import CarveTargets
    from sellip.geometry.meshes import surface_defects, vertex_normals
    from sellip.geometry.update import refine_from_normals

    directions, faces = icosphere(3)
    vertices = 0.04 * directions
    cap = np.flatnonzero(directions[:, 2] > 0.9)
    targets = CarveTargets(cap, np.full(cap.size, 0.005), np.ones(cap.size), np.ones(cap.size), np.zeros(cap.size))
    normals = vertex_normals(vertices, faces)
    moved = refine_from_normals(vertices, faces, normals, np.zeros(len(vertices)), carve=targets)
    sink = 0.04 - np.linalg.norm(moved, axis=1)
    assert 0.0025 < np.median(sink[cap]) < 0.0055  # smoothed at the cap's edge (CARVE_DECAY_EDGES)
    assert np.max(np.abs(sink[directions[:, 2] < -0.5])) < 2e-4
    assert surface_defects(moved, faces, vertices).as_dict()["self_intersecting_pairs"] == 0
    unmoved = refine_from_normals(vertices, faces, normals, np.zeros(len(vertices)), carve=targets, carve_weight=0)
    np.testing.assert_allclose(unmoved, vertices, atol=1e-12)
