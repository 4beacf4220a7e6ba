"""Speed-accuracy sweep of the whole workflow (issue #9): one factor at a time from a base configuration.

Public API::

    Factor, FACTORS, PRESETS, Variant
    plan_variants(scenes, preset, only=None) -> list[Variant]     # per scene: the base, then each factor value
    variant_overrides(variant, preset, capture, cache) -> dict      # the config file of one snakemake run
    pareto_front(cost, loss) -> (N,) bool                          # non-dominated points, both minimized
    front_marks(table) -> list[str]                                # which charted figures a row is on the front of
    job_cpu_seconds(benchmarks_dir) -> {rule: CPU s}
    sweep_row(variant, metrics, record, preset, cpu) -> dict; SWEEP_COLUMNS; sweep_schema()
    sweep_figure(table) -> matplotlib Figure                       # accuracy against time, fronts marked
    PAPER_TABLE1; ior_table(model, truth, confident) -> DataFrame  # fitted eta per Table-1 material
    augmentation_table(table), sigma_ss_table(table), model_selection_table(table, vertex_models)
    markdown_table(frame, columns)
    link_upstream(source, target); cache_entries(directory) -> int
    SnakemakeRunner(workdir, cores); run_sweep(scenes, preset, workdir, runner, ...) -> list of records

Every variant is a real ``snakemake`` run of the repository's Snakefile with a config file on top of
config/config.yaml: the base of its preset and scene, plus the one key its factor changes. Variants whose
factor does not touch the capture, ingest, poses or initial mesh (all of FACTORS) reuse one upstream run
per scene: its outputs are hard-linked into the variant's results folder (mtimes kept) and snakemake runs
with ``--rerun-triggers mtime``, so only the reconstruction loop and the evaluation run again.

Times (seconds). Wall clock: ``upstream_s`` the shared upstream run (ingest, poses, initial mesh,
previews); ``run_s`` the variant's own snakemake run; ``total_s`` = upstream_s + run_s, what the whole
pipeline takes with this setting; per-rule job times from metrics.json ``timings``. CPU: ``cpu_s``, the
user + system time of snakemake and every job of the upstream run and of the variant's run
(``getrusage``), is the chart's cost axis (:data:`TIME_AXIS`): on a machine shared with other work, wall
time measures the neighbours as much as the variant.

XLA compilation: every job compiles its JAX kernels or loads them from the persistent cache that all jobs
share. The fit's settings are static arguments and its batch shapes follow the data, so a variant compiles
kernels no other run needed. With ``repeat=2`` (the default) a variant whose run spent more than
:data:`RECOMPILE_FRACTION` of its CPU time compiling runs again, and the second run, which finds its
kernels in the cache, is the one timed: the steady-state cost of a setting, as on a machine that has run
it before. The first run's times are kept (``cold_*``): their difference is what compiling costs the
first time. ``compiled``/``compile_s`` of the timed run say what compilation is left in its time.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from sellip.bench.sweep_plan import (
    FACTORS,
    REPO,
    Factor,
    SweepError,
    Variant,
    plan_variants,
    value_label,
    variant_overrides,
)
from sellip.bench.sweep_tables import FIGURES, metric_at
from sellip.jobs import write_text

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- running the workflow


UPSTREAM_RULES = ("linearize_frames", "merge_hdr", "plot_hdr_previews", "run_sfm", "init_mesh")
"""The rules before the reconstruction loop; none of them reads a swept setting."""

UPSTREAM_OUTPUTS = ("hdr.zarr", "previews", "cameras.csv", "sfm", "mesh")
"""Their outputs under results/NAME/ (linearize_frames' linear.zarr is temporary and gone)."""


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def link_upstream(source: str | Path, target: str | Path) -> None:
    """Hard-link the upstream outputs, benchmark files and logs of results folder ``source`` into ``target``
    (created), keeping every mtime (files share the inode; folders get their source's stat), so that
    ``snakemake --rerun-triggers mtime`` finds them up to date. SweepError when an output is missing."""
    source, target = Path(source), Path(target)
    for name in UPSTREAM_OUTPUTS:
        if not (source / name).exists():
            raise SweepError(f"{source / name} is missing: the upstream run did not finish")
    target.mkdir(parents=True, exist_ok=True)
    pairs = [(source / n, target / n) for n in UPSTREAM_OUTPUTS]
    pairs += [(source / "benchmarks" / f"{r}.tsv", target / "benchmarks" / f"{r}.tsv") for r in UPSTREAM_RULES]
    pairs += [(source / "logs" / f"{r}.log", target / "logs" / f"{r}.log") for r in UPSTREAM_RULES]
    for src, dst in pairs:
        if not src.exists():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, dst, copy_function=_link_or_copy, dirs_exist_ok=True)
        else:
            _link_or_copy(str(src), str(dst))


def cache_entries(directory: str | Path) -> int:
    """Files in the persistent XLA compilation cache (one per compiled program; 0 when it does not exist)."""
    directory = Path(directory)
    return sum(1 for p in directory.rglob("*") if p.is_file()) if directory.is_dir() else 0


class SnakemakeRunner:
    """Runs the repository's workflow in ``workdir``: ``runner(config, targets, log_path) -> (wall s, CPU s)``.

    The command is ``python -m snakemake TARGETS --snakefile REPO/Snakefile --directory WORKDIR --cores N
    --rerun-triggers mtime [EXTRA] --configfile REPO/config/config.yaml CONFIG`` (the config written to
    WORKDIR/configs/NAME.yaml; the targets first, as --rerun-triggers and --configfile take several values);
    its output goes to ``log_path``. CPU s: user + system time of snakemake and every job it ran
    (``getrusage(RUSAGE_CHILDREN)`` before and after; exact, whatever else the machine runs). JAX logs
    its compilations into the job logs (``JAX_LOG_COMPILES=1``, see :func:`xla_compile_seconds`).
    SweepError with the log's tail on failure.
    """

    def __init__(self, workdir: str | Path, cores: int = 2, repo: str | Path = REPO, python: str = sys.executable,
                 extra: tuple[str, ...] = ()):
        self.workdir, self.cores, self.repo, self.python = Path(workdir).resolve(), int(cores), Path(repo), python
        self.extra = tuple(extra)
        if not (self.repo / "Snakefile").is_file():
            raise SweepError(f"{self.repo / 'Snakefile'} does not exist: run the sweep from a checkout of sellip")

    def __call__(self, config: dict, targets: list[str], log_path: str | Path) -> float:
        import yaml

        config_path = self.workdir / "configs" / f"{config['name']}.yaml"
        config_path.parent.mkdir(parents=True, exist_ok=True)
        config_path.write_text(yaml.safe_dump(config, sort_keys=False))
        command = [self.python, "-m", "snakemake", *targets, "--snakefile", str(self.repo / "Snakefile"),
                   "--directory", str(self.workdir), "--cores", str(self.cores), "--rerun-triggers", "mtime",
                   *self.extra, "--configfile", str(self.repo / "config" / "config.yaml"), str(config_path)]
        env = {**os.environ, "PATH": f"{Path(self.python).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               "JAX_LOG_COMPILES": "1"}
        log_path = Path(log_path)
        log_path.parent.mkdir(parents=True, exist_ok=True)
        before = _children_cpu()
        started = time.perf_counter()
        with open(log_path, "w") as out:
            result = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, env=env, check=False)
        wall = time.perf_counter() - started
        cpu = _children_cpu() - before
        if result.returncode != 0:
            tail = "".join(log_path.read_text().splitlines(keepends=True)[-25:])
            raise SweepError(f"snakemake for {config['name']} failed (exit {result.returncode}); "
                             f"log {log_path}:\n{tail}")
        return wall, cpu


def _children_cpu() -> float:
    """User + system CPU seconds of this process's finished (waited-for) descendants."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


_XLA_HIT = re.compile(r"Persistent compilation cache hit for '")
_XLA_DONE = re.compile(r"Finished XLA compilation of .* in ([0-9.eE+-]+) sec")


def xla_compile_seconds(logs_dir: str | Path) -> tuple[float, int]:
    """XLA compilations in the job logs under ``logs_dir`` (written with ``JAX_LOG_COMPILES=1``): their summed
    wall time (s) and count, not counting executables loaded from the persistent cache (a "Finished XLA
    compilation" line right after a "Persistent compilation cache hit" line)."""
    seconds, count = 0.0, 0
    for path in sorted(Path(logs_dir).rglob("*.log")):
        hit = False
        for line in path.read_text(errors="replace").splitlines():
            if _XLA_HIT.search(line):
                hit = True
                continue
            done = _XLA_DONE.search(line)
            if done:
                if not hit:
                    seconds += float(done.group(1))
                    count += 1
                hit = False
    return seconds, count


RECOMPILE_FRACTION = 0.1
"""A run whose XLA compilations took more than this fraction of its CPU time is repeated (up to ``repeat``)."""

RECORD = "sweep_record.json"
"""Per results folder: what the sweep ran there (config, times); a finished variant is not run again."""


@dataclass
class SweepPaths:
    """Where one sweep works: WORKDIR/captures/SCENE, WORKDIR/results/NAME, WORKDIR/jax_cache, WORKDIR/logs."""

    workdir: Path
    results: Path = field(init=False)
    cache: Path = field(init=False)
    logs: Path = field(init=False)

    def __post_init__(self):
        self.workdir = Path(self.workdir).resolve()
        self.results, self.cache, self.logs = (self.workdir / "results", self.workdir / "jax_cache",
                                               self.workdir / "logs")

    def capture(self, scene: str) -> Path:
        return self.workdir / "captures" / scene


def _read_record(folder: Path, config: dict, needs: str | None = "metrics.json",
                 keys: tuple[str, ...] = ("cpu_s", "run_s")) -> dict | None:
    """The record of a finished run in ``folder`` with this exact config, its file ``needs`` and ``keys``
    (a record of an older sweep without them is stale), else None."""
    path = folder / RECORD
    if not path.is_file() or (needs is not None and not (folder / needs).is_file()):
        return None
    record = json.loads(path.read_text())
    if any(key not in record for key in keys):
        return None
    return record if record.get("config") == json.loads(json.dumps(config)) else None


def _write_record(folder: Path, record: dict) -> None:
    write_text(json.dumps(record, indent=2), folder / RECORD)


def prepare_scene(scene: str, preset: str, paths: SweepPaths, runner: Callable) -> dict:
    """Make the scene's capture (rule synth_capture) and its upstream run (ingest, poses, initial mesh,
    previews) once; returns the upstream record ({"name", "wall_s", ...})."""
    capture = paths.capture(scene)
    base = Variant(scene, "base")
    if not (capture / "capture.yaml").is_file():
        log.info("%s: synthesizing the capture (%s preset)", scene, preset)
        config = variant_overrides(base, preset, "", paths.cache, name=f"{scene}__capture")
        config["capture"] = ""
        wall, _ = runner(config, [f"captures/{scene}/capture.yaml"], paths.logs / f"{scene}__capture.log")
        log.info("%s: capture made in %.0f s", scene, wall)
    name = f"{scene}__upstream"
    config = variant_overrides(base, preset, capture, paths.cache, name=name)
    folder = paths.results / name
    record = _read_record(folder, config, needs="mesh/init.ply", keys=("cpu_s",))
    if record is not None:
        log.info("%s: upstream run done before (%.0f s), reused", scene, record["wall_s"])
        return record
    shutil.rmtree(folder, ignore_errors=True)
    log.info("%s: upstream run (ingest, poses, initial mesh, previews) starts", scene)
    wall, cpu = runner(config, [f"results/{name}/mesh/init.ply", f"results/{name}/previews"],
                       paths.logs / f"{name}.log")
    record = {"name": name, "wall_s": wall, "cpu_s": cpu, "config": config}
    _write_record(folder, record)
    log.info("%s: upstream run done in %.0f s (%.0f s CPU)", scene, wall, cpu)
    return record


def _figures(folder: Path) -> dict:
    """The FIGURES of a run's metrics.json (None where missing)."""
    metrics = json.loads((folder / "metrics.json").read_text())
    return {column: metric_at(metrics, path) for column, (path, _, _) in FIGURES.items()}


def run_variant(variant: Variant, preset: str, paths: SweepPaths, runner: Callable, upstream: dict,
                repeat: int = 2, force: bool = False) -> dict:
    """Run one variant, again while its run compiled much (more than :data:`RECOMPILE_FRACTION` of its CPU
    time) up to ``repeat`` runs, timing the last (module docstring), unless a record with the same config
    exists. Returns its record: config, runs, run_s, run_cpu_s, cpu_s, upstream_s, upstream_cpu_s,
    new_programs, compiled, compile_s, the first run's cold_run_s, cold_cpu_s, cold_compiled (None for one
    run), and whether the runs gave the same figures (``deterministic``, None for one run)."""
    if repeat < 1:
        raise SweepError(f"repeat must be at least 1, got {repeat}")
    capture = paths.capture(variant.scene)
    config = variant_overrides(variant, preset, capture, paths.cache)
    folder = paths.results / variant.name
    record = None if force else _read_record(folder, config)
    if record is not None:
        log.info("%s: done before (%.0f s, %.0f s CPU), reused", variant.name, record["run_s"], record["cpu_s"])
        return record
    shared = not variant.upstream
    runs = []
    for attempt in range(1, repeat + 1):
        shutil.rmtree(folder, ignore_errors=True)
        if shared:
            link_upstream(paths.results / upstream["name"], folder)
        before = cache_entries(paths.cache)
        log.info("%s: run %d/%d starts (%s = %s)", variant.name, attempt, repeat, variant.key or "base",
                 value_label(variant.value))
        wall, cpu = runner(config, [], paths.logs / f"{variant.name}.{attempt}.log")
        if not (folder / "metrics.json").is_file():
            raise SweepError(f"{folder / 'metrics.json'} missing after the run of {variant.name}")
        compile_s, compiled = xla_compile_seconds(folder / "logs")
        runs.append({"run_s": wall, "run_cpu_s": cpu, "new_programs": cache_entries(paths.cache) - before,
                     "compiled": compiled, "compile_s": compile_s, "figures": _figures(folder)})
        log.info("%s: run %d/%d done in %.0f s, %.0f s CPU (%d XLA compilations, %.0f s)", variant.name, attempt,
                 repeat, wall, cpu, compiled, compile_s)
        if compile_s <= RECOMPILE_FRACTION * cpu:
            break
    last, first = runs[-1], runs[0]
    repeated = len(runs) > 1
    record = {"name": variant.name, "config": config, **{k: v for k, v in last.items() if k != "figures"},
              "upstream_s": upstream["wall_s"] if shared else 0.0,
              "upstream_cpu_s": upstream["cpu_s"] if shared else 0.0, "runs": len(runs),
              "cold_run_s": first["run_s"] if repeated else None,
              "cold_cpu_s": first["run_cpu_s"] if repeated else None,
              "cold_compiled": first["compiled"] if repeated else None,
              "deterministic": all(r["figures"] == first["figures"] for r in runs) if repeated else None}
    record["cpu_s"] = record["upstream_cpu_s"] + last["run_cpu_s"]
    if repeated and not record["deterministic"]:
        log.warning("%s: the repeated runs gave different figures: %s vs %s", variant.name, first["figures"],
                    last["figures"])
    _write_record(folder, record)
    log.info("%s: %.0f s, %.0f s CPU with the shared upstream (%.0f s, %.0f s CPU)", variant.name,
             record["upstream_s"] + last["run_s"], record["cpu_s"], record["upstream_s"], record["upstream_cpu_s"])
    return record


def run_sweep(scenes: list[str], preset: str, workdir: str | Path, runner: Callable | None = None,
              cores: int = 2, only: list[str] | None = None, repeat: int = 2, force: bool = False,
              factors: tuple[Factor, ...] = FACTORS) -> tuple[list[Variant], list[dict]]:
    """Run every planned variant (see :func:`plan_variants`; each ``repeat`` times, :func:`run_variant`) in
    ``workdir``; returns the variants and their records, in order. ``runner``: :class:`SnakemakeRunner` of
    ``workdir`` when None."""
    paths = SweepPaths(Path(workdir))
    paths.workdir.mkdir(parents=True, exist_ok=True)
    runner = runner or SnakemakeRunner(paths.workdir, cores)
    variants = plan_variants(scenes, preset, only, factors)
    log.info("sweep (%s preset): %d variants on %s", preset, len(variants), ", ".join(scenes))
    records, started = [], time.perf_counter()
    upstream = {}
    for k, variant in enumerate(variants, 1):
        if variant.scene not in upstream:
            upstream[variant.scene] = prepare_scene(variant.scene, preset, paths, runner)
        log.info("[%d/%d] %s", k, len(variants), variant.name)
        records.append(run_variant(variant, preset, paths, runner, upstream[variant.scene], repeat, force))
    log.info("sweep done in %.0f s", time.perf_counter() - started)
    return variants, records
