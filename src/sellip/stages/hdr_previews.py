"""``sellip hdr-previews``: PNG previews of every view of an hdr.zarr store (rule ``plot_hdr_previews``).

    sellip hdr-previews --hdr results/NAME/hdr.zarr --output results/NAME/previews

Writes ``<view>_<kind>.png`` for kind in :data:`sellip.report.previews.PREVIEW_KINDS`
(s0, dolp, aolp, diffuse, specular; see :mod:`sellip.report.previews`) into a folder
that appears only when complete.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from sellip.report.previews import preview_images
from sellip.stages.linearize import atomic_directory, progress_logger
from sellip.stages.merge_hdr import read_hdr

log = logging.getLogger(__name__)


def write_previews(hdr_path: str | Path, output: str | Path) -> Path:
    """Write the previews of every view of ``hdr_path`` into the folder ``output``."""
    import imageio.v3 as iio

    hdr = read_hdr(hdr_path)
    done = progress_logger(len(hdr.view_ids), "previewed views", log)
    with atomic_directory(output) as tmp:
        tmp.mkdir()
        for count, view_id in enumerate(hdr.view_ids, start=1):
            for kind, image in preview_images(*hdr.view(view_id)).items():
                iio.imwrite(tmp / f"{view_id}_{kind}.png", image)
            done(count)
    return Path(output)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr written by `sellip merge-hdr`")
    parser.add_argument("--output", required=True, type=Path, help="folder for the PNG previews")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    write_previews(args.hdr, args.output)
    return 0
