"""The HDR store ``hdr.zarr`` (docs/design.md §2 hdr_merge): one HDR image per view and analyzer (I0, I45, I90,
I135, RGB, float32, relative radiance) and its valid mask, merged from a view's flash levels
(:func:`merge_capture`), and its reader (:func:`read_hdr` -> :class:`HDRImages`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from zarr.codecs import BloscCodec

from sellip.capture import ingest
from sellip.jobs import atomic_directory, map_in_threads, progress_logger

log = logging.getLogger(__name__)


UNITS = "relative radiance: (raw - black) / (white - black) / (flash_level * exposure_s)"



HDR_CODEC = BloscCodec(cname="lz4", clevel=5, shuffle="bitshuffle")
"""Compression of the HDR images: ~0.77 of the raw size, read as fast as uncompressed (zstd: 0.87, 3x slower)."""



@dataclass(frozen=True)
class HDRImages:
    """An opened hdr.zarr store; arrays are zarr arrays read on indexing (one view per chunk).

    analyzers: (V, H, W, 4, C); valid: (V, H, W); view_ids: V names; intrinsics: output-grid camera.
    """

    analyzers: object
    valid: object
    view_ids: list[str]
    intrinsics: dict
    attrs: dict

    def view(self, view_id: str) -> tuple[np.ndarray, np.ndarray]:
        """(analyzers (H, W, 4, C) float32, valid (H, W) bool) of one view."""
        index = self.view_ids.index(view_id)
        return np.asarray(self.analyzers[index]), np.asarray(self.valid[index])



def read_hdr(path: str | Path) -> HDRImages:
    """Open an hdr.zarr store written by :func:`merge_capture` (nothing is read until indexed)."""
    import zarr

    group = zarr.open_group(str(path), mode="r")
    attrs = dict(group.attrs)
    return HDRImages(analyzers=group["analyzers"], valid=group["valid"], view_ids=list(attrs["view_id"]),
                     intrinsics=dict(attrs["intrinsics"]), attrs=attrs)



class FlashLabelError(ingest.IngestError):
    """The frames of a view are not as bright relative to each other as their flash_level * exposure_s say."""


def check_flash_labels(view_id: str, frames: list, indices: list[int], attrs: dict,
                       tolerance: float = ingest.FLASH_RATIO_TOLERANCE) -> None:
    """Raise :class:`FlashLabelError` naming the view, each mislabelled frame (frame_id, frames.csv row) and its
    measured against its labelled brightness ratio (:func:`sellip.capture.ingest.mislabelled_frames`). frames: the
    view's linear frames, indices their rows in the store (= frames.csv rows), attrs the linearize store's."""
    if len(frames) < 2:
        return
    gains = [attrs["flash_level"][i] * attrs["exposure_s"][i] for i in indices]
    _, measured, labelled = ingest.brightness_ratios(frames, gains)
    bad = np.flatnonzero(ingest.mislabelled_frames(measured, labelled, tolerance))
    if not bad.size:
        return
    ids, levels, exposures = attrs["frame_id"], attrs["flash_level"], attrs["exposure_s"]
    deviation = np.abs(np.log(measured / labelled) - np.median(np.log(measured / labelled)[np.isfinite(measured)]))
    deviation[bad] = np.inf
    anchor = int(np.nanargmin(deviation))  # the frame that agrees best with the view's consensus
    measured, labelled = measured / measured[anchor], labelled / labelled[anchor]
    r = indices[anchor]
    bad = bad[bad != anchor]  # two frames that disagree: the second is named against the first

    def label(i: int) -> str:
        return f"flash_level {levels[i]:g} x exposure_s {exposures[i]:g}"

    said = "; ".join(f"frame {ids[indices[f]]!r} (frames.csv row {indices[f]}, line {indices[f] + 2}) is "
                     f"{measured[f]:.3g}x as bright as frame {ids[r]!r} but labelled {labelled[f]:.3g}x "
                     f"({label(indices[f])} against {label(r)})" for f in bad)
    raise FlashLabelError(
        f"{attrs['capture']}/frames.csv: view {view_id!r}: the brightness of its frames contradicts their labels: "
        f"{said}. Expected measured and labelled ratios within a factor {tolerance:g} (ingest.flash_ratio_tolerance):"
        f" correct flash_level / exposure_s of these rows (or the files, if the photographs are swapped)")


def merge_capture(linear_path: str | Path, output: str | Path, threads: int = 1,
                  settings: ingest.IngestSettings = ingest.IngestSettings()) -> Path:
    """Merge the frames of every view of a ``sellip linearize`` store into ``output`` (layout above).

    Before merging a view, its frames' brightness ratios are checked against their labels (flash_level *
    exposure_s; :func:`check_flash_labels`, ``settings.flash_ratio_tolerance`` a factor > 1): a mislabelled frame stops
    the stage (FlashLabelError) and nothing is written."""
    import zarr

    started = time.perf_counter()
    source = zarr.open_group(str(linear_path), mode="r")
    attrs = dict(source.attrs)
    linear = source["linear"]
    view_of_frame = list(attrs["view_id"])
    gains = np.asarray(attrs["flash_level"], np.float64) * np.asarray(attrs["exposure_s"], np.float64)
    skipped = list(attrs.get("skipped") or [None] * len(view_of_frame))
    all_views = list(dict.fromkeys(view_of_frame))
    frames_of = {view: [i for i, v in enumerate(view_of_frame) if v == view and skipped[i] is None]
                 for view in all_views}
    view_ids = [v for v in all_views if frames_of[v]]
    dropped = [v for v in all_views if not frames_of[v]]
    if dropped:
        log.warning("dropping %d view(s) whose every frame was left out by linearize: %s", len(dropped),
                    ", ".join(dropped[:30]))
    if not view_ids:
        raise ingest.IngestError(f"{linear_path}: no view has a frame left to merge")
    _, height, width, n_analyzers, channels = linear.shape
    log.info("%s: %d frames -> %d views of %dx%d", linear_path, linear.shape[0], len(view_ids), width, height)

    with atomic_directory(output) as tmp:
        group = zarr.open_group(str(tmp), mode="w")
        analyzers = group.create_array("analyzers", shape=(len(view_ids), height, width, n_analyzers, channels),
                                       chunks=(1, height, width, n_analyzers, channels), dtype="float32",
                                       fill_value=0.0, compressors=HDR_CODEC)
        valid = group.create_array("valid", shape=(len(view_ids), height, width), chunks=(1, height, width),
                                   dtype="bool", fill_value=False)

        def run(v: int) -> float:
            indices = frames_of[view_ids[v]]
            frames = [np.asarray(linear[i]) for i in indices]
            check_flash_labels(view_ids[v], frames, indices, attrs, settings.flash_ratio_tolerance)
            merged, ok = ingest.merge_hdr(frames, gains[indices])
            analyzers[v] = merged
            valid[v] = ok
            return float(ok.mean())

        fractions = map_in_threads(run, len(view_ids), threads, progress_logger(len(view_ids), "merged views", log))
        group.attrs.update({
            "view_id": view_ids,
            "frames_per_view": [len(frames_of[v]) for v in view_ids],
            "intrinsics": attrs["intrinsics"],
            "analyzer_angles_deg": attrs["analyzer_angles_deg"],
            "channels": attrs["channels"],
            "units": UNITS,
            "capture": attrs["capture"],
            "dropped_views": dropped,
        })
    log.info("wrote %s in %.1f s; valid pixels per view: min %.3f, median %.3f", output,
             time.perf_counter() - started, min(fractions), float(np.median(fractions)))
    return Path(output)
