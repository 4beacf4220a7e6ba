"""The sensor mosaic: which analyzer angle and which colour each raw pixel sees.

A colour polarization sensor (Sony IMX250MYR) has a 2x2 cell of polarizers
(``polarizer_layout``, angles in the convention of :mod:`sellip.model.conventions`)
and a Bayer filter over those 2x2 cells, so its mosaic repeats every 4x4
pixels. A mono polarization sensor (IMX250MZR) repeats every 2x2 pixels.
Both the sensor simulator and the demosaicer use these maps, so the two can
never disagree about the layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sellip.model.conventions import ANALYZER_ANGLES_DEG

COLOR_LAYOUTS = ("RGGB", "BGGR", "GRBG", "GBRG", "mono")
_COLOR_INDEX = {"R": 0, "G": 1, "B": 2}


class MosaicError(ValueError):
    """A polarizer or colour layout that sellip cannot interpret."""


@dataclass(frozen=True)
class MosaicLayout:
    """Per-position analyzer and colour indices of one mosaic period.

    analyzer: (P, P) int, index into :data:`ANALYZER_ANGLES_DEG` for each pixel of the period.
    color: (P, P) int, 0/1/2 for R/G/B (all 0 for mono).
    period: P = 4 for colour, 2 for mono.
    """

    analyzer: np.ndarray
    color: np.ndarray
    period: int

    @property
    def channels(self) -> int:
        """Colour channels after demosaicing: 3, or 1 for a mono sensor."""
        return 1 if self.period == 2 else 3

    def analyzer_map(self, height: int, width: int) -> np.ndarray:
        """(H, W) analyzer index of every raw pixel."""
        return np.tile(self.analyzer, (height // self.period, width // self.period))

    def color_map(self, height: int, width: int) -> np.ndarray:
        """(H, W) colour index of every raw pixel."""
        return np.tile(self.color, (height // self.period, width // self.period))


def mosaic_layout(polarizer_layout, color_layout: str) -> MosaicLayout:
    """Build the mosaic period from capture.yaml's ``polarizer_layout`` and ``color_layout``.

    polarizer_layout: 2x2 nested list of angles in degrees (row-major), a
    permutation of 0, 45, 90, 135. color_layout: one of :data:`COLOR_LAYOUTS`.
    """
    angles = np.asarray(polarizer_layout)
    if angles.shape != (2, 2) or sorted(angles.ravel().tolist()) != sorted(ANALYZER_ANGLES_DEG):
        raise MosaicError(
            f"polarizer_layout must be a 2x2 arrangement of the angles {list(ANALYZER_ANGLES_DEG)}, "
            f"got {polarizer_layout!r}"
        )
    pol = np.vectorize(ANALYZER_ANGLES_DEG.index)(angles).astype(np.int64)
    if color_layout not in COLOR_LAYOUTS:
        raise MosaicError(f"color_layout must be one of {list(COLOR_LAYOUTS)}, got {color_layout!r}")
    if color_layout == "mono":
        return MosaicLayout(analyzer=pol, color=np.zeros((2, 2), np.int64), period=2)
    bayer = np.array([[_COLOR_INDEX[color_layout[0]], _COLOR_INDEX[color_layout[1]]],
                      [_COLOR_INDEX[color_layout[2]], _COLOR_INDEX[color_layout[3]]]])
    analyzer = np.tile(pol, (2, 2))
    color = np.kron(bayer, np.ones((2, 2), np.int64))
    return MosaicLayout(analyzer=analyzer, color=color, period=4)
