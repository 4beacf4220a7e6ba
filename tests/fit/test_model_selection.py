"""Model selection (sellip.fit.selection, docs/design.md §7): which lobes a cluster needs, and fitting vertices by
model.

One synthetic scene (the renderer and cameras of test_augment.py: the full model, 40 views within
25 deg of +z, 0.5 % noise): three materials of 48 surface points each, a quarter of them facing the
cameras (they see their highlight), the others 10-60 deg away. "specular" has no single scattering,
"scattering" a strong single-scattering lobe, "diffuse" no reflection lobe at all.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_augment import material_scene

from sellip import cli
from sellip.fit import clusters as fit_clusters
from sellip.fit import lobes as fit_lobes
from sellip.fit import records, solver
from sellip.fit import selection as fit_selection
from sellip.fit.records import FitSettings, Observations
from sellip.fit.vertex_fit import default_prior, fit_vertices
from sellip.model.pbrdf import PBRDFParams

MATERIALS = {  # eta, rho_d, rho_s, sigma_s, rho_ss, sigma_ss
    "specular": (1.5, (0.45, 0.25, 0.12), 0.8, 0.15, (0.0, 0.0, 0.0), 0.5),
    "scattering": (1.45, (0.25, 0.25, 0.22), 0.6, 0.2, (0.3, 0.25, 0.2), 0.6),
    "diffuse": (1.6, (0.15, 0.25, 0.45), 0.0, 0.3, (0.0, 0.0, 0.0), 0.5),
}
PER_MATERIAL = 48
HELD = FitSettings(fit_normal=False)  # the refit's settings (normals held at the truth here)
LOBES = fit_clusters.AugmentSettings(min_cluster_vertices=10, max_samples=1000)
SELECTION = fit_selection.SelectionSettings(max_samples=1000)  # the lobe fits' shape: one compilation per model

NO_CACHE = ["--job-settings", '{"compilation_cache": null}']  # the CLI's default is the workflow's cache


def _make_scene(seed=0, views=40, noise=0.005):
    names = list(MATERIALS)
    material = np.repeat(np.arange(len(names)), PER_MATERIAL)
    scene = material_scene(np.random.default_rng(seed), [MATERIALS[name] for name in names], material, views, noise,
                           oblique_deg=(10, 60))
    return {**scene, "names": names}


def _rows(obs, rows):
    return Observations(*[np.asarray(x)[rows] for x in obs])


def _select(scene, name, seed=0, selection=SELECTION):
    rows = np.flatnonzero(scene["material"] == scene["names"].index(name))
    return fit_selection.select_model(_rows(scene["obs"], rows), scene["normals"][rows], scene["params"].rho_d[rows],
                                      1.5, HELD, selection, LOBES, seed=seed)


CLUSTER_KERNELS = ("_stacked", "_stacked_jacobian", "_delta_step_jit", "_pool_solution", "_sample_losses")


@pytest.fixture(scope="module")
def scene():
    """The scene and the selection of each material's cluster (the true normals and albedos held), and
    the compiled forms each cluster kernel holds after them (counted from empty caches)."""
    s = _make_scene()
    for name in CLUSTER_KERNELS:
        getattr(fit_lobes, name).jitted.clear_cache()
    s["selection"] = {name: _select(s, name) for name in MATERIALS}
    s["compiled"] = {name: getattr(fit_lobes, name)._cache_size() for name in CLUSTER_KERNELS}
    return s


@pytest.mark.slow
def test_every_candidate_model_runs_one_compiled_program(scene):
    """The model is data to the cluster kernels, not a static argument: the four candidates of three
    clusters (twelve lobe fits and held-out scorings) compile each kernel once."""
    assert all(len(s.candidates) == 4 for s in scene["selection"].values())
    # _delta_step_jit has two forms whatever the model: albedos solved (the fit) or given (the scoring); it runs
    # in the lobe-or-none question (the lobe fit's Delta theta_h), not in the which-lobes one (none).
    assert SELECTION.max_theta_error_deg == 0
    assert scene["compiled"] == {name: 2 if name == "_delta_step_jit" else 1 for name in CLUSTER_KERNELS}


def test_model_codes_settings_and_caps():
    from sellip.settings import SettingsError, record_from_mapping

    for code in records.MODELS:
        assert records.model_of(fit_selection.settings_for_model(HELD, code)) == code
    assert fit_selection.settings_for_model(HELD, 3) == HELD  # the default settings are model 3: same compiled fit
    assert fit_selection.settings_for_model(HELD, 2, sigma_ss_fixed=0.7).sigma_ss_fixed == 0.7
    fixed = FitSettings(sigma_ss_fixed=1.0)
    assert fit_selection.settings_for_model(fixed, 2, sigma_ss_fixed=0.7).sigma_ss_fixed == 1.0  # the user's value wins
    assert fit_selection.allowed_models(fixed) == [0, 1, 2]
    assert fit_selection.allowed_models(FitSettings(lobes="specular"), (0, 1, 3)) == [0, 1]
    np.testing.assert_array_equal(fit_selection.cap_models([0, 1, 2, 3], fixed), [0, 1, 2, 2])
    assert record_from_mapping(FitSettings, {"lobes": "specular", "fit_normal": False}) == FitSettings(
        lobes="specular", fit_normal=False)
    with pytest.raises(SettingsError, match="lobes"):
        record_from_mapping(FitSettings, {"lobes": "mirror"})
    with pytest.raises(SettingsError, match="'fit.settings.max_iterations': 'many' is not"):
        record_from_mapping(FitSettings, {"max_iterations": "many"}, "fit.settings")
    with pytest.raises(ValueError, match="candidates"):
        fit_selection.SelectionSettings(candidates=(1, 4))
    with pytest.raises(ValueError, match="held_out_fraction"):
        fit_selection.SelectionSettings(held_out_fraction=1.0)


def test_the_rule_takes_the_simplest_model_within_the_tolerance():
    rng = np.random.default_rng(0)
    base = rng.uniform(1.0, 2.0, 20)  # per-vertex held-out losses of the best model
    noise = rng.normal(0, 0.01, 20)
    losses = {0: base * 3, 1: base * 1.005 + noise, 2: base * 1.002, 3: base}
    chosen, best, table = fit_selection.choose(losses, tolerance=0.01, standard_errors=1.0)
    assert (chosen, best) == (1, 3)  # 0.5 % worse: within 1 %
    assert table[0]["excess"] == pytest.approx(2 * base.sum()) and table[3]["excess"] == 0
    # 3 % worse on every vertex alike: beyond 1 % plus one (tiny) standard error.
    chosen, _, table = fit_selection.choose({1: base * 1.03, 3: base}, tolerance=0.01, standard_errors=1.0)
    assert chosen == 3 and table[1]["standard_error"] < 0.01 * table[3]["held_out_loss"]
    # 3 % worse on average but as noisy as that: within one standard error, so the simpler model.
    spread = rng.normal(0, 1, 20)
    spread = 0.3 * (spread - spread.mean()) / spread.std()
    flat = np.full(20, 1.5)
    chosen, best, table = fit_selection.choose({1: flat * (1.03 + spread), 3: flat}, tolerance=0.01,
                                               standard_errors=1.0)
    assert best == 3 and chosen == 1 and table[1]["excess"] == pytest.approx(0.03 * table[3]["held_out_loss"])
    assert fit_selection.choose({1: flat * (1.03 + spread), 3: flat}, tolerance=0.0, standard_errors=0.0)[0] == 3


def test_the_margin_says_how_near_a_choice_is_to_the_rules_boundary():
    def row(excess, allowed):
        return {"held_out_loss": 100.0 + excess, "excess": excess, "standard_error": 0.0, "allowed": allowed}

    # Model 3 best; model 1 rejected by 1.2 x its allowance (0.2 past it), model 0 far away: margin 0.2, runner-up 1.
    table = {0: row(500.0, 10.0), 1: row(2.4, 2.0), 3: row(0.0, 1.0)}
    assert fit_selection.decision_margin(table, 3) == (pytest.approx(0.2), 1)
    # Model 1 chosen within its allowance although model 3 is best: its unused allowance, 3 the runner-up.
    table = {0: row(500.0, 10.0), 1: row(1.5, 2.0), 3: row(0.0, 1.0)}
    assert fit_selection.decision_margin(table, 1) == (pytest.approx(0.25), 3)
    # Chosen and best, every simpler model far off: 1 (capped), the runner-up the next lowest loss.
    table = {0: row(500.0, 10.0), 1: row(0.0, 1.0), 2: row(0.3, 1.0), 3: row(0.1, 1.0)}
    assert fit_selection.decision_margin(table, 1) == (1.0, 3)
    # On the boundary: 0; nothing scored: NaN.
    assert fit_selection.decision_margin({1: row(2.0, 2.0), 3: row(0.0, 1.0)}, 3)[0] == 0.0
    margin, runner_up = fit_selection.decision_margin({}, 1)
    assert np.isnan(margin) and runner_up is None


def test_a_small_margin_lowers_the_confidence_and_clusters_json_gives_it_back():
    factor = fit_selection.margin_confidence(np.array([0.0, 0.1, 0.5, 1.0, np.nan]))
    np.testing.assert_allclose(factor, [0.5, 0.6, 1.0, 1.0, 1.0])
    summary = {"model_selection": {"clusters": [
        {"cluster": 0, "model": 3, "margin": 0.04, "runner_up": 2},
        {"cluster": 2, "model": 1, "inherited": True, "candidates": {}},   # inherited: no margin
        {"cluster": 1, "model": 1, "margin": 1.0, "runner_up": None}]}}
    margins, runner_up = fit_selection.cluster_margins(summary, 3)
    np.testing.assert_allclose(margins, [0.04, 1.0, np.nan])
    np.testing.assert_array_equal(runner_up, [2, -1, -1])
    margins, runner_up = fit_selection.cluster_margins({}, 2)  # selection off or an older clusters.json
    assert np.isnan(margins).all() and (runner_up == -1).all()


def test_cross_validation_holds_every_vertex_out_once():
    for n, folds in ((48, 4), (50, 4), (33, 3)):
        splits = fit_selection.fold_splits(n, fit_selection.SelectionSettings(folds=folds), np.random.default_rng(7))
        assert len(splits) == folds
        held = np.concatenate([h for _, h in splits])
        np.testing.assert_array_equal(np.sort(held), np.arange(n))  # each vertex held out exactly once
        for train, h in splits:
            assert not np.intersect1d(train, h).size and len(train) + len(h) == n
            assert abs(len(h) - n / folds) < 1
    # One fold is the single held-out split of held_out_fraction, drawn as before.
    one = fit_selection.fold_splits(40, fit_selection.SelectionSettings(folds=1), np.random.default_rng(3))
    train, held = fit_selection.split_vertices(40, 0.25, np.random.default_rng(3))
    assert len(one) == 1 and np.array_equal(one[0][0], train) and np.array_equal(one[0][1], held)
    for bad in (0, 2.5):
        with pytest.raises(ValueError, match="folds"):
            fit_selection.SelectionSettings(folds=bad)


def _lobe(loss, rho_s=1.0, rho_ss=(0.0, 0.0, 0.0), sigma_s=0.1, sigma_ss=0.5):
    return fit_lobes.ClusterLobe(eta=1.5, sigma_s=sigma_s, sigma_ss=sigma_ss, rho_s=rho_s, rho_ss=np.asarray(rho_ss),
                                 samples=100, loss=loss, theta_h_deg=np.zeros(0), value=np.zeros(0))


@pytest.mark.slow
def test_nested_fits_give_each_model_the_best_training_fit_of_its_family():
    """The near-mirror of the stability suite: model 3's fit ended with no single scattering at a worse training loss
    than model 1's; it must then score as model 1's fit, not as a lobe of its own (and the other way round)."""
    one, three = _lobe(1.76, sigma_s=0.031), _lobe(2.01, sigma_s=0.050)
    nested = fit_selection.nested_fits({1: one, 3: three}, 0.9)
    assert nested[1] is one and nested[3] is one  # a simpler model's fit is in every richer family
    # Model 1 stuck where model 3 (its single scattering at 0) found a better specular lobe: model 1 takes it.
    one, three = _lobe(2.01, sigma_s=0.031), _lobe(1.76, sigma_s=0.050)
    nested = fit_selection.nested_fits({1: one, 3: three}, 0.9)
    assert nested[1] is three and nested[3] is three
    # A real single-scattering lobe is not a model-1 fit, nor a model-2 one at another sigma_ss: each keeps its own.
    one, two, three = _lobe(2.0), _lobe(1.9, rho_ss=(0.1, 0.1, 0.1), sigma_ss=0.9), _lobe(1.5, rho_ss=(0.2, 0.1, 0.0))
    nested = fit_selection.nested_fits({1: one, 2: two, 3: three}, 0.9)
    assert (nested[1], nested[2], nested[3]) == (one, two, three)
    # Model 0 (no lobe at all) takes a lobed fit only where that fit's albedos are all 0.
    zero, empty = _lobe(5.0, rho_s=0.0), _lobe(4.0, rho_s=0.0)
    assert fit_selection.nested_fits({0: zero, 1: empty}, 0.9)[0] is empty
    assert fit_selection.nested_fits({0: zero, 1: _lobe(1.0)}, 0.9)[0] is zero
    assert fit_selection.in_family(_lobe(1.0, rho_ss=(0.1, 0, 0), sigma_ss=0.9), 2, 0.9)


@pytest.mark.slow
def test_the_candidate_fits_have_no_half_angle_error_unless_asked():
    augment = fit_clusters.AugmentSettings()
    assert augment.max_theta_error_deg > 0 and augment.alternations > 0  # the chosen lobe's fit keeps it
    plain = fit_selection.SelectionSettings().lobe_settings(augment)
    assert (plain.max_theta_error_deg, plain.alternations, plain.max_samples) == (0.0, 0, 4096)
    assert plain.lambda_theta == augment.lambda_theta and plain.k_max == augment.k_max
    old = fit_selection.SelectionSettings(max_theta_error_deg=5.0).lobe_settings(augment)
    assert (old.max_theta_error_deg, old.alternations) == (5.0, augment.alternations)
    with pytest.raises(ValueError, match="max_theta_error_deg"):
        fit_selection.SelectionSettings(max_theta_error_deg=-1.0)


@pytest.mark.slow
def test_selection_drops_the_lobes_a_cluster_does_not_need_and_keeps_those_it_needs(scene):
    chosen = {name: s.model for name, s in scene["selection"].items()}
    print({name: s.reason for name, s in scene["selection"].items()})
    # Measured: specular 1, scattering 3 (model 2's fixed sigma_ss 0.9 +4 %), diffuse 0.
    assert chosen["specular"] == 1 and chosen["scattering"] in (2, 3) and chosen["diffuse"] == 0, chosen
    for s in scene["selection"].values():
        # Four folds: every vertex of the cluster held out once, each fold's lobes fitted on the other three.
        assert sorted(s.candidates) == [0, 1, 2, 3] and s.held_out_vertices == 48 and s.train_vertices == 36
        assert s.candidates[s.model]["excess"] <= s.candidates[s.model]["allowed"]
    table = scene["selection"]["scattering"].candidates
    best = table[scene["selection"]["scattering"].best]["held_out_loss"]
    assert table[1]["excess"] > 0.2 * best  # without single scattering the held-out samples fit far worse
    table = scene["selection"]["specular"].candidates
    assert table[0]["excess"] > 10 * table[1]["held_out_loss"]  # the specular lobe is needed


@pytest.mark.slow
def test_selection_is_deterministic_for_a_seed(scene):
    again = _select(scene, "specular")
    first = scene["selection"]["specular"]
    assert again.model == first.model and again.candidates == first.candidates and again.reason == first.reason
    assert _select(scene, "specular", seed=5).model == 1  # another split: the same answer


def _refit_models(scene):
    """The models of the stage test's refit (model at most 1): diffuse 0, the others 1."""
    return np.where(scene["material"] == scene["names"].index("diffuse"), 0, 1)


@pytest.mark.slow
def test_fit_by_model_fits_every_vertex_with_its_model(scene):
    """A real grouped fit: the rows of each model are the plain fit of that model on them (to round-off), and
    the models are data to one compilation: a mix of every model compiles no LM kernel anew."""
    obs, normals, n = scene["obs"], scene["normals"], len(scene["normals"])
    vertex_models = _refit_models(scene)
    # Zero-weight virtual samples: the refit's compiled shapes (shared with the stage test below).
    virtual = fit_lobes.virtual_samples(np.full(n, -1), None, HELD, np.float64)
    prior = default_prior(n, np.float64)
    grouped = fit_selection.fit_by_model(obs, normals, prior, vertex_models, HELD, virtual=virtual)
    for code in (0, 1):
        m = vertex_models == code
        alone = fit_vertices(_rows(obs, m), normals[m], PBRDFParams(*[np.asarray(x)[m] for x in prior]),
                             fit_selection.settings_for_model(HELD, code), virtual=None if code == 0 else
                             records.VirtualSamples(*[np.asarray(x)[m] for x in virtual]))
        for name in ("eta", "rho_d", "rho_s", "sigma_s", "rho_ss"):
            # One fit for every model: the grouped batches mix models and view widths, so sums run in
            # another order (round-off, amplified a little by LM's accept/stop decisions).
            np.testing.assert_allclose(getattr(grouped.params, name)[m], getattr(alone.params, name), rtol=1e-6,
                                       atol=1e-9, err_msg=f"model {code}: {name}")
        np.testing.assert_array_equal(grouped.status[m], alone.status)
        if code == 1:  # every vertex of one model: the same as the plain fit with that model's settings
            same = fit_selection.fit_by_model(_rows(obs, m), normals[m],
                                              PBRDFParams(*[np.asarray(x)[m] for x in prior]),
                                              np.ones(m.sum(), int), HELD, virtual=records.VirtualSamples(
                                                  *[np.asarray(x)[m] for x in virtual]))
            for a, b in zip(jax_leaves(same), jax_leaves(alone)):
                np.testing.assert_array_equal(a, b)
    compiled = solver.lm_rounds._cache_size()
    mixed = fit_selection.fit_by_model(obs, normals, prior, np.arange(n) % 4, HELD, virtual=virtual)
    assert solver.lm_rounds._cache_size() == compiled
    assert (np.all(mixed.params.rho_s[np.arange(n) % 4 == 0] == 0)
            and np.all(mixed.params.rho_ss[np.arange(n) % 4 < 2] == 0))
    np.testing.assert_allclose(mixed.params.sigma_ss[np.arange(n) % 4 == 2], 0.9, rtol=1e-12)
    assert np.all(grouped.status == 0) and np.all(grouped.params.rho_ss == 0)
    assert np.all(grouped.params.rho_s[vertex_models == 0] == 0)
    specular = scene["material"] == scene["names"].index("specular")
    eta_error = np.abs(grouped.params.eta / scene["params"].eta - 1)
    assert np.median(eta_error[specular]) < 0.02 and np.median(eta_error[vertex_models == 0]) < 0.02
    with pytest.raises(ValueError, match="models for"):
        fit_selection.fit_by_model(obs, normals, prior, np.ones(n - 1, int), HELD)


def jax_leaves(tree):
    import jax

    return jax.tree_util.tree_leaves(tree)


def _write_stores(folder, scene):
    """observations.zarr (float32) and fit.zarr (the true parameters, every vertex fitted, confidence 1)."""
    from sellip.fit.observe import ObservationWriter, ObserveMesh, ObserveSettings
    from sellip.model.params import write_params

    obs, n = scene["obs"], len(scene["normals"])
    mesh = ObserveMesh(scene["positions"], scene["normals"], np.zeros((0, 3), np.int64))
    writer = ObservationWriter(folder / "observations.zarr", mesh, [f"v{k}" for k in range(np.shape(obs.usable)[1])],
                               {"camera_up": scene["up"], "light_axis": scene["right"]},
                               ObserveSettings(vertex_chunk=64, view_chunk=8))
    for name in ("diffuse", "diffuse_pol", "specular", "to_light", "to_camera", "light_distance", "usable"):
        writer.arrays[name][...] = np.asarray(getattr(obs, name))
    write_params(folder / "fit.zarr", {"vertices": scene["positions"], "normals": scene["normals"],
                                       **scene["params"]._asdict(), "confidence": np.ones(n),
                                       "status": np.zeros(n, np.int8)}, chunk=64)


@pytest.mark.slow
def test_stages_write_the_models_and_fit_every_vertex_with_its_own(tmp_path, scene, caplog, monkeypatch):
    from sellip.fit import finalize as fit_finalize
    from sellip.model.params import read_params
    from sellip.model.ply import read_ply, write_ply

    _write_stores(tmp_path, scene)
    stores = ["--params", str(tmp_path / "fit.zarr"), "--observations", str(tmp_path / "observations.zarr")]
    # Surface points placed without regard to their material (not regions): the coherence test is off.
    small = ["--augment-settings", '{"max_samples": 1000, "min_cluster_vertices": 10, "min_coherence": 0}']
    selection = ["--model-selection", '{"max_samples": 1000}']
    # At most model 1 (lobes specular): the scattering cluster may not keep its lobe.
    assert cli.main(["cluster-lobes", *NO_CACHE, *stores, "--output", str(tmp_path / "clusters"), *small, *selection,
                     "--settings", '{"lobes": "specular"}']) == 0
    labels, vertex_models = np.load(tmp_path / "clusters" / "labels.npy"), np.load(tmp_path / "clusters" / "models.npy")
    info = json.loads((tmp_path / "clusters" / "clusters.json").read_text())["model_selection"]
    assert vertex_models.dtype == np.uint8 and info["allowed"] == [0, 1] and info["enabled"]
    np.testing.assert_array_equal(vertex_models, np.asarray(info["models"])[labels])
    expected = {"specular": 1, "scattering": 1, "diffuse": 0}
    for name, code in expected.items():
        assert np.all(vertex_models[scene["material"] == scene["names"].index(name)] == code), name
    for cluster in info["clusters"]:  # why: every candidate's held-out loss
        assert sorted(cluster["candidates"]) == ["0", "1"] and cluster["reason"].startswith(f"model {cluster['model']}")
    table = (tmp_path / "clusters" / "lobes.csv").read_text().splitlines()
    assert table[0].endswith(",model") and sorted(int(line.split(",")[-1]) for line in table[1:]) == [0, 1, 1]

    # The refit: every vertex with its cluster's model (the grouped fit's compiled shapes above).
    assert cli.main(["fit", *NO_CACHE, "--observations", str(tmp_path / "observations.zarr"),
                     "--prior", str(tmp_path / "fit.zarr"),
                     "--lobes", str(tmp_path / "clusters"), "--output", str(tmp_path / "refit.npz"),
                     "--job-settings", '{"dtype": "float64", "compilation_cache": null}',
                     "--settings", '{"fit_normal": false}']) == 0
    with np.load(tmp_path / "refit.npz") as refit:
        np.testing.assert_array_equal(refit["model"], vertex_models)
        assert np.all(refit["rho_ss"] == 0) and np.all(refit["rho_s"][vertex_models == 0] == 0)
        assert np.all(refit["rho_s"][vertex_models == 1] > 0.1)
    assert cli.main(["gather-fit", "--observations", str(tmp_path / "observations.zarr"), "--shards",
                     str(tmp_path / "refit.npz"), "--output", str(tmp_path / "refit.zarr")]) == 0
    store = read_params(tmp_path / "refit.zarr")
    np.testing.assert_array_equal(store["model"], vertex_models)
    # An iteration between selections inherits the models (no candidate fitted), as many as allowed.
    for lobes, top in (("specular", 1), ("diffuse", 0)):
        assert cli.main(["cluster-lobes", *NO_CACHE, "--params", str(tmp_path / "refit.zarr"), "--observations",
                         str(tmp_path / "observations.zarr"), "--output", str(tmp_path / "inherited"), *small,
                         *selection, "--settings", json.dumps({"lobes": lobes}), "--inherit-models"]) == 0
        inherited = json.loads((tmp_path / "inherited" / "clusters.json").read_text())["model_selection"]
        assert inherited["inherited"] and all(c["inherited"] and not c["candidates"] for c in inherited["clusters"])
        np.testing.assert_array_equal(np.load(tmp_path / "inherited" / "models.npy"), np.minimum(vertex_models, top))
    # The final model carries the store's models (not a constant).
    n = len(vertex_models)
    write_ply(tmp_path / "mesh.ply", {**{k: scene["positions"][:, i] for i, k in enumerate("xyz")},
                                      **{f"n{k}": scene["normals"][:, i] for i, k in enumerate("xyz")}},
              np.array([[0, 1, 2]]))
    summary = fit_finalize.finalize_model(tmp_path / "refit.zarr", tmp_path / "mesh.ply", tmp_path / "model.ply",
                                 tmp_path / "final.zarr", tmp_path / "clusters")
    vertex, _ = read_ply(tmp_path / "model.ply")
    np.testing.assert_array_equal(vertex["model"], vertex_models)
    # ... and its cluster's selection margin, which lowers the confidence where it is small.
    record = json.loads((tmp_path / "clusters" / "clusters.json").read_text())
    margins, runner_up = fit_selection.cluster_margins(record, int(labels.max()) + 1)
    assert np.isfinite(margins).all()
    final = read_params(tmp_path / "final.zarr")
    np.testing.assert_allclose(final["selection_margin"], margins[labels], rtol=1e-6)
    np.testing.assert_array_equal(final["selection_runner_up"], runner_up[labels])
    np.testing.assert_allclose(final["confidence"], final["confidence_fit"] * fit_selection.margin_confidence(
        margins[labels]), rtol=1e-6)
    np.testing.assert_allclose(vertex["confidence"], final["confidence"])
    assert summary["vertices_per_model"]["0"] == np.sum(vertex_models == 0) and sum(
        summary["vertices_per_model"].values()) == n

    # The next iteration's first pass takes the models from its prior store (nearest vertex), capped by
    # its settings (the fit itself is stood in for: only which models it is given matters here).
    given = []

    def fake_fit(obs, normal0, prior, vertex_models, settings, sigma_ss_fixed, progress=None, virtual=None):
        given.append((np.array(vertex_models), settings, sigma_ss_fixed, virtual))
        k = len(normal0)
        return records.FitResult(normal=normal0, params=prior, status=np.zeros(k, np.int32), confidence=np.ones(k),
                                loss=np.zeros(k), views_used=np.full(k, 8), iterations=np.ones(k, np.int32),
                                normal_std_deg=np.ones(k), eta_std=np.ones(k), sigma_s_std=np.ones(k))

    monkeypatch.setattr(fit_selection, "fit_by_model", fake_fit)
    for extra, expected in (([], vertex_models), (["--settings", '{"lobes": "diffuse"}'], np.zeros(n))):
        assert cli.main(["fit", *NO_CACHE, "--observations", str(tmp_path / "observations.zarr"), "--prior",
                         str(tmp_path / "refit.zarr"), "--output", str(tmp_path / "next.npz"), "--model2-sigma-ss",
                         "0.8", *extra]) == 0
        np.testing.assert_array_equal(given[-1][0], expected)
        assert given[-1][2] == 0.8 and given[-1][3] is None
        with np.load(tmp_path / "next.npz") as fitted:
            np.testing.assert_array_equal(fitted["model"], expected)
    monkeypatch.undo()

    # Without model selection: every cluster gets the fit settings' model.
    assert cli.main(["cluster-lobes", *NO_CACHE, *stores, "--output", str(tmp_path / "plain"), *small,
                     "--settings", '{"lobes": "specular"}', "--model-selection", '{"enabled": false}']) == 0
    assert np.all(np.load(tmp_path / "plain" / "models.npy") == 1)
    assert json.loads((tmp_path / "plain" / "clusters.json").read_text())["model_selection"]["clusters"] == []

    # A bad models.npy is refused, naming the file; nothing is written.
    np.save(tmp_path / "clusters" / "models.npy", np.full(n, 7, np.uint8))
    caplog.clear()
    assert cli.main(["fit", *NO_CACHE, "--observations", str(tmp_path / "observations.zarr"),
                     "--lobes", str(tmp_path / "clusters"), "--output", str(tmp_path / "bad.npz")]) == 1
    assert "models.npy" in caplog.text and not (tmp_path / "bad.npz").exists()
