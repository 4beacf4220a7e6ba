"""Per-vertex parameter stores (``params.zarr``) and carrying parameters between meshes.

A store holds, for N vertices (docs/design.md §4 names, float32 unless noted), chunked by vertex:

    vertices (N, 3), normals (N, 3), eta (N,), rho_d (N, 3), rho_s (N,), sigma_s (N,),
    rho_ss (N, 3), sigma_ss (N,), confidence (N,), status (N,) int8, loss (N,),
    views_used (N,) int16, iterations (N,) int16, normal_std_deg (N,), eta_std (N,) and sigma_s_std (N,)
    (the fit's Gauss-Newton standard deviations, inf where not fitted or where the
    Gauss-Newton matrix is singular, all with confidence 0); the final store adds model (N,) uint8
    (:data:`MODEL_NAMES`), cluster (N,) int32, eta_source and lobe_source (N,) uint8
    (:data:`sellip.fit.lobes.VALUE_SOURCES`) and eta_vertex, sigma_s_vertex, rho_s_vertex (N,) (each vertex's own fit)

``status`` is 0 fitted, 1 too few views, 2 failed (:data:`sellip.fit.records.STATUS_NAMES`). Vertices
that could not be fitted hold parameters interpolated from their fitted neighbours and
confidence 0 (docs/design.md §7): never NaN, never another vertex's stale values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr
from scipy.spatial import cKDTree

from sellip.jobs import atomic_directory
from sellip.model.pbrdf import PBRDFParams

PARAM_FIELDS = ("eta", "rho_d", "rho_s", "sigma_s", "rho_ss", "sigma_ss")
EXTRA_FIELDS = {"confidence": np.float32, "status": np.int8, "loss": np.float32, "views_used": np.int16,
                "iterations": np.int16, "model": np.uint8, "cluster": np.int32, "eta_source": np.uint8,
                "lobe_source": np.uint8, "selection_runner_up": np.int8, "cluster_alternative": np.int32}

MODEL_NAMES = {0: "diffuse", 1: "diffuse + specular", 2: "diffuse + specular + single scattering (sigma_ss fixed)",
               3: "diffuse + specular + single scattering"}
"""Per-vertex ``model`` codes (docs/design.md §4, §7): which lobes the vertex's material uses."""


class ParamsError(ValueError):
    """A parameter store that is missing, incomplete or inconsistent (the message names it)."""


def fill_from_neighbours(vertices: np.ndarray, values: np.ndarray, known: np.ndarray, k: int = 8) -> np.ndarray:
    """Replace the rows of ``values`` where ``known`` is False by the inverse-distance mean of the
    ``k`` nearest known vertices. vertices (N, 3), values (N, ...), known (N,) bool.

    Rows stay as they are when no vertex is known.
    """
    values = np.array(values, copy=True)
    unknown = np.flatnonzero(~known)
    if unknown.size == 0 or not known.any():
        return values
    source = np.flatnonzero(known)
    tree = cKDTree(vertices[source])
    distance, index = tree.query(vertices[unknown], k=min(k, source.size))
    distance = distance.reshape(unknown.size, -1)
    index = index.reshape(unknown.size, -1)
    weight = 1.0 / np.maximum(distance, 1e-9)
    weight /= weight.sum(1, keepdims=True)
    neighbours = values[source][index]  # (U, k, ...)
    values[unknown] = np.einsum("uk,uk...->u...", weight, neighbours)
    return values


def same_vertices(a: np.ndarray, b: np.ndarray, atol: float = 1e-6) -> bool:
    """Whether two vertex arrays (N, 3) are the same vertices in the same order (stores keep float32)."""
    return len(a) == len(b) and np.allclose(a, b, atol=atol)


def transfer_nearest(from_vertices: np.ndarray, to_vertices: np.ndarray) -> np.ndarray:
    """Index (M,) of the nearest ``from_vertices`` row for each of ``to_vertices`` (M, 3)."""
    return cKDTree(from_vertices).query(to_vertices, k=1)[1]


def write_params(path: str | Path, arrays: dict, chunk: int = 65536, attrs: dict | None = None) -> Path:
    """Write a parameter store atomically (temporary name, then rename). ``arrays``: name -> (N, ...)."""
    path = Path(path)
    missing = [n for n in ("vertices", "normals", *PARAM_FIELDS) if n not in arrays]
    if missing:
        raise ParamsError(f"{path}: cannot write a parameter store without {missing}")
    n = len(arrays["vertices"])
    for name, value in arrays.items():
        if len(value) != n:
            raise ParamsError(f"{path}: array {name!r} has {len(value)} rows, expected {n}")
    with atomic_directory(path) as tmp:
        group = zarr.open_group(str(tmp), mode="w")
        for name, value in arrays.items():
            dtype = EXTRA_FIELDS.get(name, np.float32)
            group.create_array(name, data=np.asarray(value).astype(dtype),
                               chunks=(min(chunk, max(n, 1)),) + np.shape(value)[1:])
        group.attrs.update({"num_vertices": n, **(attrs or {})})
    return path


def read_params(path: str | Path, start: int = 0, stop: int | None = None, fields=None) -> dict:
    """Rows [start, stop) of a parameter store as a dict of numpy arrays (plus ``attrs``); ``fields`` (names) reads
    only those arrays (every one by default)."""
    path = Path(path)
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as error:  # zarr raises several types for a missing or broken store
        raise ParamsError(f"{path}: not a parameter store ({error})") from error
    missing = [n for n in ("vertices", "normals", *PARAM_FIELDS) if n not in group]
    if missing:
        raise ParamsError(f"{path}: missing arrays {missing}")
    rows = slice(start, stop)
    names = list(group.array_keys()) if fields is None else list(fields)
    absent = [name for name in names if name not in group]
    if absent:
        raise ParamsError(f"{path}: missing arrays {absent}")
    out = {name: np.asarray(group[name][rows]) for name in names}
    out["attrs"] = dict(group.attrs)
    return out


def params_from(arrays: dict, dtype=np.float32) -> PBRDFParams:
    """The PBRDFParams held in a dict of arrays (e.g. from :func:`read_params`)."""
    return PBRDFParams(*[np.asarray(arrays[name], dtype) for name in PARAM_FIELDS])
