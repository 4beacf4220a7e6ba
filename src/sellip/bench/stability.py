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
    stability_markdown(table) -> str
    run_case(case, workdir, snakefile, cores=2, ...) -> dict
    run_snakemake(command, workdir, log_path, timeout_s, cpus=None) -> None   # StabilityError with the reason
    run_failure(steps, timeout_s) -> str | None          # why a run's Snakemake calls failed (None: they did not)
    write_row(workdir, row)                               # workdir/row.json, atomically (a resumed run reads it)
    missing_packages(case) -> list[str]                  # the packages of case.needs not installed (case skipped)
    run_suite(cases, out, snakefile, cores=2, ...) -> DataFrame       # writes stability.csv / .md

Confidence flagging (per case, over every vertex of final/model.ply): a vertex is *bad* when its normal
is more than ``bad_above`` (10°) from the normal of its nearest ground-truth vertex
(:func:`sellip.report.figures_of_merit.vertex_errors`), *flagged* when its confidence is below ``low_below`` (0.5).
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
from pathlib import Path

import numpy as np

from sellip.bench.stability_table import Case, case_row, format_cell, stability_markdown, validate_table
from sellip.bench.sweep_plan import merge

log = logging.getLogger(__name__)


BASE_VIEWS = 36
BASE_SEED = 3
PERTURB_SEED = 20220804


class StabilityError(RuntimeError):
    """A case could not be set up or run (the message says which case and which step)."""




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
    Case("tiny_plain", "renderer", "tiny without single scattering (scene tiny_plain), sellip's renderer: the "
         "reference of mitsuba_tiny", config={"demo": {"scene": "tiny_plain"}}),
    Case("mitsuba_tiny", "renderer", "tiny_plain rendered by Mitsuba 3 (pplastic): a renderer sellip was not tuned "
         "on", config={"demo": {"scene": "tiny_plain", "renderer": "mitsuba"}}, needs=("mitsuba",)),
    Case("pplastic_set", "renderer", "four pplastic materials, eta 1.33-2.0 (scene pplastic_set), sellip's "
         "renderer", config={"demo": {"scene": "pplastic_set"}}),
    Case("mitsuba_set", "renderer", "pplastic_set rendered by Mitsuba 3",
         config={"demo": {"scene": "pplastic_set", "renderer": "mitsuba"}}, needs=("mitsuba",)),
    Case("mitsuba_uniform_bright", "renderer", "uniform_bright rendered by Mitsuba 3",
         config={"demo": {"scene": "uniform_bright", "renderer": "mitsuba"}}, needs=("mitsuba",)),
    Case("mitsuba_uniform_dark", "renderer", "uniform_dark (rho_d 0.04, one material) rendered by Mitsuba 3",
         config={"demo": {"scene": "uniform_dark", "renderer": "mitsuba"}}, needs=("mitsuba",)),
    Case("mitsuba_cow", "renderer", "the cow (flat black and white patches, concavities) rendered by Mitsuba 3",
         config={"demo": {"scene": "cow", "renderer": "mitsuba"}}, needs=("mitsuba",)),
    Case("cow_dark", "degenerate", "the cow's shape in one uniformly coloured very dark glossy material, rho_d "
         "0.045, no texture (scene cow_dark)", config={"demo": {"scene": "cow_dark"}}),
    Case("mitsuba_cow_dark", "renderer", "cow_dark rendered by Mitsuba 3",
         config={"demo": {"scene": "cow_dark", "renderer": "mitsuba"}}, needs=("mitsuba",)),
    Case("bowl", "geometry", "a 14 mm deep hollow that no silhouette shows, so the visual hull bridges it (up to "
         "6 mm above its floor; scene bowl)", config={"demo": {"scene": "bowl"}}),
    Case("mitsuba_bowl", "renderer", "the bowl rendered by Mitsuba 3 (its hollow lit by interreflections too)",
         config={"demo": {"scene": "bowl", "renderer": "mitsuba"}}, needs=("mitsuba",)),
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


def case_config(case: Case, workdir: str | Path, iterations: int = 2, jax_cache: str | Path | None = None,
                noise_seed: int | None = None) -> dict:
    """The full override of one case: :func:`base_config` with the case's views and ``config`` merged in;
    ``noise_seed``: the capture's sensor noise drawn with that seed (``demo.noise_seed``; None: the case's own)."""
    config = base_config(workdir, case.views or BASE_VIEWS, iterations, jax_cache)
    config = merge(config, {"name": case.name, **case.config})
    if noise_seed is not None:
        config["demo"]["noise_seed"] = int(noise_seed)
    return config


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
    from sellip.geometry.meshes import vertex_normals
    from sellip.model.ply import read_ply, write_ply

    path = Path(path)
    vertex, faces = read_ply(path)
    if faces is None or not {"x", "y", "z", "nx", "ny", "nz"} <= set(vertex):
        raise StabilityError(f"{path}: expected a triangle mesh with x y z nx ny nz vertex properties")
    xyz = np.stack([vertex[k] for k in "xyz"], axis=1)
    moved = perturb_along_normals(xyz, np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1), sigma_m, seed)
    normals = vertex_normals(moved, np.asarray(faces, np.int64), area_weighted=True)
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


def run_snakemake(command: list[str], workdir: Path, log_path: Path, timeout_s: float,
                   cpus: set[int] | None = None) -> None:
    """Run ``command``, its output appended to ``log_path``; ``cpus``: pin it and everything it starts to those CPUs
    (XLA then sizes its thread pool to them). Raises :class:`StabilityError` with the reason when it fails."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    pin = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
    with open(log_path, "a") as log_file:
        log_file.write(f"$ {' '.join(command)}\n")
        log_file.flush()
        result = subprocess.run(command, stdout=log_file, stderr=subprocess.STDOUT, env=env, timeout=timeout_s,
                                check=False, preexec_fn=pin)
    if result.returncode != 0:
        raise StabilityError(failure_reason(log_path.read_text(errors="replace"), workdir))


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's finished children and their descendants."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def write_row(workdir: Path, row: Mapping) -> None:
    """Write a run's table row to ``workdir/row.json`` (atomically: a benchmark that resumes never reads half a row)."""
    _write_atomic(workdir / "row.json", lambda tmp: tmp.write_text(json.dumps(row, indent=1, allow_nan=False)))


def run_failure(steps: Callable[[], None], timeout_s: float) -> str | None:
    """Call ``steps`` (a run's Snakemake calls, :func:`run_snakemake`); None when they succeed, else why they failed:
    the :class:`StabilityError` reason or "timed out after <timeout_s> s". A benchmark's failed run is a row, not a
    crash."""
    try:
        steps()
    except StabilityError as exc:
        return str(exc)
    except subprocess.TimeoutExpired:
        return f"timed out after {timeout_s:.0f} s"
    return None


def run_case(case: Case, workdir: str | Path, snakefile: str | Path, cores: int = 2, iterations: int = 2,
             jax_cache: str | Path | None = None, timeout_s: float = 3600.0, noise_seed: int | None = None) -> dict:
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
    config = case_config(case, workdir, iterations, jax_cache, noise_seed)
    override = workdir / "override.yaml"
    override.write_text(yaml.safe_dump(config, sort_keys=False))
    log_path = workdir / "snakemake.log"
    scene = config["demo"]["scene"]
    started, cpu_started = time.perf_counter(), _children_cpu_s()
    def steps() -> None:
        def snakemake(*args: str) -> None:
            run_snakemake(snakemake_command(Path(snakefile), workdir, override, "--cores", str(cores), *args),
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

    error = run_failure(steps, timeout_s)
    wall_s, cpu_s = time.perf_counter() - started, _children_cpu_s() - cpu_started
    row = case_row(case, workdir, wall_s, error, cpu_s)
    write_row(workdir, row)
    return row


def missing_packages(case: Case) -> list[str]:
    """The packages of ``case.needs`` that cannot be imported here."""
    import importlib.util

    return [name for name in case.needs if importlib.util.find_spec(name) is None]


def write_tables(rows: Sequence[Mapping], out: str | Path) -> Path:
    """Validate the rows and write ``out/stability.csv`` and ``out/stability.md`` (each atomically); returns
    the CSV path."""
    table = validate_table(rows)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _write_atomic(out / "stability.csv", lambda tmp: table.to_csv(tmp, index=False))
    _write_atomic(out / "stability.md", lambda tmp: tmp.write_text(stability_markdown(table)))
    return out / "stability.csv"


def run_suite(cases: Sequence[Case], out: str | Path, snakefile: str | Path, cores: int = 2, iterations: int = 2,
              keep: bool = False, runner: Callable[..., dict] = run_case, noise_seed: int | None = None):
    """Run ``cases`` one after the other under ``out/runs/<case>`` (sharing ``out/jax_cache``) and write the
    tables (:func:`write_tables`); ``noise_seed``: every case's capture with that sensor-noise seed. ``keep``: reuse
    the run of a case that already ran (``runs/<case>/row.json``): its figures are read again from its run folder
    (columns added since it ran get filled), its times and error kept. Returns the validated table."""
    out = Path(out)
    rows = []
    began = time.perf_counter()
    for index, case in enumerate(cases, 1):
        workdir = out / "runs" / case.name
        missing = missing_packages(case)
        if missing:
            log.warning("[%d/%d] %s: skipped, it needs %s (pip install 'sellip[test]')", index, len(cases), case.name,
                        ", ".join(missing))
            continue
        previous = workdir / "row.json"
        if keep and previous.is_file():
            kept = json.loads(previous.read_text())
            row = case_row(case, workdir, kept["wall_s"], kept.get("error") or None, kept.get("cpu_s"))
            write_row(workdir, row)
            rows.append(row)
            log.info("[%d/%d] %s: kept the earlier run (%s)", index, len(cases), case.name, previous)
            continue
        log.info("[%d/%d] %s: %s", index, len(cases), case.name, case.breaks)
        row = runner(case, workdir, snakefile, cores=cores, iterations=iterations, jax_cache=out / "jax_cache",
                     noise_seed=noise_seed)
        rows.append(row)
        log.info("[%d/%d] %s: %s in %.0f s (CPU %s s); normal median %s deg, eta median %s %%, finite %s, "
                 "bad flagged %s", index, len(cases), case.name, row["status"], row["wall_s"],
                 format_cell(row["cpu_s"], 0), format_cell(row["normal_median_deg"], 2),
                 format_cell(row["eta_median_pct"]), row["outputs_finite"],
                 format_cell(row["bad_flagged"], percent=True))
        if row["status"] != "ok":
            log.warning("%s failed: %s (see %s)", case.name, row["error"], workdir / "snakemake.log")
    write_tables(rows, out)
    log.info("wrote %s and %s: %d cases in %.0f s", out / "stability.csv", out / "stability.md", len(rows),
             time.perf_counter() - began)
    return validate_table(rows)
