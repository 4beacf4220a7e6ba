"""The silhouette benchmark's truth and figures (sellip.bench.silhouettes)."""

from __future__ import annotations

import numpy as np

from sellip.bench.silhouettes import agreement
from sellip.capture.scenes import icosphere
from sellip.model.render import Camera, coverage_masks


def test_a_sphere_seen_head_on_covers_the_disc_of_its_tangent_cone():
    """A sphere of radius r at distance d on the optical axis covers a disc of radius f r / sqrt(d^2 - r^2) pixels
    about the principal point (the inscribed polyhedron a little less: area within 1 %)."""
    radius, distance, focal = 0.05, 0.4, 500.0
    vertices, faces = icosphere(5)
    camera = Camera(intrinsics=np.array([[focal, 0, 159.5], [0, focal, 127.5], [0, 0, 1.0]]), rotation=np.eye(3),
                    translation=np.array([0.0, 0.0, distance]), width=320, height=256)
    mask = coverage_masks(radius * vertices, faces, [camera])[0]
    disc = focal * radius / np.sqrt(distance ** 2 - radius ** 2)
    assert 0.985 < mask.sum() / (np.pi * disc ** 2) < 1.005
    rows, cols = np.nonzero(mask)
    assert abs(rows.mean() - 127.5) < 0.05 and abs(cols.mean() - 159.5) < 0.05


def test_agreement_counts_missed_and_extra_pixels_against_the_true_area():
    truth = np.zeros((1, 10, 10), bool)
    truth[0, :, :5] = True  # 50 pixels
    masks = np.zeros_like(truth)
    masks[0, :, 1:6] = True  # 10 missed, 10 extra
    figures = agreement(masks, truth)
    assert figures["missed"][0] == 0.2 and figures["extra"][0] == 0.2
    assert figures["iou"][0] == 40 / 60
