"""One fit shard (rule ``fit_pbrdf``) and the gather of an iteration's shards into ``fit.zarr`` (rule
``gather_fit``): settings records from ``key=value`` pairs (the benchmarks' replay tools), XLA's persistent
compilation cache, :func:`fit_shard` and :func:`gather_shards`; what the job may use (:func:`memory_budget`) and
the message that names the shard count that fits (the shards' rows and memory model: :mod:`sellip.fit.shard_plan`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import time
from pathlib import Path

import numpy as np

from sellip.fit.records import FitJobSettings
from sellip.fit.shard_plan import SHARD_MEMORY, ShardMemory, ShardMemoryError, largest_shard, shard_rows
from sellip.jobs import atomic_file

log = logging.getLogger(__name__)


def parse_shard(text: str) -> tuple[int, int]:
    """'i-of-n' (Snakemake's scatteritem, 1-based) -> (i - 1, n)."""
    try:
        index, total = text.split("-of-")
        index, total = int(index), int(total)
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"--shard expects 'i-of-n' (e.g. 2-of-4), got {text!r}") from error
    if not 1 <= index <= total:
        raise argparse.ArgumentTypeError(f"--shard {text!r}: i must be in 1..n")
    return index - 1, total



def overrides_from_pairs(pairs: list[str], settings_class) -> dict:
    """{field: value} of ``key=value`` pairs for the dataclass ``settings_class`` (types from its fields;
    'null'/'none' -> None). Raises ValueError naming the pair for an unknown key or a value of the wrong type."""
    fields = {f.name: f for f in dataclasses.fields(settings_class)}
    values = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or key not in fields:
            raise ValueError(f"--set expects KEY=VALUE with KEY one of {sorted(fields)}, got {pair!r}")
        if fields[key].type in ("str", str):
            values[key] = text
        elif text.lower() in ("null", "none", ""):
            values[key] = None
        elif fields[key].type in ("bool", bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"--set {key} expects true or false, got {text!r}")
            values[key] = text.lower() in ("true", "1")
        else:
            kind = int if fields[key].type in ("int", int) else float
            try:
                values[key] = kind(text)
            except ValueError:
                raise ValueError(f"--set {key} expects a{'n integer' if kind is int else ' number'}, "
                                 f"got {text!r}") from None
    return values



def enable_compilation_cache(directory: str | Path | None) -> None:
    """Reuse XLA compilations across processes (every shard job compiles the same kernels), and the
    exported kernels under ``directory/exported`` (:mod:`sellip.fit.kernels`: no tracing in later jobs)."""
    if not directory:
        return
    import jax

    from sellip.fit import kernels

    Path(directory).mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(Path(directory).resolve()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    kernels.enable(Path(directory).resolve() / "exported")



def available_memory(root: str | Path = "/") -> int | None:
    """Bytes this process may still allocate: the smaller of the system's MemAvailable (``/proc/meminfo``) and the
    room left under its cgroup's limit (v2 ``memory.max`` - ``memory.current``, or v1's; a SLURM job's ``--mem``);
    None where neither can be read. ``root``: where /proc and /sys are (tests)."""
    root = Path(root)
    candidates = []
    try:
        for line in (root / "proc" / "meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                candidates.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    for limit_file, usage_file in (("sys/fs/cgroup/memory.max", "sys/fs/cgroup/memory.current"),
                                   ("sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = (root / limit_file).read_text().strip()
            if limit != "max" and int(limit) < 1 << 60:
                candidates.append(max(int(limit) - int((root / usage_file).read_text().strip()), 0))
                break
        except (OSError, ValueError):
            continue
    return min(candidates) if candidates else None


def memory_budget(mem_mb: float | None, root: str | Path = "/") -> tuple[float | None, str]:
    """(bytes a fit job may use, where that number comes from): the job's ``mem_mb`` (the rule's resource,
    config ``fit.mem_mb``) or what the machine has available now (:func:`available_memory`), the smaller."""
    options = []
    if mem_mb:
        options.append((mem_mb * 1e6, f"the job's {mem_mb:,.0f} MB (its mem_mb resource: config fit.mem_mb)"))
    available = available_memory(root)
    if available is not None:
        options.append((float(available), f"the {available / 1e9:.1f} GB this machine has available"))
    return min(options) if options else (None, "no limit known")


def shard_memory_message(shard: tuple[int, int], vertices: int, total: int, views: int, chunk_size: int,
                         budget: float, source: str, vertex_chunk: int = 1, model: ShardMemory = SHARD_MEMORY) -> str:
    """What to do when shard ``shard`` (0-based index, count) of ``total`` vertices (store chunks of
    ``vertex_chunk``) does not fit in ``budget`` bytes."""
    need = model.bytes(vertices, views, chunk_size)
    shards = model.shards_for(total, views, chunk_size, budget, vertex_chunk)
    text = (f"fit shard {shard[0] + 1} of {shard[1]} needs about {need / 1e9:.2f} GB for its {vertices:,} vertices "
            f"of {views} views, more than {source}")
    if shards is None:
        return text + (f": no shard count fits (one vertex needs {model.bytes(1, views, chunk_size) / 1e9:.2f} GB); "
                       "raise fit.mem_mb or run on a machine with more memory (docs/reliability.md)")
    shards = max(shards, shard[1] + 1)  # the job did not fit: at least one more
    per_shard = model.bytes(largest_shard(total, vertex_chunk, shards), views, chunk_size)
    return text + (f": run with fit.shards: {shards} (--config 'fit={{shards: {shards}}}'; each job then needs "
                   f"about {per_shard / 1e9:.2f} GB) or raise fit.mem_mb to {math.ceil(need / 1e6 / 100) * 100:,} "
                   "(docs/reliability.md)")


def fit_shard(observations: Path, shard: tuple[int, int], output: Path, prior: Path | None = None,
              dtype: str = FitJobSettings.dtype, settings=None, compilation_cache: str | None = None,
              lobes: Path | None = None, fixed_sigma_ss: float | None = None, mem_mb: float | None = None) -> dict:
    """Fit one shard and write ``output`` (.npz, atomically); with ``lobes`` the augmented refit.
    Every vertex is fitted with its model (module docstring); ``fixed_sigma_ss`` is model 2's
    sigma_ss when ``settings.sigma_ss_fixed`` is None (None: config ``model_selection.model2_sigma_ss``'s default).
    Returns a summary dict. Before reading the observations,
    the memory the shard needs (:data:`SHARD_MEMORY`) is checked against :func:`memory_budget` (``mem_mb``: the
    job's limit); :class:`ShardMemoryError` names the shard count that fits, then and when an allocation fails.

    """
    from sellip.timing import mark

    mark("imports")
    import jax

    if dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    enable_compilation_cache(compilation_cache)
    from sellip.fit.observe import open_observations
    from sellip.fit.records import DEFAULT_FIXED_SIGMA_SS, FitSettings

    mark("read")
    settings = settings or FitSettings()
    fixed_sigma_ss = DEFAULT_FIXED_SIGMA_SS if fixed_sigma_ss is None else fixed_sigma_ss
    group = open_observations(observations)
    total = int(group.attrs["num_vertices"])
    chunk = int(group["diffuse"].chunks[0])
    start, stop = shard_rows(total, chunk, *shard)
    log.info("shard %d of %d: vertices [%d, %d) of %d", shard[0] + 1, shard[1], start, stop, total)
    views = int(group["diffuse"].shape[1])
    budget, source = memory_budget(mem_mb)
    need = SHARD_MEMORY.bytes(stop - start, views, settings.chunk_size)
    halved = SHARD_MEMORY.shards_for(total, views, settings.chunk_size, (need + SHARD_MEMORY.base) / 2, chunk)
    log.info("memory: about %.2f GB for %d vertices of %d views; may use %s%s", need / 1e9, stop - start, views,
             source, f" (fit.shards: {halved} would halve the part that grows with the vertices)" if halved else "")
    if budget is not None and need > budget:
        raise ShardMemoryError(shard_memory_message(shard, stop - start, total, views, settings.chunk_size, budget,
                                                    source, chunk))
    try:
        return fit_rows(observations, group, total, start, stop, output, prior, dtype, settings, lobes,
                         fixed_sigma_ss)
    except Exception as error:
        # numpy raises MemoryError when an allocation fails, XLA an XlaRuntimeError "RESOURCE_EXHAUSTED: Out of
        # memory". (The kernel's OOM killer sends SIGKILL, which no handler sees: the "memory:" line above is
        # then the log's last word, and the console says so: workflow_support.format_failures.)
        if not isinstance(error, MemoryError) and "RESOURCE_EXHAUSTED" not in str(error):
            raise
        # It did not fit in what the job had: at most ~99 % of the estimate, whatever the budget said.
        budget, source = memory_budget(mem_mb)
        raise ShardMemoryError(f"out of memory ({type(error).__name__}): " + shard_memory_message(
            shard, stop - start, total, views, settings.chunk_size, min(budget or need, 0.99 * need),
            source, chunk)) from error


def fit_rows(observations, group, total, start, stop, output, prior, dtype, settings, lobes, fixed_sigma_ss) -> dict:
    """:func:`fit_shard` after the memory check: read the rows, start values, virtual samples, fit by model, write.

    Long: one job's steps in order (read, prior, virtual samples, fit by model, write), each a call."""
    from sellip.fit.observe import load_observations
    from sellip.fit.records import STATUS_NAMES, model_of
    from sellip.fit.selection import cap_models, fit_by_model
    from sellip.fit.vertex_fit import default_prior
    from sellip.model.params import PARAM_FIELDS, params_from, read_params, same_vertices, transfer_nearest
    from sellip.timing import mark

    data = load_observations(observations, start, stop)
    float_type = np.dtype(dtype)
    obs = type(data.observations)(*[np.asarray(x, float_type) if np.asarray(x).dtype.kind == "f" else np.asarray(x)
                                    for x in data.observations])
    n = stop - start
    normal0 = data.normals.astype(float_type)
    virtual = None
    models, source = np.full(n, model_of(settings), np.uint8), "the fit settings"
    if lobes is not None:
        from sellip.fit.lobe_store import read_lobes, read_models
        from sellip.fit.lobes import virtual_samples

        labels, cluster_lobes = read_lobes(lobes)
        if len(labels) != total:
            raise ValueError(f"{lobes}/labels.npy: {len(labels)} labels for the {total} vertices of {observations}")
        virtual = virtual_samples(labels[start:stop], cluster_lobes, settings, float_type)
        models, source = read_models(lobes, total)[start:stop], f"{lobes}/models.npy"
        log.info("augmented fit: %d cluster lobes, %d virtual samples per vertex, lambda_g %g",
                 len(cluster_lobes), settings.virtual_count, settings.lambda_g)
    if prior is not None:
        previous = read_params(prior)
        nearest = transfer_nearest(previous["vertices"], data.vertices)
        start_params = params_from({k: previous[k][nearest] for k in PARAM_FIELDS}, float_type)
        log.info("warm start from %s (nearest of %d vertices)", prior, len(previous["vertices"]))
        if lobes is None and "model" in previous:
            models, source = previous["model"][nearest], f"{prior} (nearest vertex)"
        same_mesh = len(previous["vertices"]) == total and same_vertices(previous["vertices"][start:stop],
                                                                         data.vertices)
        if lobes is not None and same_mesh:
            normal0 = previous["normals"][start:stop].astype(float_type)
            log.info("refit: starting normals from %s", prior)
        elif lobes is not None:
            log.info("%s is on another mesh (the previous iteration's): the starting normals are the mesh's", prior)
    else:
        start_params = default_prior(n, float_type)
    models = cap_models(models, settings)
    per_model = {int(m): int(np.sum(models == m)) for m in np.unique(models)}
    log.info("models from %s: %s vertices per model (model 2's sigma_ss %s)", source, per_model,
             settings.sigma_ss_fixed if settings.sigma_ss_fixed is not None else fixed_sigma_ss)
    mark("fit")
    began = time.perf_counter()
    if n:
        result = fit_by_model(obs, normal0, start_params, models, settings, fixed_sigma_ss,
                              progress=lambda done: log.info("fitted %d / %d vertices (%.0f s)", done, n,
                                                             time.perf_counter() - began), virtual=virtual)
    seconds = time.perf_counter() - began
    mark("write")
    arrays = {"start": np.asarray(start), "stop": np.asarray(stop)}
    if n:
        arrays.update(normal=result.normal, status=result.status, confidence=result.confidence, loss=result.loss,
                      views_used=result.views_used, iterations=result.iterations,
                      normal_std_deg=result.normal_std_deg, eta_std=result.eta_std,
                      sigma_s_std=result.sigma_s_std, model=models,
                      **{name: getattr(result.params, name) for name in result.params._fields})
    with atomic_file(output) as tmp:
        np.savez(tmp, **arrays)
    counts = {STATUS_NAMES[s]: int(np.sum(result.status == s)) for s in STATUS_NAMES} if n else {}
    summary = {"vertices": n, "seconds": seconds, "vertex_fits_per_second": n / seconds if seconds > 0 else 0.0,
               "status": counts, "models": per_model}
    log.info("shard done: %d vertices in %.1f s (%.0f vertex-fits/s); %s", n, seconds,
             summary["vertex_fits_per_second"], counts)
    return summary


def gather_shards(observations: Path, shards: list[Path], output: Path, min_fitted_share: float = 0.0) -> dict:
    """Assemble the shards of one pass into its params store (sellip.stages.gather_fit). Before writing, the fitted
    share of the visible surface is checked against ``min_fitted_share`` (:func:`sellip.fit.evidence.check_evidence`;
    EvidenceError, nothing written)."""
    from sellip.fit.evidence import check_evidence
    from sellip.fit.observe import open_observations
    from sellip.fit.records import STATUS_FITTED, STATUS_NAMES
    from sellip.model.params import (
        PARAM_FIELDS,
        ParamsError,
        fill_from_neighbours,
        write_params,
    )

    group = open_observations(observations)
    total = int(group.attrs["num_vertices"])
    parts = []
    for path in shards:
        with np.load(path) as data:
            parts.append({k: data[k] for k in data.files})
    parts.sort(key=lambda p: int(p["start"]))
    covered = 0
    for path, part in zip(shards, parts):
        if int(part["start"]) != covered:
            raise ParamsError(f"{path}: starts at vertex {int(part['start'])}, expected {covered} "
                              f"(the shards must cover [0, {total}) once)")
        covered = int(part["stop"])
    if covered != total:
        raise ParamsError(f"{observations}: the shards cover [0, {covered}) of {total} vertices")
    parts = [p for p in parts if int(p["stop"]) > int(p["start"])]
    names = ("normal", "status", "confidence", "loss", "views_used", "iterations", "normal_std_deg", "eta_std",
             "sigma_s_std", *PARAM_FIELDS)
    if parts and all("model" in p for p in parts):
        names += ("model",)
    arrays = {name: np.concatenate([p[name] for p in parts]) for name in names}
    vertices = np.asarray(group["vertices"][:])
    fitted = arrays["status"] == STATUS_FITTED
    for name in PARAM_FIELDS:
        arrays[name] = fill_from_neighbours(vertices, arrays[name], fitted)
    arrays["normal"] /= np.maximum(np.linalg.norm(arrays["normal"], axis=1, keepdims=True), 1e-12)
    arrays["confidence"] = np.where(fitted, arrays["confidence"], 0.0)
    counts = {STATUS_NAMES[s]: int(np.sum(arrays["status"] == s)) for s in STATUS_NAMES}
    share = check_evidence(arrays["status"], np.asarray(group["usable"][:]), list(group.attrs["view_ids"]),
                           min_fitted_share, str(observations))
    log.info("fitted share of the visible surface: %.3f (fit.min_fitted_share %g)", share, min_fitted_share)
    normals = arrays.pop("normal")
    attrs = {"status_counts": counts, "status_names": {str(k): v for k, v in STATUS_NAMES.items()}}
    if "model" in arrays:
        attrs["model_counts"] = {str(m): int(np.sum(arrays["model"] == m)) for m in np.unique(arrays["model"])}
    write_params(output, {"vertices": vertices, "normals": normals, **arrays}, attrs=attrs)
    log.info("%s: %d vertices, %s; vertices per model %s", output, total, counts, attrs.get("model_counts"))
    return counts
