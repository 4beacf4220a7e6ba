"""Observe a mesh in every view (docs/design.md §2 observe; rule ``gather_observations``): pair the HDR views
with the cameras, check the scale, and write the observation store (:func:`observe_mesh`).
"""

from __future__ import annotations

import logging
import resource
import time
from pathlib import Path

import numpy as np

from sellip.capture.reader import read_capture
from sellip.fit.observe import (
    MISSING_POSES,
    ObservationWriter,
    ObserveError,
    Observer,
    ObserveSettings,
    Visibility,
    read_mesh,
)
from sellip.geometry.cameras import hdr_camera
from sellip.model.render import flash_light

log = logging.getLogger(__name__)





UNITS = {"diffuse, diffuse_pol, specular": "those of hdr.zarr (relative radiance)", "light_distance": "metres",
         "to_light, to_camera, camera_up, light_axis, vertices, normals": "world frame of cameras.csv (metres)"}



def pair_views(hdr_view_ids: list[str], camera_view_ids: list[str], hdr_path, cameras_path,
               missing_poses: str) -> list[tuple[int, int]]:
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



def _check_scale(mesh_vertices: np.ndarray, centers: np.ndarray, distance_m: float, mesh_path, cameras_path) -> None:
    """Warn when cameras and mesh are not at capture.yaml's typical distance (different units or frames)."""
    median = float(np.median(np.linalg.norm(centers - mesh_vertices.mean(axis=0), axis=-1)))
    if not distance_m / 3 <= median <= 3 * distance_m:
        log.warning("cameras of %s are %.3g m from the centre of %s, capture.yaml scene.distance_m is %.3g m: "
                    "are they in the same frame and units?", cameras_path, median, mesh_path, distance_m)



def observe_mesh(mesh_path: str | Path, cameras_path: str | Path, hdr_path: str | Path, capture_path: str | Path,
              output: str | Path, settings: ObserveSettings = ObserveSettings(),
              exclude_views: tuple[str, ...] = ()) -> dict:
    """Write the observation store ``output`` (see the module docstring); returns a summary.

    ``exclude_views``: views left out of the store (held out for evaluation, never used in the fit).
    ``settings.max_views``: keep only this many of the other views, spread evenly (:func:`spread_subset`); None: all.
    ``settings.missing_poses``: HDR views without a pose are left out ("skip") or an error ("error").
    Long: one job's steps in order (pair, check, cameras, observe, write), each a call.
    """
    from sellip.capture.hdr import read_hdr
    from sellip.geometry.cameras import read_cameras
    from sellip.jobs import atomic_directory, progress_logger
    from sellip.timing import mark

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
    pairs = pair_views(hdr.view_ids, camera_view_ids, hdr_path, cameras_path, settings.missing_poses)
    dropped = sorted(set(exclude_views) & set(hdr.attrs.get("dropped_views") or []))
    if dropped:  # ingest.bad_frames: skip dropped them; nothing left to hold out
        log.warning("held-out view(s) %s were dropped at ingest (no readable frame)", ", ".join(dropped))
    unknown = sorted(set(exclude_views) - set(hdr.view_ids) - set(dropped))
    if unknown:
        raise ObserveError(hdr_path, f"held-out view(s) {unknown[:10]} (config evaluate.held_out_views, "
                                     f"--exclude-views) are not views of this capture; expected some of "
                                     f"{hdr.view_ids[:20]}")
    pairs = [(index, row) for index, row in pairs if hdr.view_ids[index] not in set(exclude_views)]
    if not pairs:
        raise ObserveError(cameras_path, "every view is held out: nothing left to observe")
    if exclude_views:
        log.info("held out (never observed, never fitted): %s", ", ".join(sorted(exclude_views)))
    if settings.max_views is not None and settings.max_views < len(pairs):
        pairs = [pairs[k] for k in spread_subset(len(pairs), settings.max_views)]
        log.info("max_views %d: observing %s", settings.max_views,
                 ", ".join(hdr.view_ids[index] for index, _ in pairs))
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
