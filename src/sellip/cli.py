"""The ``sellip`` command line: one sub-command per stage, each a thin wrapper over ``sellip.stages``.

Every stage module ``sellip.stages.<name>`` exposes ``configure_parser(parser)`` (adds its
arguments) and ``main(args) -> int``. Modules are imported only when their command runs,
so ``sellip --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from sellip import timing, workflow_support

# command name -> (module under sellip.stages, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("synth", "generate a synthetic capture"),
    "synth-calibration": ("synth_calibration",
                          "generate synthetic calibration frames (board, spheres, chart) with truth"),
    "calibrate": ("calibrate",
                  "describe a device: intrinsics, flash position, polarization check, colour -> device.yaml"),
    "capture": ("capture_new", "capture new: capture.yaml and frames.csv for a folder of raw frames and a device.yaml"),
    "linearize": ("linearize", "raw frames -> linear, demosaiced, undistorted analyzer images"),
    "merge-hdr": ("merge_hdr", "merge the flash levels of each view into HDR analyzer images"),
    "hdr-previews": ("hdr_previews", "PNG previews (s0, DoLP, AoLP, diffuse, specular) of the HDR images"),
    "observe": ("observe", "per-vertex, per-view observations (visibility, HDR samples, geometry) of a mesh"),
    "sfm": ("sfm", "camera poses: known poses.csv, SfM (pycolmap), or SfM verified against poses.csv"),
    "init-mesh": ("init_mesh", "initial mesh from silhouettes and SfM points (screened Poisson), or a scan checked "
                              "against the silhouettes"),
    "fit": ("fit", "per-vertex pBRDF and normal fit of one vertex shard"),
    "gather-fit": ("gather_fit", "assemble the fit shards of an iteration into params.zarr"),
    "cluster-lobes": ("cluster_lobes", "material clusters and per-cluster specular lobes (augmentation)"),
    "refine-geometry": ("refine_geometry", "the mesh moved to agree with the fitted normals (normal integration)"),
    "refine-poses": ("refine_poses", "every view's pose aligned to an iteration's model (pose refinement)"),
    "pass-through": ("pass_through", "a loop job that passes its inputs through once the loop has converged, else "
                                     "runs its command"),
    "finalize": ("finalize", "the final model: model.ply and params.zarr"),
    "render-outputs": ("render_outputs", "renders, Mueller images, AoLP/DoP and parameter maps of a model"),
    "evaluate": ("evaluate", "figures of merit against the ground truth (metrics.json)"),
    "view": ("view", "materials table, glTF and map-PLY exports, and the offline browser viewer of a final model"),
    "bench-sweep": ("bench_sweep", "speed-accuracy sweep of the whole workflow: chart, CSV and tables"),
    "bench-stability": ("bench_stability", "the stability suite: failure-mode cases run end to end, one table"),
    "figures": ("figures", "the documented figures: rerun their recorded commands (run) and compare them (check)"),
    "config-schema": ("config_schema", "write config/config.schema.yaml's settings sections from their declarations"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; only ``command``'s stage module is imported (all of them when None)."""
    parser = argparse.ArgumentParser(prog="sellip", description="Sparse ellipsometry workflow stages.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        if command in (None, name):
            importlib.import_module(f"sellip.stages.{module}").configure_parser(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one stage; its last log line is where the job's time went (:mod:`sellip.timing`)."""
    clock = timing.start()
    # JAX would reserve 75 % of a GPU in the first process; several jobs share one card (workflow/profiles/gpu).
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    if command == "pass-through" and argv[0] == command:
        from sellip.stages.pass_through import split

        argv = split(argv)
        if not argv:  # passed through: the job's time is its start-up and the links
            logging.getLogger("sellip").info(timing.format_report(clock.report()))
            return 0
        command = next((a for a in argv if not a.startswith("-")), None)
    with timing.phase("imports"):
        args = build_parser(command if command in COMMANDS else None).parse_args(argv)
        module = importlib.import_module(f"sellip.stages.{args._module}")
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    with timing.phase("run"):
        try:
            status = int(module.main(args) or 0)
        except OSError as exc:
            if exc.errno not in workflow_support.NO_SPACE_ERRNOS:
                raise
            logging.getLogger("sellip").error("%s", workflow_support.no_space_message(exc))
            return 1
    logging.getLogger("sellip").info(timing.format_report(clock.report()))
    return status


if __name__ == "__main__":
    sys.exit(main())
