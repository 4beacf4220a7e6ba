"""The accuracy ladder (docs/accuracy.md): where the error of a reconstruction enters, rung by rung.

Each rung adds one source of error to the one before, on the same synthetic capture:

- ``render``: the true mesh observed in noise-free analyzer images rendered straight at the HDR grid
  (no sensor, no mosaic, no ingest): what sampling images at the vertices costs;
- ``sensor``: the true mesh observed in the capture's own HDR images (sensor noise, the polarization
  and colour mosaic, demosaicing, HDR merge);
- ``mesh`` / ``hull`` / ``sfm`` (benchmarks/accuracy_ladder.py): the whole workflow from the true mesh
  (``init.mode: mesh``), from the visual hull, or from the visual hull without the capture's poses (SfM's).

The first two rungs are one observe + one fit pass (no augmentation, no iterations) on the true
mesh's vertices; their figures are those of :func:`figures`.

Public API::

    capture_tag(scene, views, width, height, renderer, seed) -> str  # the ladder's folder of one capture
    workflow_run_name(tag, rung, iterations, ...) -> str            # a workflow rung's run (results folder) name
    render_hdr(capture, hdr, output, supersample=2, renderer='sellip') -> Path  # noise-free HDR of the truth
    fit_true_mesh(capture, hdr, workdir, observe_settings) -> dict  # observe + fit on the true mesh
    figures(fit, truth) -> dict                                     # eta per material / vertex, normals
    eta_by_albedo_mode(eta, eta_true, material, true_rho_d) -> dict # eta per true material and its albedo modes
    albedo_mode_text(modes) -> str                                  # one material's modes as one line of text
    psnr_ceiling(capture, hdr, views, vertices=None) -> dict        # held-out PSNR of the truth (resampled)

:func:`psnr_ceiling` says what a per-vertex model can score at all: the true mesh and parameters, or the truth
resampled on a mesh of a given vertex count (each vertex takes its nearest true vertex's parameters), rendered at
the held-out views and scored against the capture's images as ``evaluate_model`` scores a model.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from sellip.capture.files import GROUND_TRUTH_MESH
from sellip.capture.reader import read_capture
from sellip.model.ply import read_param_mesh, write_param_mesh

WORKFLOW_RUNGS = ("mesh", "hull", "sfm")


def capture_tag(scene: str, views: int, width: int, height: int, renderer: str = "sellip",
                seed: int | None = None) -> str:
    """The name of the ladder's folder for one synthetic capture: scene, views, size, the renderer unless sellip's,
    the capture's seed unless the default (``None``), e.g. ``cow_painted_72v_1224x1024_mitsuba_seed3``."""
    return (f"{scene}_{views}v_{width}x{height}" + ("" if renderer == "sellip" else f"_{renderer}")
            + ("" if seed is None else f"_seed{seed}"))


def workflow_run_name(tag: str, rung: str, iterations: int, max_vertices: int | None = None,
                      hull_resolution: int | None = None, observed: str = "") -> str:
    """The workflow run (its ``name``, the results folder) of a workflow rung (one of :data:`WORKFLOW_RUNGS`) of
    the capture ``tag``: every setting other than its default gives the run a name of its own (``observed``: the
    observation settings' own suffix), so a rerun with other settings never reuses a cached result."""
    if rung not in WORKFLOW_RUNGS:
        raise ValueError(f"rung {rung!r} is not a workflow rung ({', '.join(WORKFLOW_RUNGS)})")
    return (f"{tag}_{rung}_{iterations}it" + (f"_{max_vertices}v" if max_vertices else "")
            + (f"_hull{hull_resolution}" if hull_resolution else "") + observed)


def render_hdr(capture: str | Path, hdr: str | Path, output: str | Path, supersample: int = 2,
               renderer: str = "sellip", batch: int = 8) -> Path:
    """A copy of the ``hdr`` store whose analyzer images are rendered noise-free from the capture's true
    mesh at the HDR grid (same intrinsics, poses from poses.csv, same flash), scaled to the store's units
    (the synthetic capture's flash power over the raw range); every pixel valid.

    ``renderer``: "sellip" (sellip.model.render) or "mitsuba" (sellip.capture.mitsuba_capture, in a fresh process,
    ``batch`` views at a time): the render rung of a capture drawn by either renderer."""
    import zarr

    from sellip.capture.hdr import read_hdr
    from sellip.geometry.cameras import intrinsics_matrix, read_cameras
    from sellip.model.conventions import stokes_to_analyzers
    from sellip.model.render import Camera, Renderer, flash_light

    if renderer not in ("sellip", "mitsuba"):
        raise ValueError(f"renderer must be 'sellip' or 'mitsuba', got {renderer!r}")

    capture, output = Path(capture), Path(output)
    config = read_capture(capture, check_files=False).config
    truth = read_param_mesh(capture / GROUND_TRUTH_MESH)
    source = read_hdr(hdr)
    view_ids, rotations, translations = read_cameras(capture / "poses.csv")
    sensor = config["sensor"]
    scale = float(config["synthetic"]["flash_power_dn"]) / (float(sensor["white_level"]) - float(sensor["black_level"]))
    tmp = output.with_name(output.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(hdr, tmp)
    group = zarr.open_group(str(tmp), mode="r+")
    k = intrinsics_matrix(source.intrinsics)
    size = int(source.intrinsics["width"]), int(source.intrinsics["height"])
    views = []
    for view_id in source.view_ids:
        row = view_ids.index(view_id)
        camera = Camera(k, rotations[row], translations[row], *size)
        views.append((camera, flash_light(camera, config["light"]["position_m"], config["light"]["polarizer_deg"])))
    if renderer == "sellip":
        ours = Renderer(truth)
        images = (ours.render(camera, light, supersample=supersample).analyzers for camera, light in views)
    else:
        from sellip.capture.mitsuba_capture import render_in_subprocess

        images = (image for start in range(0, len(views), batch)
                  for image in stokes_to_analyzers(render_in_subprocess(truth, views[start:start + batch], supersample,
                                                                        timeout_s=3600.0), axis=-2))
    for v, image in enumerate(images):
        group["analyzers"][v] = scale * np.asarray(image, np.float32)
        group["valid"][v] = np.ones(image.shape[:2], bool)
    shutil.rmtree(output, ignore_errors=True)
    tmp.rename(output)
    return output


def fit_true_mesh(capture: str | Path, hdr: str | Path, workdir: str | Path, observe_settings=None,
                  compilation_cache: str | None = None) -> dict:
    """Observe the capture's true mesh in ``hdr`` and fit every vertex (one pass, FitSettings but min_views 8);
    returns :func:`figures` of the fit. Intermediate stores go to ``workdir``."""
    from sellip.fit import observe_mesh, shard
    from sellip.fit.observe import ObserveSettings
    from sellip.fit.records import FitSettings

    capture, workdir = Path(capture), Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    truth = read_param_mesh(capture / GROUND_TRUTH_MESH)
    mesh = workdir / "true_mesh.ply"
    write_param_mesh(mesh, truth)
    shutil.rmtree(workdir / "observations.zarr", ignore_errors=True)
    observe_mesh.observe_mesh(mesh, capture / "poses.csv", hdr, capture, workdir / "observations.zarr",
                            observe_settings or ObserveSettings(edge_margin=0.0))
    # min_views 8: the setting the ladder was measured with (docs/accuracy.md), not the workflow's declared default
    shard.fit_shard(workdir / "observations.zarr", (0, 1), workdir / "fit.npz", settings=FitSettings(min_views=8),
                    compilation_cache=compilation_cache)
    return figures(dict(np.load(workdir / "fit.npz")), truth)


def figures(fit: dict, truth) -> dict:
    """Figures of a fit on the true mesh's vertices (rows in the same order): over the fitted vertices,
    eta per true material (median of its vertices, paper Table 1) and per vertex, normal error."""
    from sellip.fit.records import STATUS_FITTED
    from sellip.geometry.meshes import angular_error_deg
    from sellip.report.figures_of_merit import eta_per_material

    fitted = np.asarray(fit["status"]) == STATUS_FITTED
    if not fitted.any():
        raise ValueError(f"no vertex of the {len(fitted)} was fitted (too few usable views each): "
                         "use more views or a larger capture")
    eta_true = np.asarray(truth.params.eta, np.float64)[fitted]
    eta = np.asarray(fit["eta"], np.float64)[fitted]
    error = 100 * np.abs(eta - eta_true) / eta_true
    normal = angular_error_deg(np.asarray(fit["normal"], np.float64)[fitted], np.asarray(truth.normals)[fitted])
    material = None if truth.material is None else np.asarray(truth.material)[fitted]
    return {"fitted": int(fitted.sum()), "vertices": len(fitted),
            "eta_per_material": eta_per_material(eta, eta_true, material),
            "eta_by_albedo_mode": eta_by_albedo_mode(eta, eta_true, material,
                                                     np.asarray(truth.params.rho_d, np.float64)[fitted]),
            "eta_vertex_median_pct": float(np.median(error)), "eta_vertex_p90_pct": float(np.percentile(error, 90)),
            "normal_median_deg": float(np.median(normal)), "normal_p90_deg": float(np.percentile(normal, 90))}


def eta_by_albedo_mode(eta, eta_true, material, true_rho_d, max_modes: int = 4) -> dict:
    """Eta of each true material split by its true albedo: for a material whose vertices have at most ``max_modes``
    distinct true rho_d (a checker texture's two gains; not a photographed texture), one row per albedo with its
    vertices, the median eta and its error (%). eta, eta_true (N,), material (N,) int or None, true_rho_d (N, 3), over
    the same vertices. Returns {material: [{"rho_d", "vertices", "eta", "error_pct"}, ...]} (darkest first); a
    material with more albedos, or a truth without labels, has no entry. Two albedo modes of one material whose etas
    differ say how much the fit's eta depends on the albedo (docs/reproducibility.md)."""
    if material is None:
        return {}
    eta, eta_true = np.asarray(eta, np.float64), np.asarray(eta_true, np.float64)
    material, true_rho_d = np.asarray(material), np.asarray(true_rho_d, np.float64)
    modes = {}
    for m in np.unique(material):
        members = material == m
        albedos, which = np.unique(np.round(true_rho_d[members], 6), axis=0, return_inverse=True)
        if len(albedos) > max_modes:
            continue
        rows = []
        for a in np.argsort(albedos.sum(1)):
            chosen = np.flatnonzero(members)[which.ravel() == a]
            median = float(np.median(eta[chosen]))
            truth = float(np.median(eta_true[chosen]))
            rows.append({"rho_d": [float(v) for v in albedos[a]], "vertices": int(chosen.size), "eta": median,
                         "error_pct": 100 * (median - truth) / truth})
        modes[str(int(m))] = rows
    return modes


def albedo_mode_text(modes: list) -> str:
    """One material's rows of :func:`eta_by_albedo_mode` as one line: albedo, vertices, eta and its signed error."""
    return "; ".join(f"rho_d ({', '.join(f'{v:.3f}' for v in mode['rho_d'])}) {mode['vertices']} vertices "
                     f"eta {mode['eta']:.4f} ({mode['error_pct']:+.2f} %)" for mode in modes)


def resampled_truth(truth, vertices: int):
    """The true ParamMesh on a mesh of about ``vertices`` vertices (:func:`sellip.geometry.scan.resample_to_count`, as
    the ``mesh`` rung's initial mesh), each vertex with the parameters and material of its nearest true vertex."""
    from scipy.spatial import cKDTree

    from sellip.geometry.meshes import vertex_normals
    from sellip.geometry.scan import resample_to_count
    from sellip.model.pbrdf import PBRDFParams
    from sellip.model.render import ParamMesh

    points, faces = resample_to_count(np.asarray(truth.vertices, np.float64), np.asarray(truth.faces), vertices)
    _, nearest = cKDTree(np.asarray(truth.vertices)).query(points)
    params = PBRDFParams(*(np.asarray(value)[nearest] for value in truth.params))
    material = None if truth.material is None else np.asarray(truth.material)[nearest]
    return ParamMesh(vertices=points, faces=faces, normals=vertex_normals(points, faces), params=params,
                     material=material)


def psnr_ceiling(capture: str | Path, hdr: str | Path, views: list[str], vertices: int | None = None,
                 supersample: int = 2) -> dict:
    """Held-out PSNR (dB; :func:`sellip.report.metrics.view_psnr`, as evaluate_model scores a model) of the
    capture's ground truth at ``views`` against the HDR images of ``hdr``: the true mesh itself (``vertices`` None)
    or :func:`resampled_truth` at ``vertices``.
    Returns {"vertices", "views": {view_id: dB}, "mean_db"}."""
    from sellip.capture.hdr import read_hdr
    from sellip.geometry.cameras import hdr_camera, read_cameras
    from sellip.model.render import Renderer, flash_light
    from sellip.report.metrics import view_psnr

    capture = Path(capture)
    light = read_capture(capture, check_files=False).config["light"]
    truth = read_param_mesh(capture / GROUND_TRUTH_MESH)
    model = truth if vertices is None else resampled_truth(truth, vertices)
    store = read_hdr(hdr)
    view_ids, rotations, translations = read_cameras(capture / "poses.csv")
    renderer = Renderer(model)
    scores = {}
    for view_id in views:
        row = view_ids.index(view_id)
        camera = hdr_camera(store.intrinsics, rotations[row], translations[row], hdr)
        lamp = flash_light(camera, light["position_m"], float(light["polarizer_deg"]))
        scores[view_id] = view_psnr(renderer, camera, lamp, store, view_id, supersample)["psnr_db"]
    return {"vertices": model.num_vertices, "views": scores, "mean_db": float(np.mean(list(scores.values())))}
