"""Parameter stores, neighbour filling, and how the fit stage splits vertices into shards."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from sellip.fit.records import FitSettings
from sellip.fit.shard import parse_shard
from sellip.fit.shard_plan import shard_rows
from sellip.model.params import ParamsError, fill_from_neighbours, read_params, transfer_nearest, write_params
from sellip.settings import SettingsError, record_from_mapping


@pytest.mark.parametrize("total,chunk,shards", [(10, 4, 3), (29169, 4096, 2), (5, 4096, 4), (100, 7, 100)])
def test_shards_cover_every_vertex_once_in_whole_chunks(total, chunk, shards):
    ranges = [shard_rows(total, chunk, i, shards) for i in range(shards)]
    covered = np.concatenate([np.arange(a, b) for a, b in ranges])
    np.testing.assert_array_equal(covered, np.arange(total))
    assert all(a % chunk == 0 for a, b in ranges if b > a)


def test_shard_argument_and_settings_overrides():
    assert parse_shard("2-of-4") == (1, 4)
    with pytest.raises(argparse.ArgumentTypeError, match="i must be in 1..n"):
        parse_shard("5-of-4")
    settings = record_from_mapping(FitSettings, {"lambda_d": 10, "max_iterations": 12, "sigma_ss_fixed": None})
    assert settings.lambda_d == 10.0 and settings.max_iterations == 12 and settings.sigma_ss_fixed is None
    assert record_from_mapping(FitSettings, {"sigma_ss_fixed": 0.9}).sigma_ss_fixed == 0.9
    with pytest.raises(SettingsError,
                       match="unknown setting 'fit.settings.lambda_q'; did you mean 'fit.settings.lambda"):
        record_from_mapping(FitSettings, {"lambda_q": 1}, "fit.settings")


def test_unfitted_vertices_take_their_neighbours_values():
    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(200, 3))
    values = vertices @ np.array([1.0, -2.0, 0.5])  # a smooth field
    known = rng.random(200) > 0.2
    filled = fill_from_neighbours(vertices, np.where(known, values, np.nan), known)
    assert np.all(np.isfinite(filled))
    np.testing.assert_array_equal(filled[known], values[known])
    assert np.median(np.abs(filled[~known] - values[~known])) < 0.5 * np.std(values)


def test_params_round_trip_and_errors(tmp_path):
    n = 50
    rng = np.random.default_rng(1)
    arrays = {"vertices": rng.normal(size=(n, 3)), "normals": rng.normal(size=(n, 3)), "eta": np.full(n, 1.5),
              "rho_d": rng.random((n, 3)), "rho_s": rng.random(n), "sigma_s": rng.random(n),
              "rho_ss": rng.random((n, 3)), "sigma_ss": rng.random(n), "status": np.zeros(n, int),
              "confidence": rng.random(n)}
    write_params(tmp_path / "p.zarr", arrays, chunk=16)
    back = read_params(tmp_path / "p.zarr", 10, 20)
    np.testing.assert_allclose(back["rho_d"], arrays["rho_d"][10:20].astype(np.float32))
    assert back["status"].dtype == np.int8 and back["attrs"]["num_vertices"] == n
    assert not (tmp_path / "p.zarr.tmp").exists()
    only_eta = read_params(tmp_path / "p.zarr", fields=["eta"])
    assert sorted(only_eta) == ["attrs", "eta"] and only_eta["eta"].shape == (n,)
    with pytest.raises(ParamsError, match="albedo"):
        read_params(tmp_path / "p.zarr", fields=["albedo"])
    with pytest.raises(ParamsError, match="eta"):
        write_params(tmp_path / "q.zarr", {k: v for k, v in arrays.items() if k != "eta"})
    with pytest.raises(ParamsError, match="nothing.zarr"):
        read_params(tmp_path / "nothing.zarr")
    np.testing.assert_array_equal(transfer_nearest(arrays["vertices"], arrays["vertices"][[3, 7]]), [3, 7])


def test_gather_keeps_the_starting_normal_of_unfitted_vertices(tmp_path):
    """Parameters of unfitted vertices come from their fitted neighbours, normals do not: the fit hands
    back each unfitted vertex's starting (mesh) normal, which gather-fit keeps."""
    from sellip.fit import shard
    from sellip.fit.observe import ObservationWriter, ObserveMesh, ObserveSettings
    from sellip.fit.records import STATUS_FITTED, STATUS_TOO_FEW_VIEWS

    rng = np.random.default_rng(1)
    n = 40
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)  # every vertex its own direction
    vertices = 0.01 * rng.normal(size=(n, 3))
    ObservationWriter(tmp_path / "observations.zarr", ObserveMesh(vertices, normals, np.zeros((0, 3), np.int64)),
                      ["v0"], {"camera_up": np.eye(3)[1:2], "light_axis": np.eye(3)[:1]},
                      ObserveSettings(vertex_chunk=16, view_chunk=1))
    fitted = np.arange(n) % 3 != 0
    eta = np.where(fitted, 1.5, np.nan)
    shards = []
    for start, stop in ((0, 16), (16, n)):
        rows = slice(start, stop)
        k = stop - start
        path = tmp_path / f"{start}.npz"
        np.savez(path, start=start, stop=stop, normal=normals[rows],
                 status=np.where(fitted[rows], STATUS_FITTED, STATUS_TOO_FEW_VIEWS),
                 confidence=np.where(fitted[rows], 0.9, 0.0), loss=np.zeros(k), views_used=np.full(k, 5),
                 iterations=np.ones(k), normal_std_deg=np.ones(k), eta_std=np.ones(k), sigma_s_std=np.ones(k),
                 eta=eta[rows],
                 rho_d=np.full((k, 3), 0.3), rho_s=np.full(k, 0.1), sigma_s=np.full(k, 0.2),
                 rho_ss=np.zeros((k, 3)), sigma_ss=np.full(k, 0.6))
        shards.append(path)
    shard.gather_shards(tmp_path / "observations.zarr", shards[::-1], tmp_path / "fit.zarr")
    store = read_params(tmp_path / "fit.zarr")
    np.testing.assert_allclose(store["normals"], normals, atol=1e-6)
    np.testing.assert_allclose(store["eta"], 1.5, atol=1e-6)  # filled from the fitted neighbours
    np.testing.assert_array_equal(store["confidence"] > 0, fitted)
