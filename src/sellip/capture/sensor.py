"""Sensor simulation: the IMX250MYR colour-polarization mosaic (docs/design.md §3) from rendered analyzer images.

Public API::

    SensorModel(width, height, ...)            # layout, levels, noise, colour matrix
    SensorModel.capture_sensor() -> dict        # capture.yaml ``sensor`` section
    SensorModel.with_noise_scale(k) -> SensorModel   # noise standard deviations x k at the same signal
    sensor_from_device(sensor, color_matrix=None) -> SensorModel   # from capture.yaml / device.yaml sections
    camera_rgb_from_srgb(srgb, color_matrix) -> camera RGB (..., 3)
    mosaic_sample(analyzers, layout) -> (H, W)  # each raw pixel's analyzer and colour
    simulate_raw(analyzers, sensor, scale, rng, noise=True) -> (H, W) uint16

Model, per raw pixel: the analyzer image of its polarizer angle and Bayer
colour (:func:`sellip.capture.mosaic.mosaic_layout`, shared with the demosaicer) in
camera RGB (the inverse of capture.yaml's ``color_matrix``, which maps camera
RGB to linear sRGB), times ``scale`` (flash power x flash level, in DN), is the
mean signal; the sensor counts Poisson photo-electrons (``gain_e_per_dn``
electrons per DN), adds Gaussian read noise (``read_noise_e``), adds the
black level, rounds to integers and clips at the white level (saturation).
Mono sensors (``color_layout: mono``) see the sRGB luminance.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from sellip.capture.mosaic import MosaicLayout, mosaic_layout

IMX250_POLARIZER_LAYOUT = ((90, 45), (135, 0))
"""Angles of the IMX250MYR's 2x2 polarizer cell (row-major) in sellip's convention."""

DEFAULT_COLOR_MATRIX = (
    (3.0909, -0.55, -0.2),
    (-0.4545, 1.55, -0.4),
    (0.0909, -0.6, 2.0667),
)
"""Camera RGB -> linear sRGB: [[1.7, -0.55, -0.15], [-0.25, 1.55, -0.3], [0.05, -0.6, 1.55]] (rows sum
to 1) times diag(1 / (0.55, 1, 0.75)), the inverse channel sensitivities, rounded: white light reads
about (0.55, 1, 0.75) in camera RGB."""

SRGB_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True)
class SensorModel:
    """Raw sensor: size, mosaic, levels and noise of the LUCID PHX050S-QC (IMX250MYR) by default.

    gain_e_per_dn: electrons per DN (10.4 ke- full well over 4031 DN); read_noise_e: electrons RMS;
    black_level: DN, a scalar or one value per mosaic position (P, P); color_matrix: camera RGB -> sRGB.
    """

    width: int
    height: int
    bit_depth: int = 12
    black_level: float | tuple = 64
    white_level: int = 4095
    polarizer_layout: tuple = IMX250_POLARIZER_LAYOUT
    color_layout: str = "RGGB"
    gain_e_per_dn: float = 2.58
    read_noise_e: float = 2.4
    color_matrix: tuple = field(default=DEFAULT_COLOR_MATRIX)

    @property
    def layout(self) -> MosaicLayout:
        return mosaic_layout(self.polarizer_layout, self.color_layout)

    def capture_sensor(self) -> dict:
        """The ``sensor`` section of capture.yaml (docs/design.md §3)."""
        black = np.asarray(self.black_level)
        return {
            "width": int(self.width),
            "height": int(self.height),
            "bit_depth": int(self.bit_depth),
            "black_level": black.tolist() if black.ndim else float(black) if black % 1 else int(black),
            "white_level": int(self.white_level),
            "polarizer_layout": [list(map(int, row)) for row in self.polarizer_layout],
            "color_layout": self.color_layout,
        }

    def with_noise_scale(self, scale: float) -> SensorModel:
        """The same sensor with both noise standard deviations (in DN) multiplied by ``scale`` at the same mean signal.

        gain_e_per_dn / scale**2 (scale**2 fewer photo-electrons per DN: shot noise x scale) and
        read_noise_e / scale (read noise in DN = read_noise_e / gain_e_per_dn: x scale). Physically: the
        flash delivers 1/scale**2 of the photons and the analog gain is scale**2 higher. scale 1: unchanged.
        """
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError(f"noise scale must be a positive number, got {scale!r}")
        return replace(self, gain_e_per_dn=self.gain_e_per_dn / scale ** 2, read_noise_e=self.read_noise_e / scale)

    def black_map(self) -> np.ndarray:
        """(H, W) black level of every raw pixel."""
        black = np.asarray(self.black_level, np.float64)
        if black.ndim == 0:
            return np.full((self.height, self.width), float(black))
        period = black.shape[0]
        return np.tile(black, (self.height // period, self.width // period))


def sensor_from_device(sensor, color_matrix=None) -> SensorModel:
    """The :class:`SensorModel` of a capture.yaml / device.yaml ``sensor`` section (mapping) with ``color_matrix``
    (camera.color_matrix, camera RGB -> linear sRGB; None: the default); noise of the real device."""
    black = sensor.get("black_level", 64)
    return SensorModel(width=int(sensor["width"]), height=int(sensor["height"]),
                       bit_depth=int(sensor.get("bit_depth", 12)),
                       black_level=tuple(map(tuple, black)) if isinstance(black, (list, tuple)) else black,
                       white_level=int(sensor.get("white_level", 4095)),
                       polarizer_layout=tuple(map(tuple, sensor.get("polarizer_layout", IMX250_POLARIZER_LAYOUT))),
                       color_layout=sensor.get("color_layout", "RGGB"),
                       color_matrix=DEFAULT_COLOR_MATRIX if color_matrix is None
                       else tuple(tuple(map(float, row)) for row in color_matrix))


def camera_rgb_from_srgb(srgb: np.ndarray, color_matrix) -> np.ndarray:
    """Camera RGB (..., 3) that ``color_matrix`` (camera RGB -> linear sRGB, (3, 3)) maps to ``srgb`` (..., 3)."""
    inverse = np.linalg.inv(np.asarray(color_matrix, np.float64))
    return srgb @ inverse.T


def mosaic_sample(analyzers: np.ndarray, layout: MosaicLayout, color_transform=None) -> np.ndarray:
    """Pick each raw pixel's analyzer and colour: analyzers (H, W, 4, C) -> (H, W).

    Without ``color_transform`` the colour index of each pixel selects one of the C channels.
    With it ((K, C) matrix, K sensor colours), a pixel of colour k sees ``color_transform[k] @ rgb``;
    the transform is applied after the analyzer selection, so only one colour per pixel is computed.
    """
    height, width = analyzers.shape[:2]
    analyzer_index = layout.analyzer_map(height, width)[:, :, None, None]
    chosen = np.take_along_axis(analyzers, analyzer_index, axis=2)[:, :, 0, :]  # (H, W, C)
    color_index = layout.color_map(height, width)
    if color_transform is None:
        return np.take_along_axis(chosen, color_index[..., None], axis=-1)[..., 0]
    rows = np.asarray(color_transform, chosen.dtype)[color_index]  # (H, W, C)
    return np.einsum("hwc,hwc->hw", rows, chosen)


def sensor_mosaic(analyzers: np.ndarray, layout: MosaicLayout, color_matrix=None) -> np.ndarray:
    """The noiseless linear mosaic (H, W) that linear-sRGB analyzer images (H, W, 4, 3) put on the sensor:
    camera RGB by the inverse of ``color_matrix`` (camera RGB -> linear sRGB, (3, 3); None: identity), or
    luminance for a mono sensor, sampled by ``layout``."""
    return mosaic_sample(analyzers, layout, sensor_colors(layout, color_matrix))


def sensor_colors(layout: MosaicLayout, color_matrix=None) -> np.ndarray:
    """(K, 3) what each of the sensor's K colours sees of linear sRGB: the inverse of ``color_matrix`` (camera RGB
    -> linear sRGB; None: identity), or the luminance for a mono sensor."""
    if layout.channels == 1:
        return SRGB_LUMINANCE[None, :]
    return np.linalg.inv(np.asarray(np.eye(3) if color_matrix is None else color_matrix, np.float64))


def simulate_raw(analyzers: np.ndarray, sensor: SensorModel, scale: float, rng: np.random.Generator | None,
                 noise: bool = True) -> np.ndarray:
    """Raw mosaic (H, W) uint16 from linear-sRGB analyzer images (H, W, 4, 3) (I0, I45, I90, I135).

    scale: DN above black per unit of ``analyzers`` (flash power x flash level). rng: the noise
    source (unused when ``noise`` is False: the result is then the rounded, clipped mean signal).
    """
    if analyzers.shape[:2] != (sensor.height, sensor.width):
        raise ValueError(f"analyzer images are {analyzers.shape[:2]}, sensor is {(sensor.height, sensor.width)}")
    signal_dn = np.clip(sensor_mosaic(analyzers, sensor.layout, sensor.color_matrix), 0, None) * scale
    if noise:
        # Cap the Poisson mean far above saturation: the output clips there anyway.
        electrons = rng.poisson(np.minimum(signal_dn, 4.0 * sensor.white_level) * sensor.gain_e_per_dn)
        electrons = electrons + rng.normal(0.0, sensor.read_noise_e, signal_dn.shape)
        signal_dn = electrons / sensor.gain_e_per_dn
    raw = np.rint(signal_dn + sensor.black_map())
    return np.clip(raw, 0, sensor.white_level).astype(np.uint16)
