"""``sellip observe``: per-vertex, per-view observations of one iteration's mesh (rule ``gather_observations``).

    sellip observe --mesh results/NAME/mesh/init.ply --cameras results/NAME/cameras.csv
                   --hdr results/NAME/hdr.zarr --capture CAPTURE
                   --output results/NAME/iter/0/observations.zarr
                   [--vertex-chunk 4096] [--view-chunk 8] [--occlusion-tolerance 1e-3]
                   [--shadow-offset 0.5] [--min-cos 0] [--missing-poses skip|error] [--threads 2]
                   [--exclude-views v003 v017] [--max-views 12]

Views: those of hdr.zarr that have a pose in cameras.csv, in hdr.zarr's order. SfM leaves
unregistered views out of cameras.csv; ``--missing-poses skip`` (default) leaves them out here
too with a warning, ``error`` stops. A cameras.csv view that hdr.zarr lacks is always an error.
Held-out views (``--exclude-views``) are left out; then ``--max-views N`` keeps N of the remaining
views spread evenly over their order (:func:`spread_subset`; for an orbit, evenly around it), to
measure what fewer views cost (config ``observe.max_views``; the initial mesh still uses every view).
The flash position (``light.position_m``, camera coordinates) comes from capture.yaml.

Views are processed ``view_chunk`` at a time (:class:`sellip.fit.observe.Observer`), and each
group is written to the store (layout: :mod:`sellip.fit.observe`) before the next starts, so memory
holds one HDR view and N x view_chunk observations. The store is written under a temporary
name and renamed when complete.
"""

from __future__ import annotations

import argparse
import logging
import resource
import time
from pathlib import Path

import numpy as np

from sellip.capture.files import CaptureError
from sellip.capture.reader import read_capture
from sellip.fit.observe import ObservationWriter, ObserveError, Observer, ObserveSettings, Visibility, read_mesh
from sellip.model.render import Camera, flash_light

log = logging.getLogger(__name__)

MISSING_POSES = ("skip", "error")

UNITS = {"diffuse, diffuse_pol, specular": "those of hdr.zarr (relative radiance)", "light_distance": "metres",
         "to_light, to_camera, camera_up, light_axis, vertices, normals": "world frame of cameras.csv (metres)"}


def pair_views(hdr_view_ids: list[str], camera_view_ids: list[str], hdr_path, cameras_path,
               missing_poses: str = "skip") -> list[tuple[int, int]]:
    """(index in hdr.zarr, index in cameras.csv) of every view to observe, in hdr.zarr's order.

    Raises ObserveError naming cameras.csv for a view hdr.zarr lacks, for HDR views without a pose
    when ``missing_poses`` is "error", and when no view is left.
    """
    if missing_poses not in MISSING_POSES:
        raise ValueError(f"missing_poses must be one of {MISSING_POSES}, got {missing_poses!r}")
    in_hdr = set(hdr_view_ids)
    strangers = [v for v in camera_view_ids if v not in in_hdr]
    if strangers:
        raise ObserveError(cameras_path, f"view(s) {strangers[:10]} are not in {hdr_path} "
                                         f"(expected views of that store only)")
    row_of = {v: i for i, v in enumerate(camera_view_ids)}
    missing = [v for v in hdr_view_ids if v not in row_of]
    if missing and missing_poses == "error":
        raise ObserveError(cameras_path, f"no pose for {len(missing)} view(s) of {hdr_path}: {missing[:10]} "
                                         f"(missing_poses is 'error'; 'skip' leaves them out)")
    if missing:
        log.warning("%s has no pose for %d of %d views of %s (%s); they are left out", cameras_path, len(missing),
                    len(hdr_view_ids), hdr_path, missing[:10])
    pairs = [(i, row_of[v]) for i, v in enumerate(hdr_view_ids) if v in row_of]
    if not pairs:
        raise ObserveError(cameras_path, f"none of its views is in {hdr_path}")
    return pairs


def spread_subset(count: int, keep: int | None) -> np.ndarray:
    """Indices (min(keep, count),) of ``keep`` of ``count`` ordered items spread evenly over the order.

    Item floor(j count / keep) for j = 0..keep-1: always item 0, distinct, increasing. None (or
    keep >= count) keeps all. ValueError when keep < 1.
    """
    if keep is None or keep >= count:
        return np.arange(count)
    if keep < 1:
        raise ValueError(f"max_views must be at least 1, got {keep}")
    return (np.arange(keep) * count) // keep


def hdr_camera(intrinsics: dict, rotation: np.ndarray, translation: np.ndarray, hdr_path) -> Camera:
    """The camera of one view from ``intrinsics`` (fx, fy, cx, cy, width, height[, distortion]: hdr.zarr's attrs, or
    capture.yaml's ``camera`` at the sensor's size) and a cameras.csv pose; ``hdr_path`` names the source in errors."""
    from sellip.stages.sfm import intrinsics_matrix

    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in intrinsics]
    if missing:
        raise ObserveError(hdr_path, f"attrs 'intrinsics' lacks {missing}")
    distortion = np.asarray(intrinsics.get("distortion") or [0.0] * 5, np.float64)
    return Camera(intrinsics=intrinsics_matrix(intrinsics), rotation=rotation, translation=translation,
                  width=int(intrinsics["width"]), height=int(intrinsics["height"]),
                  distortion=distortion if np.any(distortion) else None)


def _check_scale(mesh_vertices: np.ndarray, centers: np.ndarray, distance_m: float, mesh_path, cameras_path) -> None:
    """Warn when cameras and mesh are not at capture.yaml's typical distance (different units or frames)."""
    median = float(np.median(np.linalg.norm(centers - mesh_vertices.mean(axis=0), axis=-1)))
    if not distance_m / 3 <= median <= 3 * distance_m:
        log.warning("cameras of %s are %.3g m from the centre of %s, capture.yaml scene.distance_m is %.3g m: "
                    "are they in the same frame and units?", cameras_path, median, mesh_path, distance_m)


def run_stage(mesh_path: str | Path, cameras_path: str | Path, hdr_path: str | Path, capture_path: str | Path,
              output: str | Path, settings: ObserveSettings = ObserveSettings(), missing_poses: str = "skip",
              exclude_views: tuple[str, ...] = (), max_views: int | None = None) -> dict:
    """Write the observation store ``output`` (see the module docstring); returns a summary.

    ``exclude_views``: views left out of the store (held out for evaluation, never used in the fit).
    ``max_views``: keep only this many of the other views, spread evenly (:func:`spread_subset`); None: all.
    """
    from sellip.report.timing import mark
    from sellip.stages.linearize import atomic_directory, progress_logger
    from sellip.stages.merge_hdr import read_hdr
    from sellip.stages.sfm import read_cameras

    mark("read")
    started = time.perf_counter()
    capture = read_capture(capture_path, check_files=False)  # raw frames are ingest's business
    light = capture.config["light"]
    mesh = read_mesh(mesh_path)
    if not Path(cameras_path).is_file():
        raise ObserveError(cameras_path, "cameras table does not exist")
    camera_view_ids, rotations, translations = read_cameras(cameras_path)
    if not (Path(hdr_path) / "zarr.json").is_file():
        raise ObserveError(hdr_path, "not an HDR store (no zarr.json); run `sellip merge-hdr` first")
    hdr = read_hdr(hdr_path)
    views, height, width = hdr.analyzers.shape[:3]
    if (int(hdr.intrinsics.get("width", -1)), int(hdr.intrinsics.get("height", -1))) != (width, height):
        raise ObserveError(hdr_path, f"attrs intrinsics size {hdr.intrinsics.get('width')}x"
                                     f"{hdr.intrinsics.get('height')} differs from the images, {width}x{height}")
    pairs = pair_views(hdr.view_ids, camera_view_ids, hdr_path, cameras_path, missing_poses)
    dropped = sorted(set(exclude_views) & set(hdr.attrs.get("dropped_views") or []))
    if dropped:  # ingest.bad_frames: skip dropped them; nothing left to hold out
        log.warning("held-out view(s) %s were dropped at ingest (no readable frame)", ", ".join(dropped))
    unknown = sorted(set(exclude_views) - set(hdr.view_ids) - set(dropped))
    if unknown:
        raise ObserveError(hdr_path, f"held-out view(s) {unknown[:10]} are not views of this store")
    pairs = [(index, row) for index, row in pairs if hdr.view_ids[index] not in set(exclude_views)]
    if not pairs:
        raise ObserveError(cameras_path, "every view is held out: nothing left to observe")
    if exclude_views:
        log.info("held out (never observed, never fitted): %s", ", ".join(sorted(exclude_views)))
    if max_views is not None and max_views < len(pairs):
        pairs = [pairs[k] for k in spread_subset(len(pairs), max_views)]
        log.info("max_views %d: observing %s", max_views, ", ".join(hdr.view_ids[index] for index, _ in pairs))
    cameras = [hdr_camera(hdr.intrinsics, rotations[row], translations[row], hdr_path) for _, row in pairs]
    flashes = [flash_light(c, light["position_m"], light["polarizer_deg"]) for c in cameras]
    _check_scale(mesh.vertices, np.stack([c.center for c in cameras]), float(capture.config["scene"]["distance_m"]),
                 mesh_path, cameras_path)
    view_ids = [hdr.view_ids[index] for index, _ in pairs]
    log.info("%s: %d vertices; %d of %d views of %s at %dx%d; groups of %d views", mesh_path, mesh.num_vertices,
             len(pairs), views, hdr_path, width, height, settings.view_chunk)

    observer = Observer(mesh, settings)
    usable_views = np.zeros(mesh.num_vertices, np.int32)
    passed = np.zeros(len(Visibility._fields), np.int64)  # vertex-views passing each test (cumulative)
    mark("observe")
    done = progress_logger(len(pairs), "observed views", log)
    with atomic_directory(output) as tmp:
        view_axes = {"camera_up": np.stack([c.up for c in cameras]), "light_axis": np.stack([f.axis for f in flashes])}
        writer = ObservationWriter(tmp, mesh, view_ids, view_axes, settings,
                                   attrs={"shadow_offset_m": observer.shadow_offset_m, "units": UNITS,
                                          "inputs": {"mesh": str(mesh_path), "cameras": str(cameras_path),
                                                     "hdr": str(hdr_path), "capture": str(capture_path)}})
        buffers = writer.buffers()
        for group_start in range(0, len(pairs), settings.view_chunk):
            group = range(group_start, min(group_start + settings.view_chunk, len(pairs)))
            for slot, k in enumerate(group):
                index = pairs[k][0]
                view = observer.observe(cameras[k], flashes[k].position, np.asarray(hdr.analyzers[index]),
                                        np.asarray(hdr.valid[index]))
                writer.fill(buffers, slot, view)
                usable_views += view.usable
                passed += [int(np.count_nonzero(test)) for test in view.visibility]
                done(k + 1)
            writer.write_views(group_start, buffers, len(group))
        total = mesh.num_vertices * len(pairs)
        summary = {
            "vertices": mesh.num_vertices, "views": len(pairs), "views_left_out": views - len(pairs),
            "passed_fraction": {name: float(n) / total for name, n in zip(Visibility._fields, passed)},
            "usable_views_per_vertex": {"min": int(usable_views.min()), "median": float(np.median(usable_views)),
                                        "max": int(usable_views.max())},
            "vertices_without_views": int(np.count_nonzero(usable_views == 0)),
            "total_s": time.perf_counter() - started,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        }
        writer.group.attrs["summary"] = summary
    log.info("wrote %s in %.1f s (peak RSS %.0f MB); vertex-views passing each test: %s; usable views per vertex: "
             "min %d, median %g, max %d; %d vertices seen by no view", output, summary["total_s"],
             summary["peak_rss_mb"], ", ".join(f"{k} {v:.3f}" for k, v in summary["passed_fraction"].items()),
             summary["usable_views_per_vertex"]["min"], summary["usable_views_per_vertex"]["median"],
             summary["usable_views_per_vertex"]["max"], summary["vertices_without_views"])
    return summary


def configure_parser(parser: argparse.ArgumentParser) -> None:
    defaults = ObserveSettings()
    parser.add_argument("--mesh", required=True, type=Path, help="mesh PLY with vertex normals (this iteration's)")
    parser.add_argument("--cameras", required=True, type=Path, help="cameras.csv (cam_from_world poses)")
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr store (sellip merge-hdr)")
    parser.add_argument("--capture", required=True, type=Path, help="capture folder (capture.yaml: flash position)")
    parser.add_argument("--output", required=True, type=Path, help="observations.zarr store to write")
    parser.add_argument("--vertex-chunk", type=int, default=defaults.vertex_chunk, help="vertices per chunk")
    parser.add_argument("--view-chunk", type=int, default=defaults.view_chunk,
                        help="views per chunk and per processing group (memory grows with vertices x this)")
    parser.add_argument("--occlusion-tolerance", type=float, default=defaults.occlusion_tolerance,
                        help="hidden when the mesh is hit before (1 - this) of the camera-vertex distance")
    parser.add_argument("--shadow-offset", type=float, default=defaults.shadow_offset,
                        help="shadow rays start this many median edge lengths above the vertex")
    parser.add_argument("--min-cos", type=float, default=defaults.min_cos,
                        help="front-facing / lit when the cosine to the camera / flash exceeds this")
    parser.add_argument("--edge-margin", type=float, default=defaults.edge_margin,
                        help="a sample must lie this many HDR pixels inside the object's silhouette (0: off)")
    parser.add_argument("--mask-threshold", type=float, default=defaults.mask_threshold,
                        help="silhouette threshold for --edge-margin (fraction of the view's robust maximum)")
    parser.add_argument("--max-slope", type=float, default=defaults.max_slope,
                        help="leave out samples whose footprint has an intensity slope above this "
                             "(|grad S0| / S0 per HDR pixel; 0: off)")
    parser.add_argument("--missing-poses", choices=MISSING_POSES, default="skip",
                        help="HDR views without a pose in cameras.csv: leave them out, or stop")
    parser.add_argument("--threads", type=int, default=0, help="ray-casting threads (0: all cores)")
    parser.add_argument("--exclude-views", nargs="*", default=[], metavar="VIEW",
                        help="views held out for evaluation: left out of the store")
    parser.add_argument("--max-views", type=int, default=None, metavar="N",
                        help="observe only N of the remaining views, spread evenly over their order (default: all)")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    try:
        settings = ObserveSettings(vertex_chunk=args.vertex_chunk, view_chunk=args.view_chunk,
                                   occlusion_tolerance=args.occlusion_tolerance, shadow_offset=args.shadow_offset,
                                   min_cos=args.min_cos, edge_margin=args.edge_margin,
                                   mask_threshold=args.mask_threshold, max_slope=args.max_slope,
                                   threads=args.threads)
    except ValueError as exc:
        log.error("bad settings: %s", exc)
        return 1
    if args.max_views is not None and args.max_views < 1:
        log.error("bad settings: --max-views must be at least 1, got %d", args.max_views)
        return 1
    try:
        run_stage(args.mesh, args.cameras, args.hdr, args.capture, args.output, settings,
                  missing_poses=args.missing_poses, exclude_views=tuple(args.exclude_views),
                  max_views=args.max_views)
    except (ObserveError, CaptureError) as exc:
        log.error("%s", exc)
        return 1
    return 0
