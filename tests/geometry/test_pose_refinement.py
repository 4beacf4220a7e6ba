"""Poses refined against the object: a textured sphere rendered at the true pose, the camera moved off it, and
the pose brought back by aligning the photograph to a render of the model (sellip.geometry.pose_refinement)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sellip.geometry.pose_refinement import PoseRefinementSettings, moved_pose, pose_change, refine_view
from sellip.model.pbrdf import PBRDFParams
from sellip.model.render import Camera, ParamMesh, Renderer, flash_light


def _painted_sphere(radius: float = 0.05) -> ParamMesh:
    """A sphere (radius in metres) painted with sharp-edged patches of two albedos, glossy (eta 1.5)."""
    import open3d as o3d

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=60)
    sphere.compute_vertex_normals()
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    unit = vertices / radius
    paint = (np.sin(9 * unit[:, 0] + 1) * np.sin(7 * unit[:, 1]) * np.sin(8 * unit[:, 2] + 2) > 0)
    rho_d = np.where(paint[:, None], [0.7, 0.5, 0.3], [0.1, 0.15, 0.2])
    n = len(vertices)
    params = PBRDFParams(eta=np.full(n, 1.5), rho_d=rho_d, rho_s=np.full(n, 0.3), sigma_s=np.full(n, 0.25),
                         rho_ss=np.zeros((n, 3)), sigma_ss=np.full(n, 0.5))
    return ParamMesh(vertices, faces, np.asarray(sphere.vertex_normals), params)


def _camera(rotation=None, translation=(0.0, 0.0, 0.5)) -> Camera:
    rotation = np.eye(3) if rotation is None else rotation
    return Camera(np.array([[900.0, 0, 80], [0, 900.0, 60], [0, 0, 1]]), np.asarray(rotation, np.float64),
                  np.asarray(translation, np.float64), 160, 120)


def _reprojection_px(camera: Camera, truth: Camera, points: np.ndarray) -> float:
    return float(np.median(np.linalg.norm(camera.project(points) - truth.project(points), axis=-1)))


@pytest.fixture(scope="module")
def scene():
    mesh = _painted_sphere()
    renderer = Renderer(mesh)
    truth = _camera(Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix())
    truth = Camera(truth.intrinsics, truth.rotation, np.array([0.0, 0.0, 0.5]), truth.width, truth.height)
    image = renderer.render(truth, flash_light(truth), supersample=2).analyzers
    return mesh, renderer, truth, image


def test_a_moved_camera_is_brought_back_to_the_photograph(scene):
    mesh, renderer, truth, image = scene
    step = np.array([0.004, -0.003, 0.002, 0.004, 0.003, -0.002])  # about 0.3 degrees and 2 mm at 0.5 m
    moved = Camera(truth.intrinsics, *moved_pose(step, truth.rotation, truth.translation, 0.5), truth.width,
                   truth.height)
    points = np.asarray(mesh.vertices)[(np.asarray(mesh.vertices) @ truth.rotation.T + truth.translation)[:, 2]
                                       < 0.5]  # the half the camera sees
    before = _reprojection_px(moved, truth, points)
    refined, report = refine_view(renderer, moved, flash_light, image, np.ones(image.shape[:2], bool))
    after = _reprojection_px(refined, truth, points)
    assert report["refined"] and report["pixels"] > 2000
    assert before > 1.0
    assert after < 0.05 * before and after < 0.05, (before, after, report)  # 1.38 -> 0.02 px when written
    assert report["cost_end"] < report["cost_start"]
    angle, shift = pose_change(moved.rotation, moved.translation, refined.rotation, refined.translation)
    assert report["rotation_deg"] == pytest.approx(angle) and report["shift_mm"] == pytest.approx(1e3 * shift)


def test_a_true_pose_is_kept(scene):
    """From the true pose the alignment moves the object by a few hundredths of a pixel: within min_motion_px 0.5."""
    _, renderer, truth, image = scene
    kept, report = refine_view(renderer, truth, flash_light, image, np.ones(image.shape[:2], bool),
                               PoseRefinementSettings(min_motion_px=0.5))
    assert not report["refined"] and "own noise" in report["reason"] and report["motion_px"] < 0.1, report
    assert kept is truth


def test_a_view_that_does_not_see_the_object_keeps_its_pose(scene):
    _, renderer, truth, image = scene
    away = Camera(truth.intrinsics, truth.rotation, truth.translation + np.array([0.0, 0.0, -1.0]),
                  truth.width, truth.height)  # the object behind the camera
    kept, report = refine_view(renderer, away, flash_light, image, np.ones(image.shape[:2], bool))
    assert not report["refined"] and "usable pixels" in report["reason"]
    assert kept is away


def test_a_step_beyond_the_limits_keeps_the_pose(scene):
    _, renderer, truth, image = scene
    step = np.array([0.004, -0.003, 0.002, 0.004, 0.003, -0.002])
    moved = Camera(truth.intrinsics, *moved_pose(step, truth.rotation, truth.translation, 0.5), truth.width,
                   truth.height)
    settings = PoseRefinementSettings(max_rotation_deg=0.01)
    kept, report = refine_view(renderer, moved, flash_light, image, np.ones(image.shape[:2], bool), settings)
    assert not report["refined"] and "divergence" in report["reason"]
    assert kept is moved


@pytest.mark.parametrize("bad", [{"blur_px": ()}, {"blur_px": (-1.0,)}, {"rounds": 0}, {"max_rotation_deg": 0},
                                 {"erode_px": -1}, {"robust_scale": -0.1}, {"min_motion_px": -1}])
def test_settings_are_checked(bad):
    with pytest.raises(ValueError):
        PoseRefinementSettings(**bad)


def test_a_blank_photograph_leaves_the_pose(scene):
    """A photograph that does not change with the pose (all zero): no direction is determined, nothing moves."""
    mesh, renderer, truth, image = scene
    from sellip.geometry.pose_refinement import align_pose

    points = np.asarray(mesh.vertices)[:500]
    rotation, translation, report = align_pose(points, np.ones((500, 3)), np.zeros((120, 160, 3)), truth)
    assert report["directions"] == 0
    np.testing.assert_array_equal(rotation, truth.rotation)
    np.testing.assert_array_equal(translation, truth.translation)
