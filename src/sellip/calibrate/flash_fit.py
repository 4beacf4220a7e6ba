"""The flash as the point nearest the highlights' mirror lines: the robust fit, its covariance and the outlier test
shared by both protocols of the flash step (:mod:`sellip.calibrate.flash`, :mod:`sellip.calibrate.board_spheres`).

Public API::

    nearest_point(points (N, 3), directions (N, 3), scale_m=0.001) -> (X (3,), distances (N,), weights (N,))
    solve_flash(points, directions, scale_m, centre_samples) -> (X, covariance, distances, centres' covariance)
    drop_outliers(points, directions, scale_m, min_lines) -> (keep (N,) bool, [Outlier])   # leave-one-out
    drop_outlier_highlights(points, directions, labels, left_out, scale_m, min_lines) -> keep   # named, logged

Lines are P_i + t d_i (camera coordinates, metres; unit directions). A line's residual is its distance from X.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def nearest_point(points: np.ndarray, directions: np.ndarray, scale_m: float = 1e-3, iterations: int = 50
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The point X (3,) nearest lines P_i + t d_i (points, unit directions (N, 3)) in the Huber sense: IRLS on
    sum_i w_i |(I - d_i d_i^T)(X - P_i)|^2, the Huber scale ``scale_m`` or, when the lines scatter more, twice the
    median distance after a fifth of the iterations (so that the lines' ordinary scatter keeps full weight and
    only an outlier is down-weighted). Returns (X, distances (N,), final weights (N,))."""
    projectors = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    weights = np.ones(len(points))
    x = np.zeros(3)
    for iteration in range(iterations):
        a = np.einsum("n,nij->ij", weights, projectors)
        b = np.einsum("n,nij,nj->i", weights, projectors, points)
        x = np.linalg.solve(a, b)
        distances = np.linalg.norm(np.einsum("nij,nj->ni", projectors, x - points), axis=-1)
        if iteration == iterations // 5:
            scale_m = max(scale_m, 2 * float(np.median(distances)))
        weights = np.where(distances <= scale_m, 1.0, scale_m / np.maximum(distances, 1e-15))
    return x, distances, weights


def solve_flash(points: np.ndarray, directions: np.ndarray, scale_m: float = 1e-3,
                centre_samples: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The flash X (3,) from mirror lines (points, unit directions (N, 3), :func:`nearest_point`) with its
    covariance: the lines' spread (sigma^2 (sum_i w_i (I - d_i d_i^T))^-1, sigma^2 from the weighted residuals,
    2 N - 3 degrees of freedom) plus ``centre_samples`` (S, 3): the flash recomputed with the sphere centres
    (and whatever else they hang on) drawn from their error model, whose covariance is added -- the lines' spread
    cannot see an error that all centres share. Returns (X, covariance (3, 3), distances (N,), centre part (3, 3))."""
    position, distances, weights = nearest_point(points, directions, scale_m)
    projectors = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    dof = max(len(points) * 2 - 3, 1)
    sigma2 = float(np.sum(weights * distances ** 2) / dof)
    cov = sigma2 * np.linalg.inv(np.einsum("n,nij->ij", weights, projectors))
    centre = np.zeros((3, 3))
    if centre_samples is not None and len(centre_samples) > 1:
        centre = np.atleast_2d(np.cov(np.asarray(centre_samples).T, bias=True))
    return position, cov + centre, distances, centre


OUTLIER_SIGMA = 5.0
"""A highlight is an outlier when its mirror line passes farther than this many sigmas from the flash fitted to the
other highlights; sigma is the others' residual per axis, sqrt(sum d_j^2 / (2 (N - 1) - 3)). A line's distance from
the true point is Rayleigh-distributed for Gaussian errors: beyond 5 sigma with probability exp(-12.5) = 4e-6."""

OUTLIER_FLOOR_M = 5e-4
"""The sigma that :data:`OUTLIER_SIGMA` multiplies is at least this (m), so a line within 2.5 mm of the others' flash
is never an outlier (it moves the flash by a fraction of the 2 mm target). The lines' own residual sigma measured
1.2-1.6 mm at 612x512 and 0.2 mm or less at 1224x1024; with a floor of 0.2 mm a clean Mitsuba highlight 1.0 mm off
was dropped (5.2 sigma) for nothing."""

MAX_OUTLIER_SHARE = 0.25
"""At most this share of the highlights is dropped as outliers: more is a spread the 1-sigma must show, not a few
bad spheres."""


@dataclass
class Outlier:
    """A highlight dropped by :func:`drop_outliers`: its index, its line's distance from the flash fitted to the
    others (m), that fit's residual sigma (m) and their ratio."""

    index: int
    distance_m: float
    sigma_m: float

    @property
    def ratio(self) -> float:
        return self.distance_m / self.sigma_m


def drop_outliers(points: np.ndarray, directions: np.ndarray, scale_m: float = 1e-3,
                  min_lines: int = 6) -> tuple[np.ndarray, list[Outlier]]:
    """Leave-one-out outlier test of mirror lines (points, unit directions (N, 3)): each line's distance from the
    point :func:`nearest_point` fits to the others, against their residual sigma (per axis, 2 (N - 1) - 3 degrees of
    freedom, at least :data:`OUTLIER_FLOOR_M`). The line farthest in sigmas is dropped while it is beyond
    :data:`OUTLIER_SIGMA`, then the test repeats on the rest; it stops at ``min_lines`` lines or
    :data:`MAX_OUTLIER_SHARE` dropped. Returns (keep (N,) bool, the dropped lines in the order dropped)."""
    count = len(points)
    keep = np.ones(count, bool)
    dropped: list[Outlier] = []
    projectors = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    while keep.sum() > min_lines and len(dropped) < int(MAX_OUTLIER_SHARE * count):
        worst = None
        for i in np.flatnonzero(keep):
            others = keep.copy()
            others[i] = False
            x, distances, _ = nearest_point(points[others], directions[others], scale_m)
            sigma = max(float(np.sqrt(np.sum(distances ** 2) / max(2 * others.sum() - 3, 1))), OUTLIER_FLOOR_M)
            candidate = Outlier(int(i), float(np.linalg.norm(projectors[i] @ (x - points[i]))), sigma)
            if worst is None or candidate.ratio > worst.ratio:
                worst = candidate
        if worst is None or worst.ratio <= OUTLIER_SIGMA:
            break
        keep[worst.index] = False
        dropped.append(worst)
    return keep, dropped


def drop_outlier_highlights(points: np.ndarray, directions: np.ndarray, labels: list[str], left_out: dict,
                            scale_m: float, min_highlights: int, log=None) -> np.ndarray:
    """:func:`drop_outliers` on both protocols' highlights: each dropped one is recorded in ``left_out`` under its
    ``labels`` entry (frame and sphere) with its residual and sigma, and logged. Returns keep (N,) bool."""
    keep, dropped = drop_outliers(points, directions, scale_m, min_highlights)
    for outlier in dropped:
        why = (f"highlight residual {1e3 * outlier.distance_m:.1f} mm from the flash fitted to the others, "
               f"{outlier.ratio:.1f} sigma of their residual ({1e3 * outlier.sigma_m:.2f} mm; more than "
               f"{OUTLIER_SIGMA:g} sigma): dropped as an outlier and the flash refitted (a sphere off its square's "
               "centre or on the wrong square, a wrong outline, a sphere of another radius)")
        left_out[labels[outlier.index]] = why
        if log:
            log(f"{labels[outlier.index]}: {why}")
    return keep
