"""``sellip pass-through``: a job of the outer loop that passes its inputs through once the loop has converged
(:func:`sellip.fit.convergence.pass_through`; docs/speed.md, "Convergence").

    sellip pass-through --after results/NAME/iter/4/mesh.ply.json [--link SOURCE OUTPUT ...] [--marker FILE ...]
                        [--marker-folder FOLDER ...] -- COMMAND [ARGUMENTS ...]

When the summary ``--after`` (the previous iteration's geometry update) says the loop has converged, each
``--link`` output is made from its source (hard links; a ``.json`` summary copied and marked ``passed_through``),
each ``--marker`` file and ``--marker-folder`` folder written, and ``COMMAND`` does not run; otherwise ``sellip
COMMAND ARGUMENTS`` runs in this process as if called directly (:func:`split`).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger(__name__)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--after", type=Path, required=True,
                        help="the previous iteration's mesh.ply.json: its convergence verdict decides")
    parser.add_argument("--link", nargs=2, type=Path, action="append", default=[], metavar=("SOURCE", "OUTPUT"),
                        help="an output made from the previous iteration's (hard links; .json copied)")
    parser.add_argument("--marker", type=Path, action="append", default=[], help="an output file nothing reads")
    parser.add_argument("--marker-folder", type=Path, action="append", default=[],
                        help="an output folder nothing reads")


def split(argv: list[str]) -> list[str]:
    """``argv`` of ``sellip pass-through ... -- COMMAND ...``: pass through and return [] when the loop has converged,
    else return ``COMMAND ...`` (what to run instead). Exits with status 2 and a message when there is no ``--``
    or no command after it."""
    from sellip.fit.convergence import converged_at, pass_through

    own = argv[1:]
    parser = argparse.ArgumentParser(prog="sellip pass-through")
    configure_parser(parser)
    if "--" not in own or own.index("--") == len(own) - 1:
        parser.error("expected -- and the sellip command to run when the loop has not converged")
    cut = own.index("--")
    args = parser.parse_args(own[:cut])
    if converged_at(args.after) is None:
        return own[cut + 1:]
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    pass_through(args.after, [tuple(pair) for pair in args.link], args.marker, args.marker_folder)
    return []


def main(args: argparse.Namespace) -> int:
    raise SystemExit("sellip pass-through runs through sellip.cli.main (it needs the command after --)")
