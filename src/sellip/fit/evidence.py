"""No result without evidence (docs/design.md §9): a fit that covers too little of the surface the photographs see stops
the run with what is missing, instead of handing on parameters that are the prior or neighbour fills of it.

- :data:`MIN_FITTED_SHARE` -- the declared default of config ``fit.min_fitted_share`` (``FitJobSettings``).
- :func:`fitted_share` -- (fitted, visible) vertex counts of one pass.
- :func:`check_evidence` -- :class:`EvidenceError` below the share, saying what is missing (views, coverage,
  exposure).
"""

from __future__ import annotations

import numpy as np

from sellip.fit.records import STATUS_FAILED, STATUS_FITTED, STATUS_TOO_FEW_VIEWS, FitJobSettings

MIN_FITTED_SHARE = FitJobSettings.min_fitted_share
"""Default of config ``fit.min_fitted_share``: the fitted vertices' share of the visible surface (vertices with at
least one usable view) below which the run stops. Measured shares: docs/reliability.md ("No result without
evidence"); below it, the materials are the fit's prior (eta 1.5, rho_d 0.5) over most of the surface."""


class EvidenceError(ValueError):
    """A pass whose fit covers less of the visible surface than ``fit.min_fitted_share``."""


def fitted_share(status: np.ndarray, usable: np.ndarray) -> tuple[int, int]:
    """(fitted, visible): vertices with status fitted, and vertices with at least one usable view.
    status (N,) int (sellip.fit.records STATUS_*), usable (N, V) bool."""
    visible = np.asarray(usable, bool).any(axis=1) if np.asarray(usable).size else np.zeros(len(status), bool)
    return int(np.sum(np.asarray(status) == STATUS_FITTED)), int(visible.sum())


def check_evidence(status: np.ndarray, usable: np.ndarray, view_ids: list[str],
                   min_share: float = MIN_FITTED_SHARE, where: str = "the fit") -> float:
    """The fitted share of the visible surface (fitted / visible, 0 when nothing is visible); raises EvidenceError
    below ``min_share`` (a fraction in [0, 1]; 0 turns the check off) naming the counts per status and what is missing:
    views (the store has few), coverage (few views see each point), exposure (the views see the object but the fit
    fails)."""
    if not 0 <= min_share <= 1:
        raise ValueError(f"fit.min_fitted_share must be a fraction in [0, 1], got {min_share}")
    status = np.asarray(status)
    usable = np.asarray(usable, bool)
    fitted, visible = fitted_share(status, usable)
    share = fitted / visible if visible else 0.0
    if min_share == 0 or (share >= min_share and visible):
        return share
    too_few = int(np.sum(status == STATUS_TOO_FEW_VIEWS))
    failed = int(np.sum(status == STATUS_FAILED))
    per_vertex = usable.sum(axis=1) if usable.size else np.zeros(len(status), int)
    seen = per_vertex[per_vertex > 0]
    if not visible:
        missing = (f"views: no vertex is seen lit and unoccluded in any of the {len(view_ids)} views; check that the "
                   "poses and the mesh belong to these photographs")
    elif too_few >= failed:
        missing = (f"views: {too_few} vertices have too few usable views (fewer than fit.settings.min_views); the "
                   f"store has {len(view_ids)} view(s) {view_ids[:12]}, and a visible vertex is seen in a median "
                   f"{float(np.median(seen)):g} (at most {int(seen.max())}) of them, lit and unoccluded. Capture more "
                   "views around the object (each point in 8 or more; the method is made for 100-300 photographs), "
                   "or lower fit.settings.min_views for a test")
    else:
        missing = (f"exposure: {failed} vertices failed to fit although seen in a median {float(np.median(seen)):g} "
                   "views; check the HDR previews (results/NAME/previews) for dark or saturated views and the "
                   "flash levels and exposures in frames.csv")
    raise EvidenceError(
        f"{where}: the fit covers {fitted} of {visible} visible vertices ({100 * share:.1f}% of the surface the "
        f"photographs see; {len(status)} vertices in all: {fitted} fitted, {too_few} too few views, {failed} failed),"
        f" less than fit.min_fitted_share = {min_share:g}: its materials would be the fit's prior, not a measurement. "
        f"Missing: {missing}. Nothing is written.")
