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

from sellip.report.previews import write_previews

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr written by `sellip merge-hdr`")
    parser.add_argument("--output", required=True, type=Path, help="folder for the PNG previews")


def main(args: argparse.Namespace) -> int:
    logging.getLogger("jax._src.xla_bridge").setLevel(logging.WARNING)  # "no TPU" notices
    write_previews(args.hdr, args.output)
    return 0
