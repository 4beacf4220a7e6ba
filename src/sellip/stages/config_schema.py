"""``sellip config-schema``: write config/config.schema.yaml's settings sections from their declarations.

    sellip config-schema [--schema config/config.schema.yaml] [--check]

A config section that holds a settings record's fields names the record (``x-record: module:Class``, e.g. the
``refine_poses`` section and :class:`sellip.geometry.pose_refinement.PoseRefinementSettings`); its properties are
written from the record's declarations (:func:`sellip.settings.record_schema`: type, range, meaning, unit), beside
the section's own workflow keys (``enabled``, ``every``, ...), which are kept as written. ``x-per-iteration:
false`` marks a section whose values are not lists per iteration. With ``--check`` nothing is written: the exit
status is 1, naming the file, when it differs from what would be written (a test runs this).
"""

from __future__ import annotations

import argparse
import importlib
import logging
from pathlib import Path

import yaml

log = logging.getLogger(__name__)

SCHEMA = Path("config/config.schema.yaml")
HEADER = ("# sellip workflow configuration schema (config/config.yaml). Sections marked x-record are written from the\n"
          "# settings records' declarations by `sellip config-schema` (src/sellip/settings.py); edit the record, not\n"
          "# them. Every object rejects unknown keys (additionalProperties: false); x-renamed names a key's new\n"
          "# name.\n")


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--schema", type=Path, default=SCHEMA, help="the schema file (default: %(default)s)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when the file is out of date")


def generated(schema: dict) -> dict:
    """``schema`` with every ``x-record`` section's record properties written from the record (in place)."""
    from sellip.settings import record_schema

    def visit(node):
        if isinstance(node, dict):
            if "x-record" in node:
                module, name = node["x-record"].split(":")
                record = getattr(importlib.import_module(module), name)
                derived = record_schema(record, per_iteration=node.get("x-per-iteration", True))
                # the section's own keys (the workflow's: threads, enabled, ...); a key with an x-default came from the
                # record, and is dropped once the record no longer declares it
                own = {k: v for k, v in (node.get("properties") or {}).items()
                       if k not in derived["properties"] and not (isinstance(v, dict) and "x-default" in v)}
                node["properties"] = {**own, **derived["properties"]}
                node["additionalProperties"] = False
            for value in node.values():
                visit(value)
        elif isinstance(node, list):
            for value in node:
                visit(value)
        return node

    return visit(schema)


class _Dumper(yaml.SafeDumper):
    def ignore_aliases(self, data):  # each value written out, no YAML anchors
        return True


def render(schema: dict) -> str:
    return HEADER + yaml.dump(schema, Dumper=_Dumper, sort_keys=False, width=118, allow_unicode=True,
                              default_flow_style=None)


def main(args: argparse.Namespace) -> int:
    text = args.schema.read_text(encoding="utf-8")
    wanted = render(generated(yaml.safe_load(text)))
    if args.check:
        if text != wanted:
            log.error("%s is out of date with the settings records: run `sellip config-schema` and commit it",
                      args.schema)
            return 1
        return 0
    if text != wanted:
        args.schema.write_text(wanted, encoding="utf-8")
        log.info("wrote %s", args.schema)
    return 0
