"""Exports of a final model that other tools open (issue #40): glTF 2.0 binary and per-map colour PLYs.

Public API::

    model_maps(vertex, store=None) -> {name: MapData}          # the per-vertex maps of a model (and which are missing)
    map_colors(map) -> (V, 3) uint8                              # the colours of one map (shared with the viewer)
    write_glb(path, vertex, faces, up=None) -> Path              # final/model.glb
    write_map_plys(folder, vertex, faces, maps) -> [Path]         # final/maps/map_<name>.ply

``vertex``: the vertex properties of a model PLY (:func:`sellip.io.read_ply`: name -> (V,) array; docs/design.md §4).

**glTF** (KhronosGroup/glTF ``specification/2.0``): one mesh, one primitive of triangles (``indices`` uint32),
``POSITION`` and ``NORMAL`` (float32 VEC3, the model's own world and metres), ``COLOR_0`` (float32 VEC3, linear:
ρ_d divided by the 99th percentile of its largest channel, clipped to [0, 1], so any viewer shows the albedo), and
the parameters as application-specific attributes, whose names start with an underscore as the specification requires
(:data:`GLTF_ATTRIBUTES`: ``_ETA``, ``_RHO_D`` VEC3, ``_RHO_S``, ``_SIGMA_S``, ``_RHO_SS`` VEC3, ``_SIGMA_SS``,
``_CONFIDENCE``, ``_MODEL``, ``_ETA_SOURCE``, ``_LOBE_SOURCE``, ``_CLUSTER``; each float32, present when the model
has the property), so the values are exact copies of model.ply's. The material is a plain dielectric
(metallic 0, roughness the median σ_s). glTF is y-up: the node's matrix rotates ``up`` (the capture cameras' mean up
axis, when given) onto +y and leaves the vertex data in the model's world.

**Map PLYs**: the model's mesh with per-vertex ``red green blue`` (uchar) of one map, as MeshLab shows them.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sellip.jobs import atomic_file

GLTF_ATTRIBUTES = (("_ETA", ("eta",)), ("_RHO_D", ("rho_d_r", "rho_d_g", "rho_d_b")), ("_RHO_S", ("rho_s",)),
                   ("_SIGMA_S", ("sigma_s",)), ("_RHO_SS", ("rho_ss_r", "rho_ss_g", "rho_ss_b")),
                   ("_SIGMA_SS", ("sigma_ss",)), ("_CONFIDENCE", ("confidence",)), ("_MODEL", ("model",)),
                   ("_ETA_SOURCE", ("eta_source",)), ("_LOBE_SOURCE", ("lobe_source",)), ("_CLUSTER", ("cluster",)))
"""glTF attribute name -> the model.ply properties it holds (VEC3 when three)."""

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_TYPES = {1: "SCALAR", 3: "VEC3"}

MAP_RANGE_PERCENTILES = (1.0, 99.0)
"""Scalar maps span these percentiles of their values (as the report's maps, docs/outputs.md)."""

CATEGORY_COLORS = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                            [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207]], np.uint8)
"""Colours of categorical maps (cluster, model): matplotlib's tab10, code modulo 10."""


@dataclass(frozen=True)
class MapData:
    """One per-vertex map: ``values`` (V,) or (V, 3); ``kind`` scalar | rgb | normal | category; ``low``/``high``
    the colour range (scalar: percentiles; rgb: 0 and the 99th percentile of the largest channel); ``std`` (V,)
    the fit's standard deviation where it has one; ``label`` for colour bars."""

    name: str
    kind: str
    values: np.ndarray
    low: float
    high: float
    label: str
    std: np.ndarray | None = None


MAP_LABELS = {"eta": "η (index of refraction)", "rho_d": "ρ_d (diffuse albedo, relative)",
              "rho_s": "ρ_s (specular albedo, relative)", "sigma_s": "σ_s (specular roughness)",
              "rho_ss": "ρ_ss (single-scattering albedo, relative)", "sigma_ss": "σ_ss (single-scattering roughness)",
              "normal": "normal (world, (n + 1) / 2)", "confidence": "confidence", "model": "model (lobes used)",
              "cluster": "material cluster"}
MAP_NAMES = tuple(MAP_LABELS)


def _robust_range(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    low, high = np.percentile(finite, MAP_RANGE_PERCENTILES)
    if high <= low:
        low, high = float(low) - 0.5 * max(abs(low), 1e-3), float(high) + 0.5 * max(abs(high), 1e-3)
    return float(low), float(high)


def model_maps(vertex: dict, store: dict | None = None) -> tuple[dict[str, MapData], dict[str, str]]:
    """The maps of a model: ({name: MapData} for every map of :data:`MAP_NAMES` the model has,
    {name: why it is missing} for the others). vertex: model.ply properties; store: final/params.zarr
    arrays (``cluster`` and the std arrays ``eta_std``, ``sigma_s_std``), optional."""
    store = store or {}
    maps, missing = {}, {}
    n = len(vertex["x"])

    def add(name, kind, values, std=None):
        values = np.asarray(values, np.float64)
        if kind == "rgb":
            low, high = 0.0, float(np.percentile(values.max(1), 99.0)) or 1.0
        elif kind == "normal":
            low, high = -1.0, 1.0
        elif kind == "category":
            low, high = 0.0, float(max(values.max(), 0))
        else:
            low, high = _robust_range(values)
        maps[name] = MapData(name, kind, values, low, high, MAP_LABELS[name],
                             None if std is None else np.asarray(std, np.float64))

    def have(*names):
        absent = [p for p in names if p not in vertex]
        return absent

    def std_of(name):
        value = store.get(f"{name}_std")
        return value if value is not None and len(value) == n else None

    for name, props, kind in (("eta", ("eta",), "scalar"), ("rho_d", ("rho_d_r", "rho_d_g", "rho_d_b"), "rgb"),
                              ("rho_s", ("rho_s",), "scalar"), ("sigma_s", ("sigma_s",), "scalar"),
                              ("rho_ss", ("rho_ss_r", "rho_ss_g", "rho_ss_b"), "rgb"),
                              ("sigma_ss", ("sigma_ss",), "scalar"), ("normal", ("nx", "ny", "nz"), "normal"),
                              ("confidence", ("confidence",), "scalar"), ("model", ("model",), "category")):
        absent = have(*props)
        if absent:
            missing[name] = f"model.ply has no {', '.join(absent)}"
            continue
        values = np.stack([vertex[p] for p in props], -1) if len(props) == 3 else vertex[props[0]]
        add(name, kind, values, std_of(name))
    if "confidence" in maps:  # a fraction: its whole range
        maps["confidence"] = MapData("confidence", "scalar", maps["confidence"].values, 0.0, 1.0,
                                     MAP_LABELS["confidence"])
    if "cluster" in vertex:
        add("cluster", "category", vertex["cluster"])
    elif "cluster" in store and len(store["cluster"]) == n:
        add("cluster", "category", store["cluster"])
    else:
        missing["cluster"] = "neither model.ply nor params.zarr has a cluster array"
    return maps, missing


def viridis(t: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 viridis colours of t in [0, 1] (matplotlib's table)."""
    from matplotlib import colormaps

    return (colormaps["viridis"](np.clip(t, 0, 1))[..., :3] * 255 + 0.5).astype(np.uint8)


def map_colors(data: MapData) -> np.ndarray:
    """(V, 3) uint8 colours of a map: viridis over [low, high] for scalars, the channels over ``high`` for RGB,
    (n + 1) / 2 for normals, :data:`CATEGORY_COLORS` for categories."""
    values = data.values
    if data.kind == "scalar":
        return viridis((values - data.low) / (data.high - data.low))
    if data.kind == "rgb":
        return (np.clip(values / data.high, 0, 1) * 255 + 0.5).astype(np.uint8)
    if data.kind == "normal":
        return (np.clip((values + 1) / 2, 0, 1) * 255 + 0.5).astype(np.uint8)
    return CATEGORY_COLORS[np.asarray(values, np.int64) % len(CATEGORY_COLORS)]


def write_map_plys(folder: str | Path, vertex: dict, faces: np.ndarray, maps: dict[str, MapData]) -> list[Path]:
    """``folder/map_<name>.ply`` per map: positions, normals, faces and uchar ``red green blue``; atomic per file."""
    from sellip.model.ply import write_ply

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, data in maps.items():
        colors = map_colors(data)
        table = {p: np.asarray(vertex[p], np.float32) for p in ("x", "y", "z", "nx", "ny", "nz") if p in vertex}
        table.update(red=colors[:, 0], green=colors[:, 1], blue=colors[:, 2])
        path = folder / f"map_{name}.ply"
        with atomic_file(path) as tmp:
            write_ply(tmp, table, np.asarray(faces))
        written.append(path)
    return written


def up_rotation(up) -> np.ndarray:
    """(3, 3) the smallest rotation taking the unit vector ``up`` onto +y (glTF's up)."""
    a = np.asarray(up, np.float64) / np.linalg.norm(up)
    b = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # opposite: half a turn about x
        return np.diag([1.0, -1.0, -1.0])
    skew = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + skew + skew @ skew / (1 + c)


def base_color(vertex: dict) -> np.ndarray:
    """(V, 3) float32 linear COLOR_0: ρ_d over the 99th percentile of its largest channel, in [0, 1]."""
    rho_d = np.stack([vertex[f"rho_d_{c}"] for c in "rgb"], -1).astype(np.float64)
    scale = float(np.percentile(rho_d.max(1), 99.0)) or 1.0
    return np.clip(rho_d / scale, 0, 1).astype(np.float32)


def write_glb(path: str | Path, vertex: dict, faces: np.ndarray, up=None, name: str = "sellip model") -> Path:
    """Write the model as glTF 2.0 binary (module docstring); atomic. Returns ``path``."""
    path = Path(path)
    blobs, views, accessors = [], [], []

    def add(array: np.ndarray, component: int, target: int, kind: str, minmax: bool = False) -> int:
        array = np.ascontiguousarray(array)
        offset = sum(len(b) for b in blobs)
        data = array.tobytes()
        blobs.append(data + b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data), "target": target})
        accessor = {"bufferView": len(views) - 1, "componentType": component, "count": int(array.shape[0]),
                    "type": kind}
        if minmax:
            accessor["min"] = [float(v) for v in np.atleast_1d(array.min(0))]
            accessor["max"] = [float(v) for v in np.atleast_1d(array.max(0))]
        accessors.append(accessor)
        return len(accessors) - 1

    def stack(props):
        return np.stack([np.asarray(vertex[p], np.float32) for p in props], -1) if len(props) == 3 else \
            np.asarray(vertex[props[0]], np.float32)

    attributes = {"POSITION": add(stack(("x", "y", "z")), _FLOAT, _ARRAY_BUFFER, "VEC3", minmax=True)}
    if all(p in vertex for p in ("nx", "ny", "nz")):
        normals = stack(("nx", "ny", "nz"))
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)  # glTF: unit normals
        attributes["NORMAL"] = add(normals, _FLOAT, _ARRAY_BUFFER, "VEC3")
    if all(f"rho_d_{c}" in vertex for c in "rgb"):
        attributes["COLOR_0"] = add(base_color(vertex), _FLOAT, _ARRAY_BUFFER, "VEC3")
    for attribute, props in GLTF_ATTRIBUTES:
        if all(p in vertex for p in props):
            attributes[attribute] = add(stack(props), _FLOAT, _ARRAY_BUFFER, _TYPES[len(props)])
    indices = add(np.asarray(faces, np.uint32).ravel(), _UINT, _ELEMENT_ARRAY_BUFFER, "SCALAR", minmax=True)
    roughness = float(np.median(vertex["sigma_s"])) if "sigma_s" in vertex else 0.5
    node = {"mesh": 0, "name": name}
    if up is not None:
        matrix = np.eye(4)
        matrix[:3, :3] = up_rotation(up)
        node["matrix"] = [float(v) for v in matrix.T.ravel()]  # column-major
    binary = b"".join(blobs)
    document = {
        "asset": {"version": "2.0", "generator": "sellip (issue #40 export)"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [node],
        "meshes": [{"name": name, "primitives": [{"attributes": attributes, "indices": indices, "mode": 4,
                                                  "material": 0}]}],
        "materials": [{"name": "pBRDF base colour (rho_d)", "doubleSided": False,
                       "pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0.0,
                                                "roughnessFactor": float(np.clip(roughness, 0, 1))}}],
        "buffers": [{"byteLength": len(binary)}], "bufferViews": views, "accessors": accessors,
        "extras": {"sellip": {"attributes": {a: list(p) for a, p in GLTF_ATTRIBUTES},
                              "note": "custom attributes hold model.ply's per-vertex values (float32)"}},
    }
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", 0x46546C67, 2, total))
        f.write(struct.pack("<II", len(text), 0x4E4F534A))
        f.write(text)
        f.write(struct.pack("<II", len(binary), 0x004E4942))
        f.write(binary)
    return path
