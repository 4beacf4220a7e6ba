"""Camera poses refined against the object (issue #36 item 4; rule ``refine_poses``; docs/geometry.md,
"Poses refined against the object").

SfM agrees with its own features to a fraction of a pixel, yet a few views' poses can put the object's
surface a pixel or more away from where the other views put it (the views beside a run of unregistered ones,
a narrow field of view in which a rotation and a shift across the axis look alike). Between iterations, each
view's pose is aligned to the current model: the model (the iteration's mesh, fitted normals and pBRDF) is
rendered through the view's camera under its flash; the surface points seen by the interior pixels of that
render are projected through a moved pose and the photograph is sampled there; the pose that makes the sampled
photograph agree best with the render (a robust least-squares direct image alignment, coarse to fine, the
exposure's scale solved in closed form) is the view's new pose. The model, not the other poses, is the
reference, so no gauge is free: the poses stay in the model's world. Intrinsics are held.

    align_pose(points, reference, image, camera, ...) -> (rotation, translation, report)     # one alignment
    refine_view(renderer, camera, flash, analyzers, valid, settings) -> (Camera, report)      # render + align

The stage (every view of a cameras table, written as the next iteration's) is
:func:`sellip.fit.geometry_jobs.refine_poses`.

Poses are COLMAP cam_from_world (``x_cam = R x_world + t``), metres; pixel centres at integer coordinates
(:mod:`sellip.model.render`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from sellip.settings import setting

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PoseRefinementSettings:
    """How each view's pose is aligned to the model (config section ``refine_poses``; docs/geometry.md, "Poses
    refined against the object"). Each round renders the model at the pose of the last; the first round uses every
    blur, later rounds the last. From exact or good poses the alignment moves the surface points by 0.2-0.3 px, its
    own noise (``min_motion_px``)."""

    blur_px: tuple[float, ...] = setting((1.5, 0.0), "Gaussian blurs (sigma) of the photograph, coarse to fine "
                                         "(the coarse ones widen the reach to a few pixels)", unit="HDR pixels",
                                         minimum=0, min_items=1)
    rounds: int = setting(2, "renders per view and refinement", minimum=1)
    erode_px: int = setting(2, "the render's footprint is eroded by this much (no silhouette pixel, whose value "
                            "mixes object and background)", unit="pixels", minimum=0)
    min_pixels: int = setting(500, "fewer usable pixels leave the view's pose as it was", minimum=1)
    max_rotation_deg: float = setting(2.0, "a larger rotation is taken for a divergence: the view keeps its pose",
                                      unit="degrees", exclusive_minimum=0)
    max_shift_fraction: float = setting(0.03, "a larger centre shift is taken for a divergence: the view keeps its "
                                        "pose", unit="fraction of the camera's distance", exclusive_minimum=0)
    robust_scale: float = setting(0.05, "the soft-L1 loss's scale", unit="fraction of the render's median value",
                                  exclusive_minimum=0)
    max_evaluations: int = setting(60, "cost evaluations per blur level", minimum=1)
    min_confidence: float = setting(0.5, "pixels of vertices fitted with less confidence are not compared", minimum=0,
                                    maximum=1)
    min_motion_px: float = setting(0.0, "a view whose new pose moves the object less (median) keeps its pose; 0: "
                                   "every view takes its aligned pose (docs/benchmarks.md)", unit="pixels", minimum=0)

    def __post_init__(self):
        if not self.blur_px or any(not np.isfinite(b) or b < 0 for b in self.blur_px):
            raise ValueError(f"blur_px must be a non-empty list of sigmas >= 0, got {self.blur_px}")
        for name in ("rounds", "min_pixels", "max_evaluations"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.min_motion_px >= 0:
            raise ValueError(f"min_motion_px must be >= 0, got {self.min_motion_px}")
        for name in ("max_rotation_deg", "max_shift_fraction", "robust_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if int(self.erode_px) < 0:
            raise ValueError(f"erode_px must be >= 0, got {self.erode_px}")


def moved_pose(step: np.ndarray, rotation: np.ndarray, translation: np.ndarray, distance: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """The pose moved by ``step`` (6,): a rotation vector (radians) applied in camera coordinates and a shift of
    the camera frame's origin in units of ``distance`` (metres), ``R' = exp(w) R``, ``t' = exp(w) t + distance s``."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_rotvec(step[:3]).as_matrix()
    return turn @ rotation, turn @ translation + distance * np.asarray(step[3:], np.float64)


def pose_change(rotation0, translation0, rotation, translation) -> tuple[float, float]:
    """(the rotation between two cam_from_world poses in degrees, the distance of their centres in metres)."""
    from sellip.model.conventions import camera_center

    turn = np.asarray(rotation, np.float64) @ np.asarray(rotation0, np.float64).T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(turn) - 1) / 2, -1.0, 1.0))))
    centres = [camera_center(np.asarray(r, np.float64), np.asarray(t, np.float64))
               for r, t in ((rotation0, translation0), (rotation, translation))]
    return angle, float(np.linalg.norm(centres[1] - centres[0]))


def _sample(image: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) of ``image`` (H, W, C) at ``pixels`` (N, 2) x, y (edge values outside)."""
    from scipy.ndimage import map_coordinates

    coords = [pixels[:, 1], pixels[:, 0]]
    return np.stack([map_coordinates(image[..., c], coords, order=1, mode="nearest")
                     for c in range(image.shape[-1])], axis=-1)


def _determined_directions(residual, min_singular_ratio: float, step: float = 1e-4) -> np.ndarray:
    """(6, k) orthonormal directions of the pose step along which ``residual`` (a function of the 6-vector step)
    changes: the right singular vectors of its forward-difference Jacobian at 0 whose singular value is at least
    ``min_singular_ratio`` of the largest. A direction the photograph barely sees (with a narrow field of view, a
    rotation about an axis across the view paired with a shift across it) is left where the pose had it."""
    base = residual(np.zeros(6))
    jacobian = np.stack([(residual(step * np.eye(6)[k]) - base) / step for k in range(6)], axis=1)
    _, singular, right = np.linalg.svd(jacobian, full_matrices=False)
    keep = singular >= min_singular_ratio * singular[0] if singular[0] > 0 else np.zeros(6, bool)
    log.debug("pose step singular values %s", np.array2string(singular / max(singular[0], 1e-300), precision=4))
    return right[keep].T


def align_pose(points: np.ndarray, reference: np.ndarray, image: np.ndarray, camera, blur_px=(1.5, 0.0),
               robust_scale: float = 0.05, max_evaluations: int = 60, min_singular_ratio: float = 0.002):
    """The pose of ``camera`` under which ``image`` agrees best with ``reference`` at the projected ``points``.

    points (N, 3) world surface points (metres); reference (N, C) the values the photograph should show there,
    up to one common scale; image (H, W, C) the photograph; camera a :class:`sellip.model.render.Camera` (its
    pose the start, its intrinsics and distortion held). For each blur (sigma in pixels, coarse to fine) the
    soft-L1 (scale ``robust_scale`` of the reference's median) least-squares residual
    ``(image(project(points; pose)) - k reference) / median(reference)``, k the median ratio of the two (robust to
    a few vertices fitted far too bright), is minimised over the 6 parameters of :func:`moved_pose`, in the
    directions whose singular value is at least ``min_singular_ratio`` of the largest (:func:`_determined_directions`;
    the default keeps all but a direction the photograph does not see at all: on the painted cow the weakest are
    0.5-2 % of the largest). Returns (rotation (3, 3), translation (3,), report: the step's rotation in degrees and
    centre shift in metres, the distance, the robust cost at the start pose and at the end on the finest level, the
    directions used).
    """
    from scipy.ndimage import gaussian_filter
    from scipy.optimize import least_squares

    from sellip.model.render import Camera

    points = np.asarray(points, np.float64)
    reference = np.asarray(reference, np.float64).reshape(len(points), -1)
    image = np.asarray(image, np.float64).reshape(image.shape[0], image.shape[1], -1)
    rotation0, translation0 = np.asarray(camera.rotation, np.float64), np.asarray(camera.translation, np.float64)
    distance = float(np.median(np.linalg.norm(points @ rotation0.T + translation0, axis=1)))
    norm = float(np.median(reference[reference > 0])) if np.any(reference > 0) else 1.0
    positive = reference > 0
    rotation, translation = rotation0, translation0

    def residual(step, start_rotation, start_translation, blurred):
        moved = Camera(camera.intrinsics, *moved_pose(step, start_rotation, start_translation, distance),
                       camera.width, camera.height, camera.distortion)
        sampled = _sample(blurred, moved.project(points))
        scale = float(np.median(sampled[positive] / reference[positive])) if positive.any() else 0.0
        return ((sampled - scale * reference) / norm).ravel()

    def robust_cost(values):  # scipy's cost for loss="soft_l1" with f_scale=robust_scale
        return float(np.sum(robust_scale ** 2 * (np.sqrt(1 + (values / robust_scale) ** 2) - 1)))

    directions_kept = 6
    for sigma in blur_px:
        blurred = (np.stack([gaussian_filter(image[..., c], sigma) for c in range(image.shape[-1])], axis=-1)
                   if sigma > 0 else image)
        basis = _determined_directions(lambda step: residual(step, rotation, translation, blurred), min_singular_ratio)  # noqa: B023 - called in this iteration
        directions_kept = basis.shape[1]
        if not directions_kept:  # a photograph that does not change with the pose (a flat, dark one)
            continue
        solution = least_squares(lambda y: residual(basis @ y, rotation, translation, blurred),  # noqa: B023 - called in this iteration
                                 np.zeros(basis.shape[1]),
                                 loss="soft_l1", f_scale=robust_scale, diff_step=1e-4, max_nfev=max_evaluations)
        rotation, translation = moved_pose(basis @ solution.x, rotation, translation, distance)
    cost_start = robust_cost(residual(np.zeros(6), rotation0, translation0, blurred))
    cost_end = robust_cost(residual(np.zeros(6), rotation, translation, blurred))
    angle, shift = pose_change(rotation0, translation0, rotation, translation)
    return rotation, translation, {"rotation_deg": angle, "shift_m": shift, "distance_m": distance,
                                   "cost_start": cost_start, "cost_end": cost_end,
                                   "directions": directions_kept}


def refine_view(renderer, camera, flash, analyzers: np.ndarray, valid: np.ndarray,
                settings: PoseRefinementSettings = PoseRefinementSettings(), vertex_confidence=None):
    """One view's pose aligned to the model of ``renderer`` (a :class:`sellip.model.render.Renderer`).

    camera: the view's :class:`sellip.model.render.Camera` (HDR resolution); flash: a function of a camera that
    returns its :class:`sellip.model.render.Light`; analyzers (H, W, 4, 3) the view's HDR image, valid (H, W)
    its usable pixels; vertex_confidence (V,) optional: pixels whose interpolated confidence is below
    ``settings.min_confidence`` are not compared. The s0 = I0 + I90 image (RGB) is compared. Each of
    ``settings.rounds`` rounds renders the model at the current pose and aligns (:func:`align_pose`) the
    photograph to that render on the render's fully covered, lit, eroded footprint. Returns (the camera, moved or
    not, and a report: ``refined`` and, when not, ``reason``; the step's rotation in degrees, centre shift in
    millimetres and the median motion in pixels of the surface points first compared; the pixels compared; the
    robust cost before and after at the finest blur).
    """
    from scipy.ndimage import binary_erosion

    measured = np.asarray(analyzers, np.float64)
    image = measured[..., 0, :] + measured[..., 2, :]
    start, current = camera, camera
    report: dict = {"refined": False}
    first_cost = None
    for round_index in range(settings.rounds):
        rendered = renderer.render(current, flash(current), supersample=1)
        confidence = (np.ones(renderer.mesh.num_vertices) if vertex_confidence is None
                      else np.asarray(vertex_confidence, np.float64))
        values, coverage = renderer.interpolate(current, np.column_stack([np.asarray(renderer.mesh.vertices),
                                                                          confidence]), supersample=1)
        points = values[..., :3].astype(np.float64)
        reference = rendered.analyzers[..., 0, :].astype(np.float64) + rendered.analyzers[..., 2, :]
        usable = ((coverage >= 1) & (rendered.lit >= 1) & np.asarray(valid, bool)
                  & (values[..., 3] >= settings.min_confidence)
                  & np.all(np.isfinite(image), axis=-1) & np.all(np.isfinite(reference), axis=-1))
        if settings.erode_px:
            usable = binary_erosion(usable, iterations=int(settings.erode_px))
        report["pixels"] = int(usable.sum())
        if report["pixels"] < settings.min_pixels:
            report["reason"] = f"{report['pixels']} usable pixels (< {settings.min_pixels})"
            return start, report
        blur = settings.blur_px if round_index == 0 else settings.blur_px[-1:]
        rotation, translation, step = align_pose(points[usable], reference[usable], image, current, blur,
                                                 settings.robust_scale, settings.max_evaluations)
        if first_cost is None:
            first_cost, seen = step["cost_start"], points[usable]
        current = replace(current, rotation=rotation, translation=translation)
    angle, shift = pose_change(start.rotation, start.translation, current.rotation, current.translation)
    motion = float(np.median(np.linalg.norm(current.project(seen) - start.project(seen), axis=-1)))
    report.update(rotation_deg=angle, shift_mm=1e3 * shift, motion_px=motion, cost_start=first_cost,
                  cost_end=step["cost_end"])
    if angle > settings.max_rotation_deg or shift > settings.max_shift_fraction * step["distance_m"]:
        report["reason"] = (f"a step of {angle:.3f} deg and {1e3 * shift:.2f} mm exceeds max_rotation_deg "
                            f"{settings.max_rotation_deg} or max_shift_fraction {settings.max_shift_fraction} of "
                            f"{step['distance_m']:.3f} m: taken for a divergence")
        return start, report
    if motion < settings.min_motion_px:
        report["reason"] = (f"the object would move {motion:.3f} px (median), less than min_motion_px "
                            f"{settings.min_motion_px}: within the alignment's own noise")
        return start, report
    report["refined"] = True
    return current, report
