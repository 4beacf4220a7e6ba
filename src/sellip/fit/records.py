"""The per-vertex fit's settings and records: :class:`FitSettings`, the status codes, the model
codes (which lobes), :class:`Observations` (the fit's input), :class:`VirtualSamples`, :class:`FitResult`.

Arrays are batch-first: N vertices with K view slots each; unused slots have weight 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from sellip.model.pbrdf import PBRDFParams
from sellip.settings import setting

STATUS_FITTED = 0
STATUS_TOO_FEW_VIEWS = 1
STATUS_FAILED = 2
STATUS_NAMES = {STATUS_FITTED: "fitted", STATUS_TOO_FEW_VIEWS: "too few views", STATUS_FAILED: "failed"}

ETA_BOUNDS = (1.05, 3.0)
SIGMA_BOUNDS = (0.01, 1.0)
LOBE_GAP = 0.1  # sigma_ss >= sigma_s + LOBE_GAP
LOBE_SETS = ("diffuse", "specular", "full")
"""The reflection lobes a fit may use (docs/design.md §7 model selection): none, the specular lobe, or
specular and single scattering (with sigma_ss free, or fixed by ``FitSettings.sigma_ss_fixed``)."""

MODELS = (0, 1, 2, 3)
"""The per-vertex model codes, simplest first (:data:`sellip.model.params.MODEL_NAMES`): 0 diffuse,
1 + specular, 2 + single scattering with sigma_ss fixed, 3 + single scattering (:mod:`sellip.fit.selection`)."""

DEFAULT_FIXED_SIGMA_SS = 0.9
"""Model 2's sigma_ss when the fit settings do not fix it (paper §6: 0.9 or 1.0): the default of config
``model_selection.model2_sigma_ss`` (:class:`sellip.fit.selection.SelectionSettings`)."""


DTYPES = ("float32", "float64")
"""The fit's floating-point types (``FitJobSettings.dtype``)."""


@dataclass(frozen=True)
class FitJobSettings:
    """The fit jobs' own settings (config section ``fit``, beside its ``settings``, the :class:`FitSettings`; each
    declared once here, :mod:`sellip.settings`): ``sellip fit``, ``sellip gather-fit``, ``sellip cluster-lobes``.
    The section's ``shards``, ``threads`` and ``mem_mb`` are Snakemake's (the scatter count and the jobs'
    resources), declared in config/config.yaml."""

    min_fitted_share: float = setting(0.25, "no result without evidence: a pass whose fitted vertices are less than "
                                      "this share of the vertices some view sees (lit, unoccluded) stops the run, "
                                      "saying what is missing, instead of writing a model of the fit's prior; 0: no "
                                      "check", unit="fraction", minimum=0, maximum=1)
    dtype: str = setting("float32", "the fit's floating-point type (float32: fast)", choices=DTYPES)
    compilation_cache: str | None = setting("results/.jax_cache", "XLA's persistent compilation cache, shared by "
                                            "every fit and cluster-lobes job (null: none)", unit="directory")


@dataclass(frozen=True)
class FitSettings:
    """Settings of the per-vertex fit (config sections ``fit.settings``, ``augment.settings``, ``final.settings``;
    each field declared once here: :func:`sellip.settings.setting`)."""

    lambda_psi: float = setting(100.0, "weight of the degree-of-polarization residual (docs/design.md §5 starts at 1; "
                                "100 with dimensionless residuals, docs/fit.md)", minimum=0, per_iteration=True)
    lambda_d: float = setting(100.0, "weight of the diffuse intensity residual", minimum=0, per_iteration=True)
    lambda_s: float = setting(1.0, "weight of the specular intensity residual", minimum=0, per_iteration=True)
    lambda_phi: float = setting(100.0, "weight of the polarization azimuth residual", minimum=0, per_iteration=True)
    max_iterations: int = setting(30, "Levenberg-Marquardt iterations per stage", minimum=1, per_iteration=True)
    normal_stage_iterations: int = setting(10, "iterations of the first stage (normal and eta, roughness held)",
                                           minimum=0)
    tolerance: float = setting(1e-3, "relative loss decrease (of a near Gauss-Newton step) at which LM stops",
                               exclusive_minimum=0)
    gradient_tolerance: float = setting(1e-3, "... or when the residual is this close to orthogonal to the Jacobian",
                                        exclusive_minimum=0)
    min_views: int = setting(4, "a vertex seen in fewer usable views keeps its prior (status 'too few views', "
                             "confidence 0); with more, the fit's own uncertainty (the confidence) says what its "
                             "views tell (why 4: docs/geometry_update.md)", minimum=3)
    dark_threshold: float = setting(0.02, "a view is too dark below this fraction of the vertex's median diffuse "
                                    "level", minimum=0)
    chroma_threshold: float = setting(0.2, "colour outlier: distance of the unit-norm colour to the robust mean "
                                      "colour", minimum=0)
    outlier_threshold: float = setting(4.0, "a view is an outlier when its residual exceeds this many robust sigmas "
                                       "...", unit="robust sigmas", exclusive_minimum=0)
    outlier_floor: float = setting(0.05, "... and this relative error", minimum=0)
    shading_outlier_floor: float = setting(0.9, "a shading outlier is also this far off the median apparent albedo "
                                           "(log; 0.9: 2.5x)", minimum=0)
    sigma_ss_fixed: float | None = setting(None, "every vertex's single-scattering sigma_ss held at this value instead "
                                           "of fitted (paper §6: 0.9 or 1.0; null: fitted); the most complex model "
                                           "is then 2", minimum=0.02, maximum=1)
    lobes: str = setting("full", "reflection lobes of the most complex model allowed: diffuse (none), specular (no "
                         "single scattering), full", choices=LOBE_SETS)
    round_iterations: int = setting(4, "LM iterations between compactions of the still-running vertices", minimum=1)
    lm_batch: int = setting(512, "vertices advanced together by one compiled LM kernel", minimum=1)
    chunk_size: int = setting(8192, "vertices prepared and finalized together (bounds memory)", minimum=1)
    fit_normal: bool = setting(True, "fit the normal; false holds it at the start normal (the augmented refit, "
                               "docs/augment.md)")
    lambda_g: float = setting(0.1, "weight of the virtual specular samples against the real views (paper Eq. 24)",
                              minimum=0)
    virtual_count: int = setting(180, "virtual samples per vertex, at theta_h = 0, step, ..., (count - 1) step",
                                 minimum=1)
    virtual_step_deg: float = setting(0.5, "theta_h spacing of the virtual samples", unit="degrees",
                                      exclusive_minimum=0)
    hold_diffuse_eta: bool = setting(True, "the diffuse intensity's Fresnel transmissions at a held eta (each LM "
                                     "stage's result), so that eta comes from the polarization and the specular "
                                     "lobe, not from the shading's falloff (docs/fit.md); false: the fitted eta")

    def __post_init__(self):
        if self.lobes not in LOBE_SETS:
            raise ValueError(f"FitSettings.lobes must be one of {LOBE_SETS}, got {self.lobes!r}")


def model_of(settings: FitSettings) -> int:
    """The model code (:data:`MODELS`) a FitSettings fits: its lobe set and whether sigma_ss is fixed."""
    if settings.lobes == "diffuse":
        return 0
    if settings.lobes == "specular":
        return 1
    return 2 if settings.sigma_ss_fixed is not None else 3


def model_arrays(models, sigma_ss_fixed: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex models (N,) (:data:`MODELS`) as the fit kernels take them: lobe_mask (N, 2), 1 where the
    model has the specular / single-scattering lobe, and the fixed sigma_ss (N,): ``sigma_ss_fixed``
    for model 2, NaN (free or absent) otherwise."""
    models = np.asarray(models)
    if models.size and (models.min() < 0 or models.max() > MODELS[-1]):
        raise ValueError(f"models must be in {MODELS}, got {np.unique(models).tolist()}")
    lobe_mask = np.stack([models >= 1, models >= 2], -1).astype(np.float64)
    return lobe_mask, np.where(models == 2, float(sigma_ss_fixed), np.nan)


class Observations(NamedTuple):
    """Observations of N vertices in K view slots (unused slots: weight 0).

    diffuse, diffuse_pol, specular: (N, K, 3) I_d, I_alpha, I_s (exposure-normalized linear RGB).
    to_light, to_camera, camera_up, light_axis: (N, K, 3) unit vectors (world): surface -> flash,
    surface -> camera, the camera's up axis, the flash polarizer axis; light_distance: (N, K) metres.
    usable: (N, K) bool, the view sees the vertex and its pixels are valid (not saturated).
    """

    diffuse: jnp.ndarray
    diffuse_pol: jnp.ndarray
    specular: jnp.ndarray
    to_light: jnp.ndarray
    to_camera: jnp.ndarray
    light_distance: jnp.ndarray
    camera_up: jnp.ndarray
    light_axis: jnp.ndarray
    usable: jnp.ndarray


class VirtualSamples(NamedTuple):
    """Virtual specular observations of N vertices (paper Eq. 24, docs/augment.md), M per vertex.

    Each is an exactly coaxial view (theta_i = theta_o = theta_h, theta_d = 0) at the vertex's
    median flash distance. theta_h: (N, M) radians. reflectance: (N, M, 3) the reflection lobes
    per unit shading, R+(0; eta) (rho_s kappa_s + rho_ss kappa_ss) (:func:`virtual_reflectance`),
    in the units of the fitted albedos. weight: (N, M) w^a, normalized cos theta_h (sum 1 per
    vertex; all 0 for a vertex without virtual samples); the fit scales it by ``lambda_g``.
    """

    theta_h: jnp.ndarray
    reflectance: jnp.ndarray
    weight: jnp.ndarray


class FitResult(NamedTuple):
    """Per-vertex results, each batch-first: normal (N, 3), params (PBRDFParams with batch N),
    status (N,) int, confidence (N,) in [0, 1], loss (N,), views_used (N,), iterations (N,), and the
    Gauss-Newton standard deviations normal_std_deg (N,) and eta_std (N,) the confidence comes from
    (inf where the vertex was not fitted or its Gauss-Newton matrix is singular; confidence 0 there),
    and sigma_s_std (N,), the same for the specular roughness (whether a vertex's lobe differs from
    its material's, :func:`sellip.fit.lobes.material_or_own`)."""

    normal: jnp.ndarray
    params: PBRDFParams
    status: jnp.ndarray
    confidence: jnp.ndarray
    loss: jnp.ndarray
    views_used: jnp.ndarray
    iterations: jnp.ndarray
    normal_std_deg: jnp.ndarray
    eta_std: jnp.ndarray
    sigma_s_std: jnp.ndarray


