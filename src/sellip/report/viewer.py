"""The interactive viewer of a final model: ``results/NAME/viewer/``, a static page that works offline (issue #40).

Public API::

    ViewerInputs                                          # what the page shows (model arrays, cameras, light, table)
    load_inputs(results, capture=None) -> ViewerInputs    # from results/NAME (clear errors naming what is missing)
    payload(inputs) -> (meta dict, binary bytes)          # the model as float32/uint32 arrays and their description
    write_viewer(folder, inputs) -> Path                  # index.html, viewer.js, shaders.js, model.js (atomic)
    serve(folder, port=8000)                              # http://localhost:PORT/ (blocks)

The page is plain WebGL2 (no library, no build step, nothing from a network): ``index.html`` and ``viewer.js``
are copied from :mod:`sellip.report` 's ``viewer_assets``; ``shaders.js`` holds their GLSL (``pbrdf.glsl`` is the
model of :mod:`sellip.pbrdf`, ``#include`` resolved here); ``model.js`` holds the metadata as JSON and the arrays as
base64 of little-endian binary. Everything is loaded with ``<script>`` tags, so the page also works opened
from disk (``file://`` forbids fetching local files).

Files read from ``results/NAME`` (only the first is required): ``final/model.ply`` (docs/design.md §4; any map whose
property is missing is disabled, with the reason on the page), ``final/params.zarr`` (``cluster``, the fit's
``eta_std``/``sigma_s_std``), ``cameras.csv`` (frusta, "snap to view"), ``hdr.zarr`` attrs ``intrinsics``
(the virtual camera; else a 640x512 view with the capture's or a 25 mm lens), ``final/materials.csv``; the
flash (``light.position_m``, ``light.polarizer_deg``) comes from the capture's ``capture.yaml``.
"""

from __future__ import annotations

import base64
import json
import logging
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from sellip.jobs import atomic_directory
from sellip.report.export import MAP_LABELS, MapData, model_maps

log = logging.getLogger(__name__)

ASSETS = ("index.html", "viewer.js")
SHADERS = {"mesh_vert": "mesh.vert", "mesh_frag": "mesh.frag", "line_vert": "line.vert", "line_frag": "line.frag",
           "shadow_vert": "shadow.vert", "shadow_frag": "shadow.frag"}
DEFAULT_FLASH = {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0.0}
DARK_LEVEL = 0.01
"""AoLP, DoP and the Mueller ratios are blank where the exposure-scaled s0 is below this (docs/outputs.md: 1 %)."""
DEFAULT_SIZE = (640, 512)


class ViewerError(ValueError):
    """A results folder the viewer cannot show (the message names what is missing)."""


@dataclass
class ViewerInputs:
    """Everything the page shows. vertex: model.ply properties (V,) each; faces (F, 3); store: params.zarr arrays
    (may be empty); cameras: [(view_id, R (3, 3), t (3,))]; intrinsics: fx, fy, cx, cy, width, height; light:
    position_m (camera coordinates), polarizer_deg; materials: a materials table or None."""

    name: str
    vertex: dict
    faces: np.ndarray
    store: dict = field(default_factory=dict)
    cameras: list = field(default_factory=list)
    intrinsics: dict | None = None
    light: dict = field(default_factory=lambda: dict(DEFAULT_FLASH))
    materials: object = None
    notes: list = field(default_factory=list)


def read_light(capture: str | Path) -> dict:
    """The flash of a capture (capture.yaml ``light``): position_m (3,) camera coordinates, polarizer_deg."""
    from sellip.capture.reader import read_capture

    light = read_capture(capture, check_files=False).config["light"]
    return {"position_m": [float(v) for v in light["position_m"]], "polarizer_deg": float(light["polarizer_deg"])}


def read_pose_table(path: str | Path) -> list:
    """[(view_id, R (3, 3), t (3,))] of a cameras.csv (poses.csv columns, checked with its pandera schema)."""
    import pandas as pd

    from sellip.capture.files import POSE_COLUMNS
    from sellip.capture.tables import validate_poses
    from sellip.model.conventions import quaternion_to_rotation

    table = validate_poses(pd.read_csv(path, dtype={"view_id": str}, keep_default_na=False), str(path))
    rotations = quaternion_to_rotation(table[list(POSE_COLUMNS[1:5])].to_numpy(np.float64))
    translations = table[list(POSE_COLUMNS[5:])].to_numpy(np.float64)
    return [(str(v), rotations[i], translations[i]) for i, v in enumerate(table["view_id"])]


def load_inputs(results: str | Path, capture: str | Path | None = None) -> ViewerInputs:
    """The viewer's inputs from a results folder (module docstring). ViewerError when there is no finished model."""
    from sellip.model.params import ParamsError, read_params
    from sellip.model.ply import read_ply

    results = Path(results)
    model = results / "final" / "model.ply"
    if not results.is_dir():
        raise ViewerError(f"{results}: no such results folder")
    if not model.is_file():
        raise ViewerError(f"{model}: missing: the run has no finished model (run the workflow to its final stage, "
                          f"rule finalize_model)")
    vertex, faces = read_ply(model)
    absent = [p for p in ("x", "y", "z") if p not in vertex]
    if absent or faces is None or len(faces) == 0:
        raise ViewerError(f"{model}: expected vertex positions x y z and triangles, got properties {list(vertex)} "
                          f"and {0 if faces is None else len(faces)} faces")
    inputs = ViewerInputs(name=results.name, vertex=vertex, faces=faces)
    params = results / "final" / "params.zarr"
    if params.is_dir():
        try:
            store = read_params(params)
            if len(store["vertices"]) == len(vertex["x"]):
                inputs.store = store
            else:
                inputs.notes.append(f"{params} has {len(store['vertices'])} vertices, model.ply {len(vertex['x'])}: "
                                    f"not used")
        except ParamsError as error:
            inputs.notes.append(f"{error}: not used")
    cameras = results / "cameras.csv"
    if cameras.is_file():
        inputs.cameras = read_pose_table(cameras)
    else:
        inputs.notes.append(f"{cameras} missing: no captured views to snap to")
    hdr = results / "hdr.zarr"
    if (hdr / "zarr.json").is_file():
        import zarr

        intrinsics = dict(zarr.open_group(str(hdr), mode="r").attrs.get("intrinsics") or {})
        if all(k in intrinsics for k in ("fx", "fy", "cx", "cy", "width", "height")):
            inputs.intrinsics = {k: float(intrinsics[k]) for k in ("fx", "fy", "cx", "cy", "width", "height")}
    if capture is not None and (Path(capture) / "capture.yaml").is_file():
        inputs.light = read_light(capture)
    else:
        # A WARNING (in the summary of a run, on the console of `sellip view`): the page relights with a flash
        # that is not the capture's, and nothing else on it says so.
        where = (f"the capture {str(capture)!r} has no capture.yaml (moved or deleted?)" if capture is not None else
                 f"no capture folder is known ({results / 'metrics.json'} names none that exists)")
        log.warning("%s: the viewer's flash is a DEFAULT, not the capture's: at %s m in camera coordinates, polarizer "
                    "0 deg. Give the capture's folder: sellip view %s --capture PATH", where,
                    DEFAULT_FLASH["position_m"], results)
        inputs.notes.append(f"{where}: the flash is a default, at {DEFAULT_FLASH['position_m']} m in camera "
                            "coordinates, polarizer 0 deg")
    table = results / "final" / "materials.csv"
    if table.is_file():
        from sellip.report.materials import MaterialsError, read_materials

        try:
            inputs.materials = read_materials(table)
        except MaterialsError as error:  # an older table (without the interval's columns): `sellip view` rewrites it
            inputs.notes.append(f"{error}: not used (`sellip view` writes it again)")
    return inputs


def _intrinsics(inputs: ViewerInputs) -> dict:
    """The virtual camera's intrinsics: hdr.zarr's, else the rig's 25 mm lens at DEFAULT_SIZE (noted)."""
    if inputs.intrinsics:
        return dict(inputs.intrinsics)
    from sellip.capture.scenes import device_intrinsics

    width, height = DEFAULT_SIZE
    k = device_intrinsics(width, height)
    inputs.notes.append("no hdr.zarr intrinsics: the virtual camera is the rig's 25 mm lens at 640x512")
    return {"fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
            "width": float(width), "height": float(height)}


def default_exposure(vertex: dict, distance: float) -> float:
    """An exposure that puts a bright diffuse vertex facing the flash at 80 % of white: 0.8 / (p99 of mean rho_d
    / d^2), d the typical camera distance (the unit flash of sellip.render gives S = cos_i / d^2)."""
    rho = np.mean([vertex[f"rho_d_{c}"] for c in "rgb" if f"rho_d_{c}" in vertex] or [np.ones(1)], axis=0)
    level = float(np.percentile(rho, 99)) / distance**2
    return 0.8 / level if level > 0 else 1.0


def payload(inputs: ViewerInputs) -> tuple[dict, bytes]:
    """(meta, binary): the arrays the page uploads (float32 except ``indices`` uint32; byte offsets 4-aligned) and
    their description, the maps (colour ranges, what is missing and why), cameras, light and materials."""
    vertex, store = inputs.vertex, inputs.store
    positions = np.stack([vertex[p] for p in ("x", "y", "z")], -1).astype(np.float64)
    centre = 0.5 * (positions.min(0) + positions.max(0))
    radius = float(np.linalg.norm(positions - centre, axis=1).max()) or 1.0
    if inputs.cameras:
        centres = np.array([-r.T @ t for _, r, t in inputs.cameras])
        distance = float(np.median(np.linalg.norm(centres - centre, axis=1)))
        up = np.mean([-r[1] for _, r, _ in inputs.cameras], axis=0)
        up = up / (np.linalg.norm(up) or 1.0)
    else:
        distance, up = 20.0 * radius, np.array([0.0, 0.0, 1.0])
    maps, missing = model_maps(vertex, store)
    sources = {"position": ("x", "y", "z"), "normal": ("nx", "ny", "nz"), "eta": ("eta",),
               "rho_d": ("rho_d_r", "rho_d_g", "rho_d_b"), "rho_s": ("rho_s",), "sigma_s": ("sigma_s",),
               "rho_ss": ("rho_ss_r", "rho_ss_g", "rho_ss_b"), "sigma_ss": ("sigma_ss",),
               "confidence": ("confidence",), "model": ("model",), "eta_source": ("eta_source",)}
    columns = {}
    for name, props in sources.items():
        if all(p in vertex for p in props):
            columns[name] = np.stack([vertex[p] for p in props], -1) if len(props) == 3 else vertex[props[0]]
    if "cluster" in maps:
        columns["cluster"] = maps["cluster"].values
    if "eta_vertex" in store:  # each vertex's own eta (the model's may be its material's)
        columns["eta_vertex"] = store["eta_vertex"]
    for name in ("eta_std", "sigma_s_std"):
        if name in store:
            columns[name] = np.where(np.isfinite(store[name]), store[name], np.nan)
    if "normal" not in columns:  # a model without normals: area-weighted face normals, so the page still shades
        from sellip.geometry.meshes import vertex_normals

        columns["normal"] = vertex_normals(positions, np.asarray(inputs.faces), area_weighted=True)
        inputs.notes.append("model.ply has no normals: shaded with the mesh's own")
    blobs, arrays, offset = [], {}, 0
    for name, values in columns.items():
        data = np.ascontiguousarray(values, "<f4").tobytes()
        arrays[name] = {"offset": offset, "length": len(data) // 4, "dtype": "float32"}
        blobs.append(data)
        offset += len(data)
    data = np.ascontiguousarray(inputs.faces, "<u4").tobytes()
    arrays["indices"] = {"offset": offset, "length": len(data) // 4, "dtype": "uint32"}
    blobs.append(data)
    from sellip.model.params import MODEL_NAMES

    meta = {
        "name": inputs.name, "vertices": len(positions), "faces": len(inputs.faces), "arrays": arrays,
        "maps": {name: {"kind": m.kind, "low": m.low, "high": m.high, "label": m.label} for name, m in maps.items()},
        "missing": missing, "map_names": dict(MAP_LABELS),
        "model_names": {str(k): v for k, v in MODEL_NAMES.items()},
        "cameras": [{"id": v, "R": [float(x) for x in r.ravel()], "t": [float(x) for x in t]}
                    for v, r, t in inputs.cameras],
        "intrinsics": _intrinsics(inputs), "light": inputs.light,
        "center": [float(x) for x in centre], "radius": radius, "distance": distance, "up": [float(x) for x in up],
        "exposure": default_exposure(vertex, distance), "dark_level": DARK_LEVEL, "notes": inputs.notes,
        "materials": None if inputs.materials is None else {
            "columns": list(inputs.materials.columns),
            "rows": json.loads(inputs.materials.to_json(orient="values", double_precision=6))},
    }
    return meta, b"".join(blobs)


def _asset(name: str) -> str:
    return resources.files("sellip.report").joinpath("viewer_assets").joinpath(name).read_text(encoding="utf-8")


def shader_sources() -> dict[str, str]:
    """{mesh_vert, mesh_frag, line_vert, line_frag}: the GLSL with ``#include "FILE"`` lines replaced by FILE."""
    def resolve(text: str) -> str:
        return re.sub(r'^#include "([\w.]+)"\s*$', lambda m: _asset(m.group(1)), text, flags=re.MULTILINE)

    return {key: resolve(_asset(name)) for key, name in SHADERS.items()}


def write_viewer(folder: str | Path, inputs: ViewerInputs) -> Path:
    """Write the page into ``folder`` (built under a temporary name, then renamed). Returns the index.html path."""
    folder = Path(folder)
    meta, binary = payload(inputs)
    with atomic_directory(folder) as tmp:
        tmp.mkdir()
        for name in ASSETS:
            (tmp / name).write_text(_asset(name), encoding="utf-8")
        (tmp / "shaders.js").write_text("window.SELLIP_SHADERS = " + json.dumps(shader_sources()) + ";\n",
                                        encoding="utf-8")
        with open(tmp / "model.js", "w", encoding="ascii") as f:
            f.write("window.SELLIP_MODEL = {meta: " + json.dumps(meta, allow_nan=False) + ', data: "')
            f.write(base64.b64encode(binary).decode("ascii"))
            f.write('"};\n')
    return folder / "index.html"


def serve(folder: str | Path, port: int = 8000, host: str = "127.0.0.1") -> None:
    """Serve ``folder`` on http://HOST:PORT/ until interrupted (localhost only by default)."""
    import functools
    import http.server

    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    with http.server.ThreadingHTTPServer((host, port), handler) as server:
        print(f"sellip viewer: http://{host}:{port}/index.html (Ctrl-C stops)", flush=True)
        server.serve_forever()


def maps_of(inputs: ViewerInputs) -> dict[str, MapData]:
    """The maps of the inputs (as the page draws them; also the map PLYs)."""
    return model_maps(inputs.vertex, inputs.store)[0]


def find_capture(results: Path) -> Path | None:
    """The capture folder recorded in ``results/metrics.json`` (None when there is none), also when it no longer
    exists (the capture moved): :func:`load_inputs` then names it in its warning."""
    metrics = results / "metrics.json"
    if metrics.is_file():
        capture = json.loads(metrics.read_text()).get("capture")
        if capture:
            return Path(capture)
    return None



def ground_truth_for(results: Path, capture: Path | None):
    """The capture's ground-truth ParamMesh when its world is the model's (known or verified poses), else None."""
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.model.ply import read_param_mesh

    if capture is None or not (capture / GROUND_TRUTH_MESH).is_file():
        return None
    report = results / "sfm" / "report.json"
    if report.is_file() and json.loads(report.read_text()).get("mode") == "sfm":
        log.info("poses from SfM: the materials table has no ground-truth columns (the worlds differ by a Sim(3))")
        return None
    return read_param_mesh(capture / GROUND_TRUTH_MESH)



def export_results(results: Path, capture: Path | None = None) -> dict:
    """Write materials.csv, model.glb, the map PLYs and the viewer of ``results``; returns what was written."""
    from sellip.report.export import write_glb, write_map_plys
    from sellip.report.materials import material_table, write_materials
    from sellip.report.viewer import load_inputs, maps_of, write_viewer

    results = Path(results)
    capture = Path(capture) if capture is not None else find_capture(results)
    inputs = load_inputs(results, capture)  # ViewerError when there is no finished model
    final = results / "final"
    written = {}
    if inputs.store:
        table = material_table(inputs.store, inputs.faces, ground_truth_for(results, capture))
        written["materials"] = write_materials(final / "materials.csv", table)
        inputs.materials = table
        log.info("materials:\n%s", table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    else:
        log.warning("%s: no params.zarr: no materials table", final)
    vertex = dict(inputs.vertex)
    if "cluster" not in vertex and "cluster" in inputs.store:
        vertex["cluster"] = inputs.store["cluster"]
    up = None
    if inputs.cameras:
        import numpy as np

        up = np.mean([-r[1] for _, r, _ in inputs.cameras], axis=0)
    written["glb"] = write_glb(final / "model.glb", vertex, inputs.faces, up=up, name=results.name)
    maps = maps_of(inputs)
    with atomic_directory(final / "maps") as tmp:
        write_map_plys(tmp, vertex, inputs.faces, maps)
    written["maps"] = final / "maps"
    written["viewer"] = write_viewer(results / "viewer", inputs)
    for note in inputs.notes:
        log.info("viewer: %s", note)
    log.info("wrote %s", ", ".join(str(p) for p in written.values()))
    print(f"sellip viewer: open {written['viewer'].resolve()} (or: sellip view {results} --serve)", flush=True)
    return written
