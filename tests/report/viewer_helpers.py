"""A small results folder for the viewer's tests, built directly from a scene (no workflow run): the scene's own
mesh and parameters as final/model.ply and final/params.zarr (with clusters = its material regions, per-vertex
noise on eta and a fit std), cameras.csv from a handheld orbit and an hdr.zarr holding only its intrinsics."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sellip.geometry.cameras import write_cameras

VIEWS = 12
WIDTH, HEIGHT = 512, 416
FLASH = {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0.0}


def write_results(root: Path, scene: str = "tiny", seed: int = 0, drop: tuple[str, ...] = ()) -> Path:
    """results/NAME under ``root`` for ``scene``; ``drop``: model.ply properties to leave out (an older run)."""
    import zarr

    from sellip.capture.scenes import build_scene, handheld_orbit
    from sellip.model.params import write_params
    from sellip.model.ply import write_ply

    rng = np.random.default_rng(seed)
    built = build_scene(scene)
    mesh = built.mesh
    n = mesh.num_vertices
    results = root / "results" / scene
    (results / "final").mkdir(parents=True)
    p = mesh.params
    cluster = np.asarray(mesh.material, np.int32)
    eta_vertex = np.asarray(p.eta) + rng.normal(0, 0.02, n)
    vertex = {"x": mesh.vertices[:, 0], "y": mesh.vertices[:, 1], "z": mesh.vertices[:, 2],
              "nx": mesh.normals[:, 0], "ny": mesh.normals[:, 1], "nz": mesh.normals[:, 2], "eta": p.eta,
              "rho_d_r": p.rho_d[:, 0], "rho_d_g": p.rho_d[:, 1], "rho_d_b": p.rho_d[:, 2], "rho_s": p.rho_s,
              "sigma_s": p.sigma_s, "rho_ss_r": p.rho_ss[:, 0], "rho_ss_g": p.rho_ss[:, 1], "rho_ss_b": p.rho_ss[:, 2],
              "sigma_ss": p.sigma_ss}
    vertex = {k: np.asarray(v, np.float32) for k, v in vertex.items()}
    vertex["confidence"] = rng.uniform(0.5, 1.0, n).astype(np.float32)
    vertex["model"] = np.where(cluster == 0, 1, 3).astype(np.uint8)
    vertex["eta_source"] = (rng.uniform(size=n) < 0.05).astype(np.uint8)
    vertex["lobe_source"] = np.zeros(n, np.uint8)
    for name in drop:
        vertex.pop(name)
    write_ply(results / "final" / "model.ply", vertex, mesh.faces)
    write_params(results / "final" / "params.zarr", {
        "vertices": mesh.vertices, "normals": mesh.normals, "eta": p.eta, "rho_d": p.rho_d, "rho_s": p.rho_s,
        "sigma_s": p.sigma_s, "rho_ss": p.rho_ss, "sigma_ss": p.sigma_ss, "confidence": vertex["confidence"] if
        "confidence" in vertex else np.ones(n), "cluster": cluster, "eta_vertex": eta_vertex,
        "eta_std": np.full(n, 0.02), "sigma_s_std": np.full(n, 0.01), "model": np.where(cluster == 0, 1, 3),
        "eta_source": np.zeros(n), "lobe_source": np.zeros(n)})
    cameras = handheld_orbit(VIEWS, WIDTH, HEIGHT, rng, distance_m=built.distance_m, elevation_deg=built.elevation_deg)
    write_cameras(results / "cameras.csv", [f"v{i:03d}" for i in range(len(cameras))],
                  np.stack([c.rotation for c in cameras]), np.stack([c.translation for c in cameras]))
    k = cameras[0].intrinsics
    group = zarr.open_group(str(results / "hdr.zarr"), mode="w")
    group.attrs["intrinsics"] = {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]),
                                 "cy": float(k[1, 2]), "width": WIDTH, "height": HEIGHT}
    return results
