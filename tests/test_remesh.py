"""The geometry update of each iteration: screened Poisson from fitted normals weighted by confidence
(sellip.geometry.remesh_from_normals), the `sellip remesh` stage, and `sellip finalize`."""

from __future__ import annotations

import numpy as np
import pytest

from sellip import geometry
from sellip.scenes import icosphere

RADIUS = 0.05


def noisy_sphere(rng, noise_m=0.0008, subdivisions=4):
    """Vertices of a 5 cm sphere pushed along the normal by Gaussian noise, the true normals, the true faces."""
    unit, faces = icosphere(subdivisions)
    vertices = unit * (RADIUS + rng.normal(0, noise_m, (len(unit), 1)))
    return vertices, unit.copy(), faces


def radial_error(vertices):
    return np.abs(np.linalg.norm(vertices, axis=1) - RADIUS)


def test_poisson_from_true_normals_removes_position_noise():
    rng = np.random.default_rng(0)
    vertices, normals, _ = noisy_sphere(rng)
    new_vertices, new_faces = geometry.remesh_from_normals(vertices, normals, np.ones(len(vertices)), normals,
                                                           target_vertices=len(vertices), depth=6)
    assert abs(len(new_vertices) / len(vertices) - 1) < 0.15
    before, after = np.median(radial_error(vertices)), np.median(radial_error(new_vertices))
    assert after < 0.7 * before, (before, after)
    # A closed, outward-facing surface.
    normals_out = geometry.vertex_normals(new_vertices, new_faces)
    assert np.median(np.sum(normals_out * new_vertices / np.linalg.norm(new_vertices, axis=1, keepdims=True), 1)) > 0.99


def test_failed_fits_leave_the_surface_where_it_was():
    """A cap of vertices whose fitted normals are wrong (those of a sphere 3 cm off) and flagged with
    confidence 0 keeps the mesh's normals: the cap stays on the sphere; trusting them bends it."""
    rng = np.random.default_rng(1)
    vertices, normals, _ = noisy_sphere(rng, noise_m=0.0002)
    cap = vertices[:, 2] > 0.6 * RADIUS
    fitted = normals.copy()
    offset = vertices[cap] - [0.03, 0.0, 0.0]
    fitted[cap] = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    np.testing.assert_allclose(geometry.blend_normals(fitted, normals, np.where(cap, 0.0, 1.0)), normals)
    errors = {}
    for name, confidence in (("trusted", np.ones(len(vertices))), ("flagged", np.where(cap, 0.0, 1.0))):
        new_vertices, _ = geometry.remesh_from_normals(vertices, fitted, confidence, normals, len(vertices), depth=6,
                                                       point_weight=0.5)
        errors[name] = float(np.mean(radial_error(new_vertices[new_vertices[:, 2] > 0.6 * RADIUS])))
    assert errors["flagged"] < 0.8 * errors["trusted"], errors


def test_remesh_and_finalize_stages_write_readable_models(tmp_path):
    from sellip.io import read_param_mesh, read_ply, write_ply
    from sellip.params import MODEL_NAMES, ParamsError, read_params, write_params
    from sellip.stages import finalize, remesh

    rng = np.random.default_rng(2)
    vertices, normals, faces = noisy_sphere(rng, subdivisions=3)
    n = len(vertices)
    eta = 1.4 + 0.2 * (vertices[:, 0] > 0)  # two halves: carried by nearest vertex, so still two values
    arrays = {"vertices": vertices, "normals": normals, "eta": eta, "rho_d": np.tile([0.5, 0.4, 0.3], (n, 1)),
              "rho_s": np.full(n, 0.3), "sigma_s": np.full(n, 0.2), "rho_ss": np.full((n, 3), 0.1),
              "sigma_ss": np.full(n, 0.6), "confidence": np.full(n, 0.8), "status": np.zeros(n, np.int8)}
    write_params(tmp_path / "params.zarr", arrays)
    write_ply(tmp_path / "sphere.ply", {"x": vertices[:, 0], "y": vertices[:, 1], "z": vertices[:, 2],
                                        "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]}, faces)
    summary = remesh.run_stage(tmp_path / "params.zarr", tmp_path / "sphere.ply", tmp_path / "mesh.ply", depth=6)
    mesh = read_param_mesh(tmp_path / "mesh.ply")
    assert summary["vertices"] == mesh.num_vertices and abs(mesh.num_vertices / n - 1) < 0.2
    assert set(np.round(np.unique(mesh.params.eta), 3)) == {1.4, 1.6}
    left = mesh.vertices[:, 0] < -0.2 * RADIUS
    np.testing.assert_allclose(mesh.params.eta[left], 1.4, atol=1e-6)
    assert not list(tmp_path.glob("*.tmp*"))

    # The final pass fits the final mesh: its store has the mesh's vertices.
    vertex, _ = read_ply(tmp_path / "mesh.ply")
    m = mesh.num_vertices
    final = {"vertices": mesh.vertices, "normals": mesh.normals, "eta": mesh.params.eta, "rho_d": mesh.params.rho_d,
             "rho_s": mesh.params.rho_s, "sigma_s": mesh.params.sigma_s, "rho_ss": mesh.params.rho_ss,
             "sigma_ss": mesh.params.sigma_ss, "confidence": vertex["confidence"], "status": np.zeros(m, np.int8)}
    write_params(tmp_path / "last.zarr", final)
    (tmp_path / "clusters").mkdir()
    np.save(tmp_path / "clusters" / "labels.npy", (mesh.vertices[:, 0] > 0).astype(np.int32))
    import pandas as pd

    from sellip.stages.cluster_lobes import LOBE_COLUMNS

    lobe = {"vertices": m // 2, "sigma_s": 0.3, "sigma_ss": 0.6, "rho_s": 0.5, "rho_ss_r": 0.0, "rho_ss_g": 0.0,
            "rho_ss_b": 0.0, "samples": 100, "loss": 0.1, "model": 3}
    pd.DataFrame([{**lobe, "cluster": k, "eta": eta} for k, eta in enumerate((1.4, 1.6))])[list(LOBE_COLUMNS)].to_csv(
        tmp_path / "clusters" / "lobes.csv", index=False)
    finalize.run_stage(tmp_path / "last.zarr", tmp_path / "mesh.ply", tmp_path / "final" / "model.ply",
                       tmp_path / "final" / "params.zarr", tmp_path / "clusters", model=3)
    model_vertex, model_faces = read_ply(tmp_path / "final" / "model.ply")
    assert model_vertex["model"].dtype == np.uint8 and np.all(model_vertex["model"] == 3) and 3 in MODEL_NAMES
    np.testing.assert_allclose(model_vertex["confidence"], vertex["confidence"])
    np.testing.assert_array_equal(model_faces, read_ply(tmp_path / "mesh.ply")[1])
    store = read_params(tmp_path / "final" / "params.zarr")
    np.testing.assert_array_equal(store["cluster"], (mesh.vertices[:, 0] > 0).astype(np.int32))
    # No eta_std in the store: no vertex's own eta is known well enough, each takes its cluster's (DESIGN §7).
    np.testing.assert_array_equal(store["eta_source"], 0)
    np.testing.assert_allclose(store["eta"], np.where(mesh.vertices[:, 0] > 0, 1.6, 1.4), rtol=1e-6)
    np.testing.assert_allclose(model_vertex["eta"], store["eta"], rtol=1e-6)
    # open3d reads the model with its normals.
    import open3d as o3d

    o3d_mesh = o3d.io.read_triangle_mesh(str(tmp_path / "final" / "model.ply"))
    assert len(o3d_mesh.vertices) == m and o3d_mesh.has_vertex_normals()

    # A store that does not belong to the mesh is refused, naming both files.
    with pytest.raises(ParamsError, match="params.zarr.*mesh.ply"):
        finalize.run_stage(tmp_path / "params.zarr", tmp_path / "mesh.ply", tmp_path / "x.ply", tmp_path / "x.zarr")
