"""The stability suite (issue #9): small reconstructions built to hit the known failure modes.

Each case is a real Snakemake run of the repository's workflow on a small synthetic capture (the
``tiny`` sphere at 320x256, 36 views, two iterations: :func:`base_config`) with one thing broken:
the material (paper §6: very dark, white and rough, near-mirror), the capture (12 or 24 views, 4x
sensor noise, the flash position off by 1 cm, missing and corrupt frames) or the geometry (a sphere
with 4 mm bumps and dents from the default and from an over-smoothed initial mesh; relief finer than a
pixel; the initial mesh perturbed by 1 mm along the normals); ``baseline`` breaks nothing. Per case: the
figures of merit of metrics.json, whether every output is finite, and how well the per-vertex
confidence flags the vertices whose normal (or η) is wrong. docs/benchmarks.md has the table.

Public API::

    Case, CASES, CASE_NAMES                     # what each case breaks, and how
    base_config(workdir, views=36, iterations=2) -> dict
    case_config(case, workdir, iterations=2) -> dict     # the override YAML of one case
    perturb_along_normals(vertices, normals, sigma_m, seed) -> (V, 3)
    perturb_mesh_file(path, sigma_m, seed) -> None        # a PLY rewritten in place (atomically)
    miscalibrate_flash(capture_dir, offset_m) -> (true, declared)   # capture.yaml light.position_m += offset
    damage_frames(capture_dir, missing=(), corrupt=(), truncated=(), seed=0) -> list[str]
    rank_auc(score, positive) -> float | None
    confidence_flagging(error, confidence, bad_above, low_below=0.5) -> dict
    nonfinite_outputs(results_dir) -> dict[str, int]
    case_row(case, workdir, wall_s, error=None) -> dict
    STABILITY_SCHEMA, validate_table(rows) -> DataFrame
    markdown_table(table) -> str
    run_case(case, workdir, snakefile, cores=2, ...) -> dict
    run_suite(cases, out, snakefile, cores=2, ...) -> DataFrame       # writes stability.csv / .md

Confidence flagging (per case, over every vertex of final/model.ply): a vertex is *bad* when its normal
is more than ``bad_above`` (10°) from the normal of its nearest ground-truth vertex
(:func:`sellip.evaluate.vertex_errors`), *flagged* when its confidence is below ``low_below`` (0.5).
``bad_flagged`` = flagged share of the bad vertices (recall); ``flagged_bad`` = bad share of the flagged
vertices (precision); ``auc`` = the probability that a random bad vertex has a lower confidence than a
random good one (ties count one half): 0.5 is a confidence that knows nothing, 1 a perfect ranking.
``worst_auc``: the same AUC with the worst tenth of the vertices (error at or above the 90th percentile) as the
bad ones, defined also when no error passes the threshold. The same for η with bad = relative error above 10 %.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sellip.sweep import merge

log = logging.getLogger(__name__)

BAD_NORMAL_DEG = 10.0
"""A vertex whose normal is further than this from the ground truth's is bad."""

BAD_ETA_PCT = 10.0
"""A vertex whose η is further than this (relative, %) from the ground truth's is bad."""

LOW_CONFIDENCE = 0.5
"""A vertex whose confidence is below this is flagged."""

BASE_VIEWS = 36
BASE_SEED = 3
PERTURB_SEED = 20220804


class StabilityError(RuntimeError):
    """A case could not be set up or run (the message says which case and which step)."""


@dataclass(frozen=True)
class Case:
    """One case of the suite.

    name: results/<name> and the table row; group: material, capture, geometry or baseline;
    breaks: what is broken, in words; config: merged over :func:`base_config` (deep);
    views: captured views (None: the base's); flash_offset_m: added to capture.yaml ``light.position_m``
    after synthesis (the capture keeps the true flash; the reconstruction believes the declared one);
    missing / corrupt / truncated: frame ids deleted, overwritten with random bytes, cut to a third
    after synthesis (the run uses ``ingest.bad_frames: skip``); perturb_m: standard deviation of the
    seeded displacement of the initial mesh's vertices along their normals.
    """

    name: str
    group: str
    breaks: str
    config: Mapping = field(default_factory=dict)
    views: int | None = None
    flash_offset_m: tuple[float, float, float] | None = None
    missing: tuple[str, ...] = ()
    corrupt: tuple[str, ...] = ()
    truncated: tuple[str, ...] = ()
    perturb_m: float = 0.0

    @property
    def edits_capture(self) -> bool:
        return self.flash_offset_m is not None or bool(self.missing or self.corrupt or self.truncated)


CASES: tuple[Case, ...] = (
    Case("baseline", "baseline", "nothing (tiny sphere, 36 views, real sensor noise)"),
    Case("dark", "material", "very dark albedo, rho_d 0.02-0.05 (scene tiny_dark)",
         config={"demo": {"scene": "tiny_dark"}}),
    Case("white_rough", "material", "white rough, rho_d ~0.8, sigma_s 0.55-0.6, single scattering on half "
         "(scene tiny_white)", config={"demo": {"scene": "tiny_white"}}),
    Case("mirror", "material", "near-mirror, sigma_s 0.03/0.05 over rho_d 0.03-0.08 (scene tiny_mirror)",
         config={"demo": {"scene": "tiny_mirror"}}),
    Case("fine_texture", "material", "albedo speckle finer than a pixel and the mesh: 1 mm cells, gain 0.75-1.2 "
         "(scene tiny_speckle; a pixel is about 1 mm)", config={"demo": {"scene": "tiny_speckle"}}),
    Case("dark_noisy", "material", "very dark albedo (tiny_dark) and sensor noise x4 together",
         config={"demo": {"scene": "tiny_dark", "noise_scale": 4.0}}),
    Case("views_24", "capture", "only 24 views (2 held out)", views=24),
    Case("views_12", "capture", "only 12 views (2 held out)", views=12),
    Case("noise_x4", "capture", "sensor noise x4 (demo.noise_scale 4: 1/16 of the photons)",
         config={"demo": {"noise_scale": 4.0}}),
    Case("flash_out_1cm", "capture", "flash declared 1 cm further from the lens (6 cm) than it was (5 cm)",
         flash_offset_m=(0.0, 0.01, 0.0)),
    Case("flash_in_1cm", "capture", "flash declared 1 cm closer to the lens (4 cm) than it was (5 cm)",
         flash_offset_m=(0.0, -0.01, 0.0)),
    Case("bad_frames", "capture", "frames missing (v001_f0; all of v004) and corrupt (v002_f1 random bytes, "
         "v003_f2 truncated); ingest.bad_frames skip",
         config={"ingest": {"bad_frames": "skip"}}, missing=("v001_f0", "v004_f0", "v004_f1", "v004_f2"),
         corrupt=("v002_f1",), truncated=("v003_f2",)),
    Case("bumpy", "geometry", "shape detail: 4 mm bumps and dents (scene tiny_bumpy), default initial mesh",
         config={"demo": {"scene": "tiny_bumpy"}}),
    Case("bumpy_smooth", "geometry", "tiny_bumpy from an over-smoothed initial mesh (hull 16 voxels, Poisson "
         "depth 4)", config={"demo": {"scene": "tiny_bumpy"}, "init": {"hull_resolution": 16, "poisson_depth": 4}}),
    Case("relief", "geometry", "surface relief finer than a pixel: 0.35 mm ridges between 3.3 mm cells "
         "(scene tiny_relief; a pixel is about 1 mm)", config={"demo": {"scene": "tiny_relief"}}),
    Case("init_perturbed", "geometry", "initial mesh perturbed along its normals (1 mm RMS, seeded)",
         perturb_m=0.001),
    Case("uniform_dark", "degenerate", "one uniformly coloured very dark glossy material, rho_d 0.04 (scene "
         "uniform_dark): every albedo one value", config={"demo": {"scene": "uniform_dark"}}),
    Case("uniform_dark_sfm", "degenerate", "uniform_dark without poses (SfM)",
         config={"demo": {"scene": "uniform_dark"}, "sfm": {"mode": "sfm"}}),
    Case("uniform_bright", "degenerate", "one uniformly coloured bright material, rho_d 0.7 (scene uniform_bright)",
         config={"demo": {"scene": "uniform_bright"}}),
    Case("uniform_bright_sfm", "degenerate", "uniform_bright without poses (SfM)",
         config={"demo": {"scene": "uniform_bright"}, "sfm": {"mode": "sfm"}}),
    Case("cow", "degenerate", "a cow-like figure with legs and concavities, flat black and white patches with sharp "
         "edges, one material (scene cow)", config={"demo": {"scene": "cow"}}),
    Case("cow_sfm", "degenerate", "the cow without poses (SfM)",
         config={"demo": {"scene": "cow"}, "sfm": {"mode": "sfm"}}),
)
CASE_NAMES = tuple(case.name for case in CASES)


# --------------------------------------------------------------------------- configuration


def held_out_views(views: int, count: int = 2) -> list[str]:
    """``count`` evaluation views of a synthetic capture of ``views`` views (ids v000, v001, ...), spread
    evenly over the orbit: for two, a quarter and three quarters along it."""
    step = views / count
    return [f"v{int(step / 2 + i * step):03d}" for i in range(count)]


def base_config(workdir: str | Path, views: int = BASE_VIEWS, iterations: int = 2,
                jax_cache: str | Path | None = None) -> dict:
    """The override of config/config.yaml that every case starts from: the tiny sphere at 320x256,
    ``views`` views (two held out), at most 2500 vertices, ``iterations`` iterations, two fit shards of
    about equal size."""
    return {
        "iterations": int(iterations),
        "demo": {"scene": "tiny", "views": int(views), "width": 320, "height": 256, "seed": BASE_SEED,
                 "noise_scale": 1.0},
        "init": {"hull_resolution": 64, "max_vertices": 2500},
        # Fit shards are whole observation chunks: 256-vertex chunks split ~2.5k vertices evenly over both. The
        # demo's slope test (demo.overrides) is for its 612x512 capture: off here, as for any capture by default.
        "observe": {"vertex_chunk": 256, "max_slope": 0.0},
        "fit": {"shards": 2, "compilation_cache": str(jax_cache or Path(workdir) / "jax_cache"),
                "settings": {"min_views": 4}},
        "evaluate": {"held_out_views": held_out_views(views), "render_views": ["v000"], "supersample": 1},
    }


def case_config(case: Case, workdir: str | Path, iterations: int = 2, jax_cache: str | Path | None = None) -> dict:
    """The full override of one case: :func:`base_config` with the case's views and ``config`` merged in."""
    config = base_config(workdir, case.views or BASE_VIEWS, iterations, jax_cache)
    return merge(config, {"name": case.name, **case.config})


# --------------------------------------------------------------------------- breaking things


def perturb_along_normals(vertices: np.ndarray, normals: np.ndarray, sigma_m: float, seed: int) -> np.ndarray:
    """Vertices (V, 3) moved along their unit normals (V, 3) by independent N(0, sigma_m^2) offsets (seeded)."""
    vertices = np.asarray(vertices, np.float64)
    normals = np.asarray(normals, np.float64)
    if vertices.shape != normals.shape or vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices and normals must both be (V, 3), got {vertices.shape} and {normals.shape}")
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if not np.all(np.isfinite(length)) or np.any(length == 0):
        raise ValueError("every normal must be finite and non-zero")
    offset = np.random.default_rng(seed).normal(0.0, sigma_m, len(vertices))
    return vertices + offset[:, None] * normals / length


def _write_atomic(path: Path, write: Callable[[Path], None]) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        write(tmp)
        tmp.replace(path)
    finally:
        if tmp.exists():
            tmp.unlink()


def perturb_mesh_file(path: str | Path, sigma_m: float, seed: int) -> None:
    """Rewrite a mesh PLY (x y z nx ny nz, faces) with its vertices perturbed along its normals and the
    normals of the new surface (area-weighted); other properties kept. Atomic (temporary file + rename)."""
    from sellip.io import read_ply, write_ply
    from sellip.scenes import vertex_normals

    path = Path(path)
    vertex, faces = read_ply(path)
    if faces is None or not {"x", "y", "z", "nx", "ny", "nz"} <= set(vertex):
        raise StabilityError(f"{path}: expected a triangle mesh with x y z nx ny nz vertex properties")
    xyz = np.stack([vertex[k] for k in "xyz"], axis=1)
    moved = perturb_along_normals(xyz, np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1), sigma_m, seed)
    normals = vertex_normals(moved, np.asarray(faces, np.int64))
    out = dict(vertex)
    for k, name in enumerate("xyz"):
        out[name] = moved[:, k].astype(vertex[name].dtype)
    for k, name in enumerate(("nx", "ny", "nz")):
        out[name] = normals[:, k].astype(vertex[name].dtype)
    _write_atomic(path, lambda tmp: write_ply(tmp, out, faces))


def miscalibrate_flash(capture_dir: str | Path, offset_m: Sequence[float]) -> tuple[list[float], list[float]]:
    """Add ``offset_m`` (camera coordinates, metres) to capture.yaml's ``light.position_m``, keeping the rest of
    the file; returns (true, declared) positions. The frames stay as they were shot: the flash is now wrong."""
    import yaml

    path = Path(capture_dir) / "capture.yaml"
    config = yaml.safe_load(path.read_text())
    true = [float(v) for v in config["light"]["position_m"]]
    declared = [t + float(o) for t, o in zip(true, offset_m, strict=True)]
    config["light"]["position_m"] = declared
    config.setdefault("synthetic", {})["true_flash_position_m"] = true
    _write_atomic(path, lambda tmp: tmp.write_text(yaml.safe_dump(config, sort_keys=False)))
    return true, declared


def damage_frames(capture_dir: str | Path, missing: Sequence[str] = (), corrupt: Sequence[str] = (),
                  truncated: Sequence[str] = (), seed: int = 0) -> list[str]:
    """Break raw frames of a capture by frame_id: delete ``missing`` files (their frames.csv rows stay),
    overwrite ``corrupt`` ones with as many random bytes (seeded), cut ``truncated`` ones to a third.
    Returns the files touched, relative to the capture. Raises StabilityError for an unknown frame_id."""
    import pandas as pd

    capture_dir = Path(capture_dir)
    frames = pd.read_csv(capture_dir / "frames.csv").set_index("frame_id")
    rng = np.random.default_rng(seed)
    touched = []
    for how, ids in (("missing", missing), ("corrupt", corrupt), ("truncated", truncated)):
        for frame_id in ids:
            if frame_id not in frames.index:
                raise StabilityError(f"{capture_dir / 'frames.csv'}: no frame {frame_id!r} to make {how}")
            path = capture_dir / frames.loc[frame_id, "file"]
            size = path.stat().st_size
            if how == "missing":
                path.unlink()
            elif how == "corrupt":
                path.write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
            else:
                path.write_bytes(path.read_bytes()[: size // 3])
            touched.append(str(frames.loc[frame_id, "file"]))
    return touched


# --------------------------------------------------------------------------- measuring


def rank_auc(score: np.ndarray, positive: np.ndarray) -> float | None:
    """Probability that a random positive has a larger ``score`` than a random negative, ties one half
    (the Mann-Whitney U / ROC AUC). None when either class is empty."""
    from scipy.stats import rankdata

    score = np.asarray(score, np.float64)
    positive = np.asarray(positive, bool)
    n_pos, n_neg = int(positive.sum()), int((~positive).sum())
    if n_pos == 0 or n_neg == 0:
        return None
    ranks = rankdata(score)
    return float((ranks[positive].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def confidence_flagging(error: np.ndarray, confidence: np.ndarray, bad_above: float,
                        low_below: float = LOW_CONFIDENCE) -> dict:
    """How well a low confidence marks large errors (definitions: module docstring).

    error, confidence: (N,). Returns bad_share, flagged_share, bad_flagged (recall), flagged_bad
    (precision), auc, and worst_auc: the AUC for the worst tenth of the vertices (error at or above its
    90th percentile), defined whatever the errors' scale; a ratio over an empty set is None.
    """
    error = np.asarray(error, np.float64)
    confidence = np.asarray(confidence, np.float64)
    if error.shape != confidence.shape or error.ndim != 1:
        raise ValueError(f"error and confidence must be (N,) of one length, got {error.shape}, {confidence.shape}")
    if error.size == 0:
        return {"bad_share": None, "flagged_share": None, "bad_flagged": None, "flagged_bad": None, "auc": None,
                "worst_auc": None}
    bad = error > bad_above
    flagged = ~(confidence >= low_below)  # NaN confidence counts as flagged

    def share(of, among):
        return float(np.mean(of[among])) if among.any() else None

    doubt = -np.nan_to_num(confidence, nan=-1.0)
    return {"bad_share": float(bad.mean()), "flagged_share": float(flagged.mean()),
            "bad_flagged": share(flagged, bad), "flagged_bad": share(bad, flagged), "auc": rank_auc(doubt, bad),
            "worst_auc": rank_auc(doubt, error >= np.percentile(error, 90))}


def _count_nonfinite(values) -> int:
    values = np.asarray(values)
    return int(np.size(values) - np.count_nonzero(np.isfinite(values))) if values.dtype.kind in "fc" else 0


INFINITE_WHEN_UNKNOWN = ("normal_std_deg", "eta_std", "sigma_s_std")
"""params.zarr arrays that are +inf by design where the uncertainty is unknown: a vertex not fitted
(status != 0), or fitted with a singular Gauss-Newton matrix (confidence 0; sellip.params)."""


def nonfinite_outputs(results_dir: str | Path) -> dict[str, int]:
    """Non-finite values per output array of a finished run: every vertex property of final/model.ply, every
    array of final/params.zarr (except +inf in INFINITE_WHEN_UNKNOWN where the uncertainty is unknown),
    every array of the .npz files under final/renders, and metrics.json (NaN or Infinity literals). Returns
    only the arrays with any ({} when all is finite); a missing output counts -1."""
    import warnings

    import zarr

    from sellip.io import read_ply

    results_dir = Path(results_dir)
    bad: dict[str, int] = {}
    model = results_dir / "final" / "model.ply"
    if model.is_file():
        vertex, _ = read_ply(model)
        for name, values in vertex.items():
            if (count := _count_nonfinite(values)):
                bad[f"model.ply:{name}"] = count
    else:
        bad["model.ply"] = -1
    params = results_dir / "final" / "params.zarr"
    if (params / "zarr.json").is_file():
        with warnings.catch_warnings():  # Snakemake's .snakemake_timestamp in a directory output
            warnings.simplefilter("ignore")
            group = zarr.open_group(str(params), mode="r")
            arrays = {name: np.asarray(array[...]) for name, array in group.arrays()}
        unknown = np.zeros(0, bool)
        if "status" in arrays and "confidence" in arrays:
            unknown = (arrays["status"] != 0) | (arrays["confidence"] == 0)
        for name, values in arrays.items():
            if name in INFINITE_WHEN_UNKNOWN and values.shape == unknown.shape:
                values = np.where(unknown & (values == np.inf), 0.0, values)
            if (count := _count_nonfinite(values)):
                bad[f"params.zarr:{name}"] = count
    else:
        bad["params.zarr"] = -1
    renders = results_dir / "final" / "renders"
    if renders.is_dir():
        for path in sorted(renders.glob("*.npz")):
            with np.load(path) as data:
                for name in data.files:
                    if (count := _count_nonfinite(data[name])):
                        bad[f"renders/{path.name}:{name}"] = count
    else:
        bad["renders"] = -1
    metrics = results_dir / "metrics.json"
    if metrics.is_file():
        literals = []
        json.loads(metrics.read_text(), parse_constant=literals.append)
        if literals:
            bad["metrics.json"] = len(literals)
    else:
        bad["metrics.json"] = -1
    return bad


def _get(mapping, *keys):
    for key in keys:
        if not isinstance(mapping, Mapping) or mapping.get(key) is None:
            return None
        mapping = mapping[key]
    return mapping


COLUMNS: dict[str, str] = {
    # name: pandas dtype ("float" columns may be null)
    "case": "str", "group": "str", "breaks": "str", "status": "str", "error": "str",
    "wall_s": "float", "cpu_s": "float", "views": "float", "vertices": "float", "confident_share": "float",
    "normal_mean_deg": "float", "normal_median_deg": "float", "normal_p90_deg": "float",
    "eta_median_pct": "float", "eta_material_mean_pct": "float", "eta_material_max_pct": "float",
    "rho_d_rmse": "float", "sigma_s_median_err": "float",
    "chamfer_mm": "float", "hausdorff_mm": "float", "psnr_held_out_db": "float", "psnr_new_light_db": "float",
    "outputs_finite": "bool", "nonfinite": "str",
    "confidence_median": "float", "bad_share": "float", "flagged_share": "float", "bad_flagged": "float",
    "flagged_bad": "float", "auc": "float", "worst_auc": "float", "eta_bad_share": "float",
    "eta_bad_flagged": "float", "eta_flagged_bad": "float", "eta_auc": "float", "eta_worst_auc": "float",
}
"""The columns of stability.csv, in order (definitions: docs/benchmarks.md)."""


def empty_row(case: Case) -> dict:
    row = {name: (None if kind == "float" else "") for name, kind in COLUMNS.items()}
    row.update(case=case.name, group=case.group, breaks=case.breaks, outputs_finite=False)
    return row


def case_row(case: Case, workdir: str | Path, wall_s: float, error: str | None = None,
             cpu_s: float | None = None) -> dict:
    """One table row from a case's finished run in ``workdir`` (results/<case.name>, captures/<scene>).

    wall_s, cpu_s: the run's wall time and the CPU time (user + system) of all its processes;
    ``error``: why the run failed (the row then has status "failed" and whatever outputs exist)."""
    from sellip.evaluate import vertex_errors
    from sellip.io import GROUND_TRUTH_MESH, read_param_mesh, read_ply

    workdir = Path(workdir)
    results = workdir / "results" / case.name
    row = empty_row(case)
    row.update(status="failed" if error else "ok", error=error or "", wall_s=float(wall_s),
               cpu_s=None if cpu_s is None else float(cpu_s))
    hdr = results / "hdr.zarr" / "zarr.json"
    if hdr.is_file():
        row["views"] = float(len(json.loads(hdr.read_text()).get("attributes", {}).get("view_id", [])))
    nonfinite = nonfinite_outputs(results)
    row["outputs_finite"] = not nonfinite
    row["nonfinite"] = "; ".join(f"{k} {'missing' if v < 0 else v}" for k, v in nonfinite.items())
    metrics_path = results / "metrics.json"
    if metrics_path.is_file():
        m = json.loads(metrics_path.read_text())
        vertices = _get(m, "vertices", "model")
        row.update(
            vertices=vertices,
            confident_share=(_get(m, "vertices", "confident") / vertices) if vertices else None,
            normal_mean_deg=_get(m, "normal_error_deg", "all", "mean"),
            normal_median_deg=_get(m, "normal_error_deg", "all", "median"),
            normal_p90_deg=_get(m, "normal_error_deg", "all", "p90"),
            eta_median_pct=_get(m, "eta_relative_error_pct", "median"),
            eta_material_mean_pct=_get(m, "eta_per_material", "mean_error_pct"),
            eta_material_max_pct=_get(m, "eta_per_material", "max_error_pct"),
            rho_d_rmse=_get(m, "rho_d_relative_rmse", "relative_rmse"),
            sigma_s_median_err=_get(m, "sigma_s_abs_error", "median"),
            chamfer_mm=_get(m, "geometry", "chamfer_mm"), hausdorff_mm=_get(m, "geometry", "hausdorff_mm"),
            psnr_held_out_db=_get(m, "psnr_held_out", "mean_db"),
            psnr_new_light_db=_get(m, "psnr_new_light", "mean_db"))
    model_path = results / "final" / "model.ply"
    scene = (case.config.get("demo") or {}).get("scene", "tiny")
    truth_path = workdir / "captures" / scene / GROUND_TRUTH_MESH
    if model_path.is_file() and truth_path.is_file():
        vertex, _ = read_ply(model_path)
        confidence = np.asarray(vertex.get("confidence", np.zeros(len(vertex["x"]))), np.float64)
        errors = vertex_errors(read_param_mesh(model_path), read_param_mesh(truth_path))
        normal = confidence_flagging(errors["normal_error_deg"], confidence, BAD_NORMAL_DEG)
        eta = confidence_flagging(errors["eta_relative_error_pct"], confidence, BAD_ETA_PCT)
        row.update(confidence_median=float(np.nanmedian(confidence)), **normal,
                   **{f"eta_{k}": eta[k] for k in ("bad_share", "bad_flagged", "flagged_bad", "auc", "worst_auc")})
    return row


def _schema():
    import pandera.pandas as pa

    def column(kind: str):
        if kind == "float":
            return pa.Column(float, pa.Check.ge(0), nullable=True)
        return pa.Column(bool if kind == "bool" else str)

    columns = {name: column(kind) for name, kind in COLUMNS.items()}
    columns["status"] = pa.Column(str, pa.Check.isin(["ok", "failed"]))
    columns["case"] = pa.Column(str, unique=True)
    for name in ("bad_share", "flagged_share", "bad_flagged", "flagged_bad", "auc", "worst_auc", "eta_bad_share",
                 "eta_bad_flagged", "eta_flagged_bad", "eta_auc", "eta_worst_auc", "confident_share",
                 "confidence_median"):
        columns[name] = pa.Column(float, [pa.Check.in_range(0, 1)], nullable=True)
    return pa.DataFrameSchema(columns, strict=True, ordered=True)


def validate_table(rows: Sequence[Mapping]):
    """The rows as a DataFrame in COLUMNS order, checked against STABILITY_SCHEMA (pandera raises naming the
    column and row)."""
    import pandas as pd

    table = pd.DataFrame([{name: row.get(name) for name in COLUMNS} for row in rows], columns=list(COLUMNS))
    for name, kind in COLUMNS.items():
        table[name] = table[name].astype({"float": "float64", "bool": "bool", "str": "object"}[kind])
        if kind == "str":
            table[name] = table[name].fillna("").astype(str)
    return _schema().validate(table, lazy=True)


def _fmt(value, digits: int = 1, percent: bool = False) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return f"{100 * value:.0f} %" if percent else f"{value:.{digits}f}"


def _share_count(share, vertices) -> str:
    """'1.2 % (28)': a share of the vertices with its vertex count."""
    if share is None or not np.isfinite(share):
        return "–"
    count = f" ({round(share * vertices)})" if vertices is not None and np.isfinite(vertices) else ""
    return f"{100 * share:.1f} %{count}"


def _markdown(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def markdown_table(table) -> str:
    """The suite's tables in Markdown: the figures of merit per case, then finiteness and confidence flagging."""
    records = table.to_dict("records")
    merit, flags = [], []
    for row in records:
        status = "ok" if row["status"] == "ok" else f"**failed**: {row['error'][:160]}"
        merit.append([
            row["case"], row["breaks"], status, _fmt(row["views"], 0), _fmt(row["vertices"], 0),
            " / ".join(_fmt(row[k]) for k in ("normal_mean_deg", "normal_median_deg", "normal_p90_deg")),
            _fmt(row["eta_median_pct"]),
            " / ".join(_fmt(row[k], 2) for k in ("eta_material_mean_pct", "eta_material_max_pct")),
            _fmt(row["rho_d_rmse"], 2), _fmt(row["sigma_s_median_err"], 2),
            f"{_fmt(row['chamfer_mm'], 2)} / {_fmt(row['hausdorff_mm'], 1)}", _fmt(row["psnr_held_out_db"]),
            _fmt(row["psnr_new_light_db"]), f"{_fmt(row['wall_s'], 0)} / {_fmt(row['cpu_s'], 0)}"])
        finite = "yes" if row["outputs_finite"] else f"**no**: {row['nonfinite'][:120]}"
        flags.append([
            row["case"], finite, _fmt(row["confident_share"], percent=True), _fmt(row["confidence_median"], 2),
            _fmt(row["flagged_share"], percent=True),
            f"{_share_count(row['bad_share'], row['vertices'])} / "
            + " / ".join(_fmt(row[k], percent=True) for k in ("bad_flagged", "flagged_bad")),
            _fmt(row["auc"], 2), _fmt(row["worst_auc"], 2),
            f"{_share_count(row['eta_bad_share'], row['vertices'])} / "
            + " / ".join(_fmt(row[k], percent=True) for k in ("eta_bad_flagged", "eta_flagged_bad")),
            _fmt(row["eta_auc"], 2), _fmt(row["eta_worst_auc"], 2)])
    lines = ["Figures of merit (metrics.json of each run):", ""]
    lines += _markdown(["case", "broken", "status", "views", "vertices", "normal mean / median / p90 (°)",
                        "η per vertex, median (%)", "η per material, mean / worst (%)", "ρ_d rel. RMSE",
                        "σ_s err. (median)", "Chamfer / Hausdorff (mm)",
                        "held-out PSNR (dB)", "new-light PSNR (dB)", "wall / CPU (s)"], merit)
    caption = (f"Outputs and confidence (bad: normal error > {BAD_NORMAL_DEG:g}°, η error > {BAD_ETA_PCT:g} %; "
               f"flagged: confidence < {LOW_CONFIDENCE:g}):")
    lines += ["", caption, ""]
    lines += _markdown(["case", "outputs finite", "confidence > 0", "median confidence", "flagged",
                        "normal bad (vertices) / bad flagged / flagged bad", "normal AUC", "normal worst-10 % AUC",
                        "η bad (vertices) / bad flagged / flagged bad", "η AUC", "η worst-10 % AUC"], flags)
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- running


def snakemake_command(snakefile: Path, workdir: Path, override: Path, *args: str) -> list[str]:
    """`python -m snakemake` on the repository's Snakefile in ``workdir``, config.yaml then ``override``."""
    snakefile = Path(snakefile).resolve()
    return [sys.executable, "-m", "snakemake", "--snakefile", str(snakefile), "--directory", str(workdir),
            "--configfile", str(snakefile.parent / "config" / "config.yaml"), str(override), *args]


def failure_reason(output: str, workdir: Path) -> str:
    """A one-line reason from Snakemake's output: the failing rule and the last error line of its log."""
    rule = next((line.strip() for line in output.splitlines() if line.strip().startswith("Error in rule")), None)
    log_file = None
    lines = output.splitlines()
    for i, line in enumerate(lines):
        if line.strip().startswith("log:") and rule and i > 0:
            log_file = line.split("log:", 1)[1].split("(")[0].strip()
    detail = ""
    if log_file and (workdir / log_file).is_file():
        text = [ln for ln in (workdir / log_file).read_text(errors="replace").splitlines() if ln.strip()]
        errors = [ln for ln in text if "ERROR" in ln or "Error" in ln]
        detail = (errors or text or [""])[-1].strip()
    if rule is None:
        tail = [ln for ln in lines if ln.strip()]
        return (tail[-1] if tail else "snakemake failed").strip()[:300]
    return f"{rule.rstrip(':')}: {detail}"[:300]


def _run_snakemake(command: list[str], workdir: Path, log_path: Path, timeout_s: float) -> None:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    with open(log_path, "a") as log_file:
        log_file.write(f"$ {' '.join(command)}\n")
        log_file.flush()
        result = subprocess.run(command, stdout=log_file, stderr=subprocess.STDOUT, env=env, timeout=timeout_s,
                                check=False)
    if result.returncode != 0:
        raise StabilityError(failure_reason(log_path.read_text(errors="replace"), workdir))


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's finished children and their descendants."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _write_row(workdir: Path, row: Mapping) -> None:
    _write_atomic(workdir / "row.json", lambda tmp: tmp.write_text(json.dumps(row, indent=1, allow_nan=False)))


def run_case(case: Case, workdir: str | Path, snakefile: str | Path, cores: int = 2, iterations: int = 2,
             jax_cache: str | Path | None = None, timeout_s: float = 3600.0) -> dict:
    """Run one case from scratch in ``workdir`` (deleted first) and return its table row.

    Steps: write ``override.yaml`` (:func:`case_config`); when the case edits the capture, make it
    (rule synth_capture) and edit it; when it perturbs the initial mesh, run up to mesh/init.ply and perturb
    it; then the whole workflow. Snakemake's output goes to ``workdir/snakemake.log``. A failed run gives a
    row with status "failed" and the reason (nothing is raised).
    """
    import yaml

    workdir = Path(workdir)
    if workdir.exists():
        shutil.rmtree(workdir)
    workdir.mkdir(parents=True)
    config = case_config(case, workdir, iterations, jax_cache)
    override = workdir / "override.yaml"
    override.write_text(yaml.safe_dump(config, sort_keys=False))
    log_path = workdir / "snakemake.log"
    scene = config["demo"]["scene"]
    started, cpu_started = time.perf_counter(), _children_cpu_s()
    error = None
    try:
        def snakemake(*args: str) -> None:
            _run_snakemake(snakemake_command(Path(snakefile), workdir, override, "--cores", str(cores), *args),
                           workdir, log_path, timeout_s)

        if case.edits_capture:
            snakemake(f"captures/{scene}/capture.yaml")
            capture = workdir / "captures" / scene
            if case.flash_offset_m is not None:
                true, declared = miscalibrate_flash(capture, case.flash_offset_m)
                log.info("%s: flash at %s m, capture.yaml now says %s m", case.name, true, declared)
            if case.missing or case.corrupt or case.truncated:
                touched = damage_frames(capture, case.missing, case.corrupt, case.truncated, seed=PERTURB_SEED)
                log.info("%s: damaged %s", case.name, ", ".join(touched))
        if case.perturb_m:
            mesh = f"results/{case.name}/mesh/init.ply"
            snakemake(mesh)
            perturb_mesh_file(workdir / mesh, case.perturb_m, PERTURB_SEED)
            log.info("%s: initial mesh perturbed along its normals by %.2f mm RMS", case.name, 1000 * case.perturb_m)
        snakemake()
    except (StabilityError, subprocess.TimeoutExpired) as exc:
        error = str(exc) if isinstance(exc, StabilityError) else f"timed out after {timeout_s:.0f} s"
    wall_s, cpu_s = time.perf_counter() - started, _children_cpu_s() - cpu_started
    row = case_row(case, workdir, wall_s, error, cpu_s)
    _write_row(workdir, row)
    return row


def write_tables(rows: Sequence[Mapping], out: str | Path) -> Path:
    """Validate the rows and write ``out/stability.csv`` and ``out/stability.md`` (each atomically); returns
    the CSV path."""
    table = validate_table(rows)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _write_atomic(out / "stability.csv", lambda tmp: table.to_csv(tmp, index=False))
    _write_atomic(out / "stability.md", lambda tmp: tmp.write_text(markdown_table(table)))
    return out / "stability.csv"


def run_suite(cases: Sequence[Case], out: str | Path, snakefile: str | Path, cores: int = 2, iterations: int = 2,
              keep: bool = False, runner: Callable[..., dict] = run_case):
    """Run ``cases`` one after the other under ``out/runs/<case>`` (sharing ``out/jax_cache``) and write the
    tables (:func:`write_tables`). ``keep``: reuse the run of a case that already ran (``runs/<case>/row.json``):
    its figures are read again from its run folder (columns added since it ran get filled), its times and
    error kept. Returns the validated table."""
    out = Path(out)
    rows = []
    began = time.perf_counter()
    for index, case in enumerate(cases, 1):
        workdir = out / "runs" / case.name
        previous = workdir / "row.json"
        if keep and previous.is_file():
            kept = json.loads(previous.read_text())
            row = case_row(case, workdir, kept["wall_s"], kept.get("error") or None, kept.get("cpu_s"))
            _write_row(workdir, row)
            rows.append(row)
            log.info("[%d/%d] %s: kept the earlier run (%s)", index, len(cases), case.name, previous)
            continue
        log.info("[%d/%d] %s: %s", index, len(cases), case.name, case.breaks)
        row = runner(case, workdir, snakefile, cores=cores, iterations=iterations, jax_cache=out / "jax_cache")
        rows.append(row)
        log.info("[%d/%d] %s: %s in %.0f s (CPU %s s); normal median %s deg, eta median %s %%, finite %s, "
                 "bad flagged %s", index, len(cases), case.name, row["status"], row["wall_s"],
                 _fmt(row["cpu_s"], 0), _fmt(row["normal_median_deg"], 2), _fmt(row["eta_median_pct"]),
                 row["outputs_finite"], _fmt(row["bad_flagged"], percent=True))
        if row["status"] != "ok":
            log.warning("%s failed: %s (see %s)", case.name, row["error"], workdir / "snakemake.log")
    write_tables(rows, out)
    log.info("wrote %s and %s: %d cases in %.0f s", out / "stability.csv", out / "stability.md", len(rows),
             time.perf_counter() - began)
    return validate_table(rows)
