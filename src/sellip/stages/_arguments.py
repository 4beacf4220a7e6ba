"""Argument groups that several stage adapters share (not a stage).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_image_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments shared by the stages that read hdr.zarr and cut silhouettes (sfm, init-mesh)."""
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr store (sellip merge-hdr)")
    parser.add_argument("--mask-threshold", type=float, default=0.03,
                        help="silhouette: fraction of the view's robust maximum")
    parser.add_argument("--threads", type=int, default=-1, help="threads (-1: all cores)")
