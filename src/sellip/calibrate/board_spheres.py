"""The flash step's board protocol: glossy spheres resting on the checkerboard, their centres from its pose.

Public API::

    BOARD_SUFFIX                                                     # NAME_board.ext: the board frame of NAME.ext
    square_centres(cols, rows, square_m) -> (K, 2)                   # where a sphere may be set down (board x, y)
    sphere_centre(R, t, mark (2,), radius_m) -> centre (3,)          # resting on the board at ``mark``
    board_pose(raw, device, cols, rows, square_m) -> (BoardPose | None, why | None)   # solvePnP + covariance
    board_sphere_marks(s0_spheres, s0_board, intrinsics, pose, cols, rows, square_m, radius_m) -> (marks, left out)
    calibrate_flash_on_board(frames, device, radius_m, cols, rows, square_m) -> FlashResult

Board coordinates are OpenCV's (origin at the first inner corner, x along a row of corners, y down the columns,
z normal to the board); camera coordinates and the output grid as in :mod:`sellip.calibrate.flash`. The protocol
(docs/calibration.md, "Flash position"): from one camera position, a frame of the board alone, then a frame with
2-3 spheres set down on squares' centres; a sphere's centre is ``radius_m`` above its square's centre on the
camera's side of the board, so the board's pose fixes it to a few hundredths of a millimetre, which no outline
of a glossy sphere does (it mirrors its background at its rim).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from sellip.calibrate.flash import (
    MIN_HIGHLIGHTS,
    FlashResult,
    Sphere,
    develop_frame,
    highlight_rays,
    intensity,
    mirror_ray,
    pixel_rays,
    shared_highlight_covariance,
    too_few_highlights,
)
from sellip.calibrate.flash_fit import drop_outlier_highlights, nearest_point, solve_flash


def square_centres(cols: int, rows: int, square_m: float) -> np.ndarray:
    """(K, 2) board coordinates (x, y) of the centres of a ``cols`` x ``rows``-corner board's (cols + 1) x
    (rows + 1) squares, row by row: where a sphere may be set down."""
    j, i = np.meshgrid(np.arange(cols + 1), np.arange(rows + 1))
    return np.stack([(j.ravel() - 0.5) * square_m, (i.ravel() - 0.5) * square_m], axis=-1)


BOARD_SUFFIX = "_board"
"""The board frame of the sphere frame NAME.ext is NAME_board.ext: the board alone, from the same camera position,
before the spheres were set down on it."""

CHANGE_LEVEL = 0.05
"""What changed between a board frame and its sphere frame: more than this share of the board's white."""

MIN_MARK_IOU = 0.6
"""A sphere's silhouette (what changed between the board frame and the sphere frame) must overlap the disc of a
sphere on a square's centre by this much (intersection over union; 0.7-0.95 measured on the synthetic frames,
where the next square's disc overlaps it by about 0.3), else it is left out."""

CENTRE_SAMPLES = 200
"""Draws of the board poses and intrinsics from their 1-sigma for the flash's centre error (:func:`solve_flash`)."""


@dataclass
class BoardPose:
    """A board frame's pose: rvec, tvec (board -> camera, OpenCV), corners (N, 2) raw px, object (N, 3) board
    coordinates (m), cov (6, 6) of (rvec, tvec) from the corners' reprojection residuals."""

    rvec: np.ndarray
    tvec: np.ndarray
    corners: np.ndarray
    object: np.ndarray
    cov: np.ndarray

    @property
    def rotation(self) -> np.ndarray:
        import cv2

        return cv2.Rodrigues(self.rvec)[0]


def _camera_matrix(camera: Mapping) -> np.ndarray:
    return np.array([[camera["fx"], 0, camera["cx"]], [0, camera["fy"], camera["cy"]], [0, 0, 1]], np.float64)


def board_pose(raw: np.ndarray, device: Mapping, cols: int, rows: int, square_m: float
               ) -> tuple[BoardPose | None, str | None]:
    """The board's pose in a raw frame (cv2.solvePnP on its refined corners, the device's intrinsics and
    distortion) with its covariance, or (None, why)."""
    import cv2

    from sellip.calibrate.intrinsics import detect_board, opencv_single_threaded

    found = detect_board(raw, device["sensor"], cols, rows)
    if found.problem:
        return None, found.problem
    camera = device["camera"]
    k, dist = _camera_matrix(camera), np.asarray(camera.get("distortion", [0.0] * 5), np.float64)
    obj = np.zeros((rows * cols, 3), np.float64)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_m
    with opencv_single_threaded():
        ok, rvec, tvec = cv2.solvePnP(obj, found.corners, k, dist, flags=cv2.SOLVEPNP_ITERATIVE)
        projected, jacobian = cv2.projectPoints(obj, rvec, tvec, k, dist)
    residual = projected.reshape(-1, 2) - found.corners
    j = jacobian[:, :6]
    sigma2 = float(np.sum(residual ** 2) / max(residual.size - 6, 1))
    cov = sigma2 * np.linalg.inv(j.T @ j)
    return BoardPose(rvec.ravel(), tvec.ravel(), found.corners, obj, cov), None


def _toward_camera(rotation: np.ndarray, tvec: np.ndarray) -> float:
    """The sign of board z on the camera's side: -1 when the board's z axis points away from the camera, +1 when
    the corners' order (a symmetric board's is ambiguous) made it point towards it."""
    return -1.0 if rotation[:, 2] @ tvec > 0 else 1.0


def sphere_centre(rotation: np.ndarray, tvec: np.ndarray, mark: np.ndarray, radius_m: float) -> np.ndarray:
    """Camera coordinates (3,) of a sphere of ``radius_m`` resting on the board (pose R, t) at board point ``mark``
    (x, y): ``radius_m`` above it on the camera's side."""
    side = _toward_camera(rotation, tvec)
    return rotation @ np.array([mark[0], mark[1], side * radius_m]) + tvec


def board_sphere_marks(s0_spheres: np.ndarray, s0_board: np.ndarray, intrinsics: Mapping, pose: BoardPose,
                       cols: int, rows: int, square_m: float, radius_m: float
                       ) -> tuple[list[np.ndarray], dict[str, str]]:
    """The square centres (x, y board coordinates, m) that spheres rest on. What changed between the board frame
    and the sphere frame (|difference| above 8x its noise and :data:`CHANGE_LEVEL` of the board's white, opened,
    closed over a square, holes filled) are the spheres' silhouettes; from its deepest point (the distance
    transform's maximum, one sphere at a time, spheres that merge in the image taken apart) a ray meets the plane of
    the sphere centres (``radius_m`` above the board), and of the square centres within 1.5 squares of that point
    the one whose sphere's projected disc overlaps the silhouette best (intersection over union, at least
    :data:`MIN_MARK_IOU`) is the sphere's. Returns (marks, {blob: why left out})."""
    finite = np.isfinite(s0_spheres) & np.isfinite(s0_board)
    diff = np.where(finite, s0_spheres - s0_board, np.inf)
    values = diff[finite]
    noise = 1.4826 * float(np.median(np.abs(values - np.median(values))))
    rotation, tvec = pose.rotation, pose.tvec
    f = float(np.sqrt(intrinsics["fx"] * intrinsics["fy"]))
    depth = float(tvec[2])
    square_px = f * square_m / depth
    radius_px = f * radius_m / depth
    # the noise grows with the signal (shot noise on the white squares): a change must also exceed a share of the
    # board's white
    white = float(np.percentile(s0_board[finite], 99))
    changed = np.abs(diff) > max(8 * noise, CHANGE_LEVEL * white)
    changed = ndimage.binary_opening(changed, iterations=2)
    size = max(int(round(0.6 * square_px)), 1)
    changed = ndimage.binary_closing(changed, structure=np.ones((3, 3)), iterations=size)
    changed = ndimage.binary_fill_holes(changed)
    labels, count = ndimage.label(changed)
    height, width = s0_spheres.shape
    yy, xx = np.mgrid[0:height, 0:width]
    side = _toward_camera(rotation, tvec)
    origin = -rotation.T @ tvec  # the camera in board coordinates
    squares = square_centres(cols, rows, square_m)
    marks, left_out = [], {}
    distance = ndimage.distance_transform_edt(changed)
    for index in range(1, count + 1):
        blob = labels == index
        if float(blob.sum()) < 0.3 * np.pi * radius_px ** 2:
            continue  # noise, not a sphere
        # one sphere at a time: the blob's deepest point is a sphere's middle (spheres close in the image merge)
        while True:
            inner = np.where(blob, distance, 0.0)
            deepest = np.unravel_index(int(np.argmax(inner)), inner.shape)
            if inner[deepest] < 0.5 * radius_px:
                break
            middle = np.array([deepest[1], deepest[0]], np.float64)
            near_middle = blob & (np.hypot(xx - middle[0], yy - middle[1]) < 1.3 * radius_px)
            where = f"blob at ({middle[0]:.0f}, {middle[1]:.0f})"
            ray = rotation.T @ pixel_rays(middle, intrinsics)
            lam = (side * radius_m - origin[2]) / ray[2]
            point = (origin + lam * ray)[:2]
            near = squares[np.linalg.norm(squares - point, axis=1) < 1.5 * square_m]
            best, best_iou, best_disc = None, 0.0, near_middle
            for mark in near:
                centre = sphere_centre(rotation, tvec, mark, radius_m)
                u = intrinsics["fx"] * centre[0] / centre[2] + intrinsics["cx"]
                v = intrinsics["fy"] * centre[1] / centre[2] + intrinsics["cy"]
                disc = np.hypot(xx - u, yy - v) < f * radius_m / float(np.linalg.norm(centre))
                iou = float(np.sum(disc & near_middle) / np.sum(disc | near_middle))
                if iou > best_iou:
                    best, best_iou, best_disc = mark, iou, disc
            if best is None or best_iou < MIN_MARK_IOU:
                left_out[where] = (f"a change between the frames that is not a sphere on a square's centre (overlap "
                                   f"{best_iou:.2f} with the best one's disc, at least {MIN_MARK_IOU} expected): a "
                                   "sphere set down off a square's centre, something moved, or a wrong "
                                   "--sphere-radius-mm")
                blob = blob & ~near_middle
            else:
                marks.append(best)
                blob = blob & ~ndimage.binary_dilation(best_disc, iterations=2)
    return marks, left_out


def _perturbed(camera: Mapping, draw: np.ndarray, std: Mapping) -> dict:
    return {**camera, **{key: float(camera[key]) + draw[n] * float(std.get(key, 0.0))
                         for n, key in enumerate(("fx", "fy", "cx", "cy"))}}


def _pairs(frames: Mapping[str, np.ndarray]) -> tuple[dict[str, str], dict[str, str]]:
    """{sphere frame: its board frame} (NAME.ext and NAME_board.ext, :data:`BOARD_SUFFIX`) and {frame: why left
    out} for a frame without its partner."""
    left_out: dict[str, str] = {}
    names = {n: Path(n) for n in frames}
    boards = {p.stem[: -len(BOARD_SUFFIX)]: n for n, p in names.items() if p.stem.endswith(BOARD_SUFFIX)}
    pairs = {}
    for name, path in names.items():
        if path.stem.endswith(BOARD_SUFFIX):
            if path.stem[: -len(BOARD_SUFFIX)] not in {p.stem for p in names.values()}:
                left_out[name] = "a board frame without its sphere frame (expected " \
                                 f"{path.stem[: -len(BOARD_SUFFIX)]}{path.suffix} beside it)"
            continue
        if path.stem not in boards:
            left_out[name] = (f"no board frame {path.stem}{BOARD_SUFFIX}{path.suffix} beside it: expected the board "
                              "alone, shot from the same camera position before the spheres were set down")
            continue
        pairs[name] = boards[path.stem]
    return pairs, left_out


def _centre_draws(poses: Mapping[str, BoardPose], used: list, device: Mapping, std: Mapping, radius_m: float,
                  samples: int, seed: int, scale_m: float, min_highlights: int) -> np.ndarray:
    """(S, 3) the flash recomputed ``samples`` times with the intrinsics (fx, fy, cx, cy) drawn from their 1-sigma
    ``std`` (raw px; each board's pose re-solved with them) and every board's pose then drawn from its covariance;
    ``used``: (sphere frame, mark, highlight px) per line. The highlights stay as measured."""
    import cv2

    from sellip.capture.ingest import output_intrinsics

    rng = np.random.default_rng(seed)
    camera, sensor = device["camera"], device["sensor"]
    dist = np.asarray(camera.get("distortion", [0.0] * 5), np.float64)
    draws = []
    for _ in range(samples):
        drawn = _perturbed(camera, rng.standard_normal(4), std)
        k = _camera_matrix(drawn)
        grid = output_intrinsics(drawn, int(sensor["height"]), int(sensor["width"]))
        drawn_poses = {}
        for name, pose in poses.items():
            _, rvec, tvec = cv2.solvePnP(pose.object, pose.corners, k, dist, pose.rvec.copy(), pose.tvec.copy(),
                                         useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
            delta = rng.multivariate_normal(np.zeros(6), pose.cov)
            drawn_poses[name] = (cv2.Rodrigues(rvec.ravel() + delta[:3])[0], tvec.ravel() + delta[3:])
        lines = []
        for name, mark, highlight in used:
            rotation, tvec = drawn_poses[name]
            line = mirror_ray(sphere_centre(rotation, tvec, mark, radius_m), radius_m, highlight, grid)
            if line is not None:
                lines.append(line)
        if len(lines) >= min_highlights:
            draws.append(nearest_point(np.asarray([p for p, _ in lines]), np.asarray([d for _, d in lines]),
                                       scale_m)[0])
    return np.asarray(draws)


def calibrate_flash_on_board(frames: Mapping[str, np.ndarray], device: Mapping, radius_m: float, cols: int,
                             rows: int, square_m: float, min_highlights: int = MIN_HIGHLIGHTS, scale_m: float = 1e-3,
                             samples: int = CENTRE_SAMPLES, seed: int = 0, log=None) -> FlashResult:
    """The flash position from spheres resting on the checkerboard (``cols`` x ``rows`` inner corners, squares of
    ``square_m``) at square centres. ``frames``: pairs NAME (spheres on the board) and NAME_board (the board alone,
    same camera position, :data:`BOARD_SUFFIX`). The board frame's pose (:func:`board_pose`) fixes each sphere's
    centre: ``radius_m`` above its square's centre (:func:`board_sphere_marks`); the highlight's mirror line as in
    the module docstring. The 1-sigma adds to the lines' spread the flash's spread over ``samples`` draws of every
    board's pose (its covariance) and the intrinsics (``device['calibration']['intrinsics']['std_px']``, when
    there): the error the centres share (:func:`solve_flash`)."""
    pairs, left_out = _pairs(frames)
    std = (device.get("calibration") or {}).get("intrinsics", {}).get("std_px", {}) or {}
    points, directions, records, used, labels = [], [], [], [], []
    image_size = (0, 0)
    poses: dict[str, BoardPose] = {}
    for name, board_name in pairs.items():
        pose, problem = board_pose(frames[board_name], device, cols, rows, square_m)
        if problem:
            left_out[board_name] = f"board not found or unusable: {problem}"
            if log:
                log(f"{board_name}: {problem}")
            continue
        poses[name] = pose
        analyzers, intrinsics = develop_frame(frames[name], device)
        s0 = intensity(analyzers)
        s0_board = intensity(develop_frame(frames[board_name], device)[0])
        image_size = (s0.shape[1], s0.shape[0])
        marks, spots = board_sphere_marks(s0, s0_board, intrinsics, pose, cols, rows, square_m, radius_m)
        for where, why in spots.items():
            left_out[f"{name} {where}"] = why
        if not marks:
            left_out[name] = "no sphere highlight on the board (expected glossy spheres set down on squares' centres)"
        f = float(np.sqrt(intrinsics["fx"] * intrinsics["fy"]))
        for k, mark in enumerate(marks):
            centre = sphere_centre(pose.rotation, pose.tvec, mark, radius_m)
            centroid = np.array([intrinsics["fx"] * centre[0] / centre[2] + intrinsics["cx"],
                                 intrinsics["fy"] * centre[1] / centre[2] + intrinsics["cy"]])
            sphere = Sphere(centre, f * radius_m / float(np.linalg.norm(centre)), centroid)
            label = f"{name}#{k} on square ({1e3 * mark[0]:.0f}, {1e3 * mark[1]:.0f}) mm"
            found = highlight_rays(s0, sphere, [centre], radius_m, intrinsics, label, left_out,
                                   "the highlight's ray misses the sphere (wrong --sphere-radius-mm or --square-mm?)",
                                   log)
            if found is None:
                continue
            highlight, (line,) = found
            points.append(line[0])
            directions.append(line[1])
            used.append((name, mark, highlight))
            records.append({"frame": name, "sphere": k, "mark_m": mark.tolist(), "centre_m": centre.tolist(),
                            "highlight_px": highlight.tolist()})
            labels.append(label)
    if len(points) < min_highlights:
        raise too_few_highlights(len(points), min_highlights, left_out)
    points, directions = np.asarray(points), np.asarray(directions)
    keep = drop_outlier_highlights(points, directions, labels, left_out, scale_m, min_highlights, log)
    points, directions = points[keep], directions[keep]
    records = [r for r, k in zip(records, keep) if k]
    used = [u for u, k in zip(used, keep) if k]
    draws = _centre_draws(poses, used, device, std, radius_m, samples, seed, scale_m, min_highlights)
    position, cov, distances, centre = solve_flash(points, directions, scale_m, np.asarray(draws))
    cov = cov + shared_highlight_covariance(records, radius_m, intrinsics, position, scale_m)
    for record, distance in zip(records, distances):
        record["residual_mm"] = float(distance * 1e3)
    return FlashResult(position_m=position, std_m=np.sqrt(np.diag(cov)),
                       rms_mm=float(np.sqrt(np.mean(distances ** 2)) * 1e3), highlights=records, left_out=left_out,
                       image_size=image_size, centre_std_m=np.sqrt(np.diag(centre)), protocol="board",
                       dropped=int(np.sum(~keep)))
