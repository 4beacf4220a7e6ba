"""The accuracy ladder's figures (sellip.ladder; the rungs themselves run in benchmarks/accuracy_ladder.py)."""

from __future__ import annotations

import numpy as np
import pytest

from sellip.fit import STATUS_FITTED, STATUS_TOO_FEW_VIEWS
from sellip.ladder import figures
from sellip.scenes import build_scene


def test_figures_of_a_fit_on_the_true_mesh():
    truth = build_scene("tiny").mesh
    n = len(truth.vertices)
    eta = np.asarray(truth.params.eta, np.float64).copy()
    status = np.full(n, STATUS_FITTED)
    status[:10] = STATUS_TOO_FEW_VIEWS
    eta[:10] = 9.0  # unfitted rows do not count
    exact = figures({"status": status, "eta": eta, "normal": truth.normals}, truth)
    assert exact["fitted"] == n - 10 and exact["eta_vertex_median_pct"] == 0 and exact["normal_median_deg"] < 1e-6
    assert exact["eta_per_material"]["max_error_pct"] == 0
    biased = figures({"status": status, "eta": 1.02 * eta, "normal": truth.normals}, truth)
    assert biased["eta_per_material"]["mean_error_pct"] == pytest.approx(2.0)
    assert biased["eta_vertex_p90_pct"] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="no vertex"):
        figures({"status": np.full(n, STATUS_TOO_FEW_VIEWS), "eta": eta, "normal": truth.normals}, truth)
