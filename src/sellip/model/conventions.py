"""The conventions every stage shares, stated and implemented once (docs/design.md §3).

Camera axes
    OpenCV: x right, y down, z forward (into the scene). Poses are COLMAP's
    ``cam_from_world``: ``x_cam = R @ x_world + t``. The rows of ``R`` are the
    camera axes expressed in world coordinates; the camera centre is ``-R.T @ t``.

Stokes frame of a ray arriving at the camera
    x = image right, y = image up, z = towards the camera (the propagation
    direction), right-handed. For an off-axis ray the frame is made orthogonal
    to the ray: z = the ray's propagation direction, y = the camera's up axis
    with its z component removed, x = y x z. Mitsuba 3's ``stokes`` output
    uses the same frame.

Polarizer / analyzer angles
    0 deg is the image x axis; angles grow from x towards -y_image (image up),
    i.e. counter-clockwise as the image is displayed (row 0 on top) and as
    seen by an observer looking back along the beam. An ideal analyzer at
    angle theta transmits ``(s0 + s1 cos 2theta + s2 sin 2theta) / 2``, so

        I0 = (s0 + s1) / 2,  I90 = (s0 - s1) / 2,
        I45 = (s0 + s2) / 2, I135 = (s0 - s2) / 2.

Analyzer arrays
    Four-analyzer data are stacked on the axis before the colour channel in
    the order of :data:`ANALYZER_ANGLES_DEG`: ``(..., 4, C)`` with C = 3 (RGB)
    or 1 (mono); a Stokes vector is ``(..., 4)`` (s0, s1, s2, s3), or
    ``(..., 4, C)`` per colour channel.

Every function here works on numpy or jax arrays (the result has the type of
the input) and keeps the input's dtype.
"""

from __future__ import annotations

import numpy as np

ANALYZER_ANGLES_DEG: tuple[int, ...] = (0, 45, 90, 135)
"""The order of the analyzer axis in every four-analyzer array."""


def _xp(x):
    """The array namespace of ``x``: jax.numpy for jax arrays, else numpy."""
    if type(x).__module__.startswith("jax"):
        import jax.numpy as jnp

        return jnp
    return np


def analyzer_intensity(stokes, theta):
    """Intensity behind an ideal linear analyzer at angle ``theta`` (radians).

    stokes: (..., 4) or (..., 3) Stokes vectors; theta broadcastable to (...).
    Returns (...,).
    """
    xp = _xp(stokes)
    return 0.5 * (stokes[..., 0] + stokes[..., 1] * xp.cos(2 * theta) + stokes[..., 2] * xp.sin(2 * theta))


def stokes_to_analyzers(stokes, axis: int = -1):
    """Four analyzer intensities (I0, I45, I90, I135) from Stokes vectors.

    stokes: Stokes components on ``axis`` (length 3 or 4; s3 is ignored).
    Returns an array with the four intensities on that axis.
    """
    xp = _xp(stokes)
    s = xp.moveaxis(stokes, axis, 0)
    s0, s1, s2 = s[0], s[1], s[2]
    out = xp.stack([(s0 + s1) / 2, (s0 + s2) / 2, (s0 - s1) / 2, (s0 - s2) / 2])
    return xp.moveaxis(out, 0, axis)


def analyzers_to_stokes(analyzers, axis: int = -1):
    """Linear Stokes components (s0, s1, s2) from (I0, I45, I90, I135) on ``axis``.

    s0 uses all four intensities: (I0 + I45 + I90 + I135) / 2.
    """
    xp = _xp(analyzers)
    a = xp.moveaxis(analyzers, axis, 0)
    i0, i45, i90, i135 = a[0], a[1], a[2], a[3]
    out = xp.stack([(i0 + i45 + i90 + i135) / 2, i0 - i90, i45 - i135])
    return xp.moveaxis(out, 0, axis)


def observations_from_analyzers(analyzers, axis: int = -2):
    """The three observations of docs/design.md §5 from four analyzer intensities.

    analyzers: (..., 4, C) by default (``axis`` selects the analyzer axis).
    Returns ``(I_d, I_alpha, I_s)``, each (..., C):
    I_d = 2 I90 (diffuse), I_alpha = I135 - I45 (diffuse polarization),
    I_s = I0 - I90 (specular-dominant).
    """
    xp = _xp(analyzers)
    a = xp.moveaxis(analyzers, axis, 0)
    i0, i45, i90, i135 = a[0], a[1], a[2], a[3]
    return 2 * i90, i135 - i45, i0 - i90


def camera_center(rotation, translation):
    """Camera centre in world coordinates, ``-R^T t``. rotation (..., 3, 3), translation (..., 3)."""
    xp = _xp(rotation)
    return -xp.einsum("...ji,...j->...i", rotation, translation)


def camera_right(rotation):
    """Image x axis (right) in world coordinates: the first row of R. (..., 3)."""
    return rotation[..., 0, :]


def camera_up(rotation):
    """The camera's up axis in world coordinates: minus the second row of R (OpenCV y is down)."""
    return -rotation[..., 1, :]


def camera_forward(rotation):
    """The optical axis (into the scene) in world coordinates: the third row of R."""
    return rotation[..., 2, :]


def camera_to_world_point(rotation, translation, point_cam):
    """A point given in camera coordinates (e.g. the flash position) in world coordinates.

    Solves ``x_cam = R x_world + t``: ``x_world = R^T (x_cam - t)``.
    """
    xp = _xp(rotation)
    return xp.einsum("...ji,...j->...i", rotation, point_cam - translation)


def quaternion_to_rotation(q):
    """Rotation matrices (..., 3, 3) from unit quaternions (..., 4) ordered (qw, qx, qy, qz) as in COLMAP."""
    xp = _xp(q)
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def rotation_to_quaternion(rotation):
    """Unit quaternions (..., 4) as (qw, qx, qy, qz), qw >= 0, from rotation matrices (..., 3, 3).

    numpy only (used by the capture writer and SfM I/O).
    """
    from scipy.spatial.transform import Rotation

    r = np.asarray(rotation, dtype=np.float64)
    xyzw = Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    wxyz *= np.where(wxyz[:, :1] < 0, -1.0, 1.0)
    return wxyz.reshape(r.shape[:-2] + (4,))
