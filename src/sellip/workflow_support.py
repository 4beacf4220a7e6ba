"""Helpers of the Snakefile (workflow/rules/common.smk) that are worth a unit test (issue #38).

Every function here runs in the Snakemake process when the workflow is parsed, before any job: it imports
nothing heavy (no numpy, pandas or JAX) and never raises on a capture it cannot read (the stage that reads the
capture reports that, with file, row and column).

- :func:`check_results_name` -- config ``name`` must be one plain path component (``results/NAME/``).
- :func:`coerce_to_schema` -- ``--config 'augment={min_coherence: 0}'`` arrives as the string ``'0'``
  (Snakemake parses nested values with YAML's BaseLoader); this turns such strings into the number, boolean or
  null that the config schema expects at that key.
- :func:`raw_frame_files`, :func:`optional_file` -- the files of a capture that are inputs of the DAG
  (the raw frames frames.csv names, poses.csv, ground truth), so that changing one re-runs what reads it.
- :func:`collect_warnings`, :func:`failed_job_logs`, :func:`error_lines` -- the run's warnings and a failed job's
  error message, read from the jobs' log files, for the console and the report.
"""

from __future__ import annotations

import csv
import errno
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import yaml

FRAMES_CSV = "frames.csv"

_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


class ResultsNameError(ValueError):
    """Config ``name`` is not a single plain path component."""


def check_results_name(name: object) -> str:
    """``name`` if it is a single plain path component (results go to ``results/NAME/``), else ValueError.

    Spaces and non-ASCII letters are fine; empty, ``.``, ``..``, anything with ``/`` or ``\\``, a control
    character, or leading or trailing spaces are not (``name=..`` would write into the repository's root).
    """
    text = str(name) if name is not None else ""
    why = None
    if not text:
        why = "it is empty"
    elif text in (".", ".."):
        why = f"'{text}' is not a folder name but a reference to a folder"
    elif "/" in text or "\\" in text:
        why = "it contains a path separator"
    elif _CONTROL.search(text):
        why = "it contains a control character"
    elif text != text.strip():
        why = "it starts or ends with white space"
    elif text.startswith("-"):
        why = "it starts with '-' (it would read as an option)"
    if why:
        raise ResultsNameError(f"config: name {text!r} is not a usable results name: {why}. Expected one plain folder "
                         "name (letters, digits, spaces, '_', '-', '.'), e.g. name=owl; results go to results/NAME/")
    return text


# --------------------------------------------------------------------------- --config values

def _types(schema: Mapping) -> list[str]:
    kind = schema.get("type")
    return [kind] if isinstance(kind, str) else list(kind or [])


def _scalar(text: str, kinds: Iterable[str]):
    """``text`` as a value of one of the JSON-schema ``kinds`` (YAML's reading of it), or the text itself."""
    kinds = list(kinds)
    if "string" in kinds or not kinds:
        return text
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    if isinstance(value, bool):
        return value if "boolean" in kinds else text
    if isinstance(value, int) and ("integer" in kinds or "number" in kinds):
        return value
    if isinstance(value, float) and "number" in kinds:
        return int(value) if "integer" in kinds and "number" not in kinds and value.is_integer() else value
    if value is None and "null" in kinds:
        return None
    return text


def coerce_to_schema(value, schema: Mapping):
    """``value`` with each string converted where ``schema`` (a JSON schema, the parts sellip's config schema
    uses: type, properties, items, oneOf/anyOf) expects a number, integer, boolean or null there (lists too:
    ``smoothness: [0.1, 0.01]`` arrives as two strings), and an empty value (None) where only a string is
    expected becomes ``''`` (``--config capture=``). Anything else is returned as it is, and the schema's
    validation then reports it. Pure; the input is not modified."""
    if not isinstance(schema, Mapping):
        return value
    alternatives = list(schema.get("oneOf") or []) + list(schema.get("anyOf") or [])
    if alternatives:
        import jsonschema

        for alternative in alternatives:
            candidate = coerce_to_schema(value, alternative)
            if jsonschema.Draft202012Validator(alternative).is_valid(candidate):
                return candidate
    kinds = _types(schema)
    if isinstance(value, Mapping):
        properties = schema.get("properties") or {}
        return {key: coerce_to_schema(item, properties.get(key, {})) for key, item in value.items()}
    if isinstance(value, list) and isinstance(schema.get("items"), Mapping):
        return [coerce_to_schema(item, schema["items"]) for item in value]
    if isinstance(value, str) and kinds:
        return _scalar(value, kinds)
    if value is None and kinds == ["string"]:
        return ""  # `--config capture=` (Snakemake gives None for an empty value)
    return value


# --------------------------------------------------------------------------- capture files as inputs

def raw_frame_files(capture: str | Path) -> list[str]:
    """The raw frame files that ``capture``/frames.csv names and that exist, in file order, without repeats
    (paths as ``capture``/file). Empty when frames.csv is missing or cannot be read as CSV: ``sellip
    linearize`` reports that. A named file that does not exist is left out, so that ``ingest.bad_frames: skip``
    can run without it, and adding it later changes the job's input set (Snakemake then re-runs the job)."""
    frames = Path(capture) / FRAMES_CSV
    try:
        with open(frames, newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle, skipinitialspace=True))
    except (OSError, UnicodeDecodeError, csv.Error):
        return []
    files = []
    for row in rows:
        relative = (row.get("file") or "").strip()
        if relative and (Path(capture) / relative).is_file():
            files.append(str(Path(capture) / relative))
    return list(dict.fromkeys(files))


def optional_file(capture: str | Path, relative: str) -> list[str]:
    """``[capture/relative]`` when that file exists, else ``[]`` (an optional input: poses.csv, the ground truth)."""
    path = Path(capture) / relative
    return [str(path)] if path.is_file() else []


# --------------------------------------------------------------------------- what the console shows

_LEVEL = re.compile(r"^\S+ \S+ (WARNING|ERROR|CRITICAL) (\S+): (.*)$")
"""A line of sellip's log format, ``%(asctime)s %(levelname)s %(name)s: %(message)s``."""


def collect_warnings(logs: str | Path) -> list[tuple[str, str]]:
    """(log file relative to ``logs``, message) of every WARNING line in the job logs under ``logs``, in the
    order of the log files' names, each message once."""
    logs = Path(logs)
    found, seen = [], set()
    if not logs.is_dir():
        return found
    for path in sorted(logs.rglob("*.log")):
        try:
            lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
        except OSError:
            continue
        for line in lines:
            match = _LEVEL.match(line)
            if match and match.group(1) == "WARNING" and match.group(3) not in seen:
                seen.add(match.group(3))
                found.append((str(path.relative_to(logs)), match.group(3)))
    return found


def format_warnings(warnings: list[tuple[str, str]], limit: int = 20) -> str:
    """The warnings of :func:`collect_warnings` as the lines the workflow prints at its end ('' for none)."""
    if not warnings:
        return ""
    lines = [f"sellip: {len(warnings)} warning(s) in this run's logs:"]
    lines += [f"  [{log}] {message}" for log, message in warnings[:limit]]
    if len(warnings) > limit:
        lines.append(f"  ... and {len(warnings) - limit} more (grep WARNING in the logs folder)")
    return "\n".join(lines)


def failed_job_logs(snakemake_log) -> list[tuple[str, list[str]]]:
    """(rule, its log files) of each ``Error in rule NAME:`` block in Snakemake's own log file (a path, or the list
    of paths that Snakemake passes to ``onerror``)."""
    paths = [snakemake_log] if isinstance(snakemake_log, (str, Path)) else list(snakemake_log or [])
    lines = []
    for path in paths:
        try:
            lines += Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
        except (OSError, TypeError):
            continue
    failed, rule = [], None
    for line in lines:
        start = re.match(r"^Error in rule (\S+):", line)
        if start:
            rule = start.group(1)
            failed.append((rule, []))
            continue
        if rule is not None:
            entry = re.match(r"^\s+log: (.*?)(?: \(check log file\(s\) for error details\))?$", line)
            if entry:
                failed[-1][1].extend(part.strip() for part in entry.group(1).split(", ") if part.strip())
            elif line and not line.startswith((" ", "\t")):
                rule = None
    return failed


def error_lines(log: str | Path, limit: int = 8) -> list[str]:
    """A failed job's message from its log: the ERROR lines of sellip's log format (the message only), else
    the last lines of a traceback or of the file (at most ``limit`` lines)."""
    try:
        lines = Path(log).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return []
    errors = [m.group(3) for m in map(_LEVEL.match, lines) if m and m.group(1) in ("ERROR", "CRITICAL")]
    if errors:
        return errors[-limit:]
    lines = [line for line in lines if line.strip()]
    return lines[-limit:]


def killed_from_outside(log: str | Path) -> list[str]:
    """For a job log that ends mid-run (its last line one of sellip's INFO/DEBUG/WARNING lines; no ERROR line, no
    traceback): what that means, and the log's memory estimates (a fit job's ``memory:`` line,
    :func:`sellip.fit.shard.fit_shard`). Empty otherwise."""
    try:
        lines = Path(log).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return []
    levels = [m.group(1) for m in map(_LEVEL.match, lines) if m]
    last = next((line for line in reversed(lines) if line.strip()), "")
    if ("ERROR" in levels or "CRITICAL" in levels or any(line.startswith("Traceback") for line in lines)
            or not re.match(r"^\S+ \S+ (DEBUG|INFO|WARNING) \S+: ", last)):
        return []  # an error of its own, or not a sellip log that stops mid-run (e.g. "sellip: command not found")
    memory = [line.split(": ", 1)[1] for line in lines if " memory: about " in line]
    return (["it stopped without an error message: it was killed from outside (the system's out-of-memory "
             "killer, a time limit, or by hand)"] + [f"its {line}" for line in memory[-1:]])


def format_failures(snakemake_log, root: str | Path = ".") -> str:
    """What failed and why, for the console: for each failed rule, its log's error lines and where the log is;
    for a job killed from outside (:func:`killed_from_outside`), that, and its memory estimate."""
    out = []
    for rule, logs in failed_job_logs(snakemake_log):
        for log in logs or [None]:
            out.append(f"sellip: rule {rule} failed" + (f" (full log: {log})" if log else ""))
            if log:
                out += [f"  {line}" for line in error_lines(Path(root) / log)]
                out += [f"  {line}" for line in killed_from_outside(Path(root) / log)]
    if out:
        out.append("sellip: fix that and run the same command again: finished jobs are kept (docs/reliability.md)")
    return "\n".join(out)


def load_yaml(path: str | Path):
    """A YAML file (the config schema) as Python objects."""
    with open(path, encoding="utf-8") as handle:
        return yaml.safe_load(handle)


NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""A write that failed for want of room: a full disk, a quota, a file-size limit."""


def no_space_message(exc: OSError) -> str:
    """What a stage says when a write fails for want of room (``exc.errno`` in NO_SPACE_ERRNOS)."""
    where = f" while writing {exc.filename}" if getattr(exc, "filename", None) else ""
    return (f"no room to write{where} ({exc.strerror or exc}): free disk space (or raise the quota / file-size "
            "limit) and run the same command again; nothing half-written is kept (outputs are written under a "
            "temporary name and renamed when complete)")
