"""Unit checks of a capture's numbers against each other (issue #38): lengths that are off by a factor of 1000
must not pass silently.

- :func:`camera_distances` -- (V,) camera-to-object distances (metres, if the poses are) of poses
  (R (V, 3, 3), t (V, 3), COLMAP cam_from_world), the object being the point nearest to every optical axis.
- :func:`check_pose_units` -- their median against capture.yaml's ``scene.distance_m``: a
  :class:`PoseUnitsError` that names the likely unit (millimetres, centimetres, inches; of poses.csv or of
  ``scene.distance_m``) when they disagree by more than :data:`DISTANCE_TOLERANCE`.

The scan's own units check (init.mode mesh) is :func:`sellip.geometry.check_against_silhouettes`; this module
uses its table of units (:data:`sellip.geometry.UNIT_SIZES`).
"""

from __future__ import annotations

import numpy as np

from sellip.capture.files import POSES_CSV, CaptureError
from sellip.geometry.scan import UNIT_SIZES
from sellip.model.conventions import camera_center, camera_forward

DISTANCE_TOLERANCE = 4.0
"""The median camera distance may differ from scene.distance_m by this factor either way ("typical camera-object
distance", docs/design.md §3: a rough figure; a millimetre or centimetre mistake is a factor of 1000 or 100)."""

UNIT_MATCH = 1.5
"""A ratio within this factor of a unit's size (UNIT_SIZES) is named as that unit."""


class PoseUnitsError(CaptureError):
    """poses.csv and capture.yaml's scene.distance_m disagree about the scale of the scene."""


class SamePoseError(CaptureError):
    """poses.csv puts every camera at the same place (one pose copied to every view)."""


SAME_PLACE = 1e-3
"""Camera centres all within this fraction of scene.distance_m of their mean are one place: the poses are a copy."""


def camera_distances(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """(V,) distance of each camera centre from the point nearest to all optical axes (least squares).

    rotations (V, 3, 3) and translations (V, 3): cam_from_world poses (COLMAP, docs/design.md §3), in any length unit;
    the distances are in that unit. With fewer than two views, or axes that are (nearly) parallel, the point is
    undefined: the distances are then from the centroid of the camera centres (0 for a single view)."""
    rotations = np.asarray(rotations, np.float64)
    translations = np.asarray(translations, np.float64)
    centers = camera_center(rotations, translations)
    axes = camera_forward(rotations)
    projector = np.eye(3) - axes[:, :, None] * axes[:, None, :]
    system = projector.sum(axis=0)
    if len(centers) >= 2 and np.linalg.cond(system) < 1e6:
        target = np.linalg.solve(system, np.einsum("vij,vj->i", projector, centers))
    else:
        target = centers.mean(axis=0)
    return np.linalg.norm(centers - target, axis=1)


def likely_unit(ratio: float) -> tuple[str, str, float] | None:
    """(unit, whose: "poses" or "distance", factor) when ``ratio`` (poses' distance / scene.distance_m) is within
    UNIT_MATCH of a unit's size (the poses in that unit) or of its inverse (scene.distance_m in it), else None."""
    for unit, size in UNIT_SIZES.items():
        if abs(np.log(ratio / size)) <= np.log(UNIT_MATCH):
            return unit, "poses", size
        if abs(np.log(ratio * size)) <= np.log(UNIT_MATCH):
            return unit, "distance", size
    return None


def check_pose_units(rotations: np.ndarray, translations: np.ndarray, distance_m: float,
                     file_label: str = POSES_CSV, capture_label: str = "capture.yaml") -> float:
    """The median camera distance of the poses (in the poses' unit), checked against ``distance_m``
    (capture.yaml's scene.distance_m, metres). Rows with NaN are left out; fewer than two usable views are not
    checked. Raises PoseUnitsError naming the likely unit when the two differ by more than DISTANCE_TOLERANCE."""
    rotations = np.asarray(rotations, np.float64)
    translations = np.asarray(translations, np.float64)
    usable = np.isfinite(translations).all(axis=1) & np.isfinite(rotations).all(axis=(1, 2))
    if usable.sum() < 2:
        return float("nan")
    centers = camera_center(rotations[usable], translations[usable])
    spread = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max())
    if spread < SAME_PLACE * float(distance_m):
        same = bool(np.allclose(rotations[usable], rotations[usable][0], atol=1e-6))
        raise SamePoseError(file_label, "columns qw..qz, tx, ty, tz",
                            f"all {int(usable.sum())} cameras are at the same place (within {spread:.3g} of each "
                            f"other{', with the same rotation' if same else ''}): every view was given the same pose. "
                            "Expected one pose per photograph, from a calibrated rig or sfm.mode: sfm (drop "
                            "poses.csv to estimate the poses)")
    median = float(np.median(camera_distances(rotations[usable], translations[usable])))
    ratio = median / float(distance_m)
    if 1 / DISTANCE_TOLERANCE <= ratio <= DISTANCE_TOLERANCE:
        return median
    seen = (f"the cameras are a median {median:.4g} units from the point their optical axes meet, "
            f"{ratio:.4g} times scene.distance_m = {distance_m:g} m in {capture_label}")
    guess = likely_unit(ratio)
    if guess is None:
        advice = (f"expected translations in metres (docs/design.md §3) within {DISTANCE_TOLERANCE:g}x of "
                  "scene.distance_m; check the units of tx, ty, tz and scene.distance_m")
    elif guess[1] == "poses":
        advice = (f"the translations look like {guess[0]}; poses.csv needs metres (docs/design.md §3): "
                  f"divide tx, ty, tz by {guess[2]:.4g}")
    else:
        advice = (f"scene.distance_m looks like {guess[0]} (it needs metres): {distance_m / guess[2]:.4g} m "
                  "would fit the poses")
    raise PoseUnitsError(file_label, "columns tx, ty, tz", f"{seen}: {advice}")
