"""Argument groups that several stage adapters share (not a stage).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_image_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments shared by the stages that read hdr.zarr and cut silhouettes (sfm, init-mesh)."""
    parser.add_argument("--hdr", required=True, type=Path, help="hdr.zarr store (sellip merge-hdr)")
    add_silhouette_argument(parser)
    parser.add_argument("--threads", type=int, default=-1, help="threads (-1: all cores)")


def add_silhouette_argument(parser: argparse.ArgumentParser) -> None:
    """``--silhouette-settings``: :class:`sellip.geometry.silhouettes.SilhouetteOptions` as one JSON object (config
    ``silhouette``), for the stages that cut the photographs' silhouettes (sfm, init-mesh, observe, refine-geometry).
    ``args.silhouette_settings`` is the record."""
    from sellip.geometry.silhouettes import SilhouetteOptions
    from sellip.settings import add_renamed_argument, add_settings_argument

    add_settings_argument(parser, SilhouetteOptions, "--silhouette-settings", "silhouette")
    add_renamed_argument(parser, "--mask-threshold", "--silhouette-settings '{\"threshold\": ...}'")
