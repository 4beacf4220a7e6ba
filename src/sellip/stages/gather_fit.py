"""``sellip gather-fit``: assemble the fit shards of one iteration into its params.zarr (rule ``gather_fit``).

    sellip gather-fit --observations results/NAME/iter/0/observations.zarr
                      --shards results/NAME/iter/0/fit/1-of-2.npz results/NAME/iter/0/fit/2-of-2.npz
                      --output results/NAME/iter/0/fit.zarr

The shards must cover the store's vertices exactly once. Vertices that could not be fitted
(too few views, failed) get parameters interpolated from their fitted neighbours and confidence 0
(DESIGN §7); they keep their starting normal (the mesh's: a neighbour's normal belongs to another
part of the surface; interpolating them left the demo's unlit underside 17 deg median off its own
mesh) and their ``model`` (their cluster's, not fitted). The store
layout is :mod:`sellip.model.params`; ``model`` (the model each vertex was fitted with) is written when
every shard has it.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def run_stage(observations: Path, shards: list[Path], output: Path) -> dict:
    from sellip.fit.observe import open_observations
    from sellip.fit.records import STATUS_FITTED, STATUS_NAMES
    from sellip.model.params import PARAM_FIELDS, ParamsError, fill_from_neighbours, write_params

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
    normals = arrays.pop("normal")
    attrs = {"status_counts": counts, "status_names": {str(k): v for k, v in STATUS_NAMES.items()}}
    if "model" in arrays:
        attrs["model_counts"] = {str(m): int(np.sum(arrays["model"] == m)) for m in np.unique(arrays["model"])}
    write_params(output, {"vertices": vertices, "normals": normals, **arrays}, attrs=attrs)
    log.info("%s: %d vertices, %s; vertices per model %s", output, total, counts, attrs.get("model_counts"))
    return counts


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--observations", type=Path, required=True)
    parser.add_argument("--shards", type=Path, nargs="+", required=True)
    parser.add_argument("--output", type=Path, required=True)


def main(args: argparse.Namespace) -> int:
    from sellip.fit.observe import ObserveError
    from sellip.model.params import ParamsError

    try:
        run_stage(args.observations, args.shards, args.output)
    except (ObserveError, ParamsError) as error:
        log.error("%s", error)
        return 1
    return 0
