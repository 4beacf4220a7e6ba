"""Helpers of the Snakefile (workflow/rules/common.smk) that are worth a unit test (issue #38).

Every function here runs in the Snakemake process when the workflow is parsed, before any job: it imports
nothing heavy (no numpy, pandas or JAX) and never raises on a capture it cannot read (the stage that reads the
capture reports that, with file, row and column).

- :func:`check_results_name` -- config ``name`` must be one plain path component (``results/NAME/``).
- :func:`check_config_keys` -- every config key, at every level, is a setting of the schema: a typo
  (``iteratons=2``, ``fit={shard: 3}``) is an error naming the key and the nearest valid one, a renamed key an error
  naming its new name.
- :func:`coerce_to_schema` -- ``--config 'augment={min_coherence: 0}'`` arrives as the string ``'0'``
  (Snakemake parses nested values with YAML's BaseLoader); this turns such strings into the number, boolean or
  null that the config schema expects at that key.
- :func:`raw_frame_files`, :func:`optional_file` -- the files of a capture that a stage reads (the raw frames
  frames.csv names, poses.csv, ground truth).
- :class:`ContentDigests` -- one digest of those files' content (size and BLAKE2b), cached by path, size, mtime,
  ctime and inode: a rule's ``params``, so that a change of content re-runs what reads the files whatever their
  modification times say, and a file touched but unchanged re-runs nothing.
- :func:`collect_warnings`, :func:`failed_job_logs`, :func:`error_lines` -- the run's warnings and a failed job's
  error message, read from the jobs' log files, for the console and the report.
- :func:`end_jobs_on_sigterm` -- SIGTERM ends the run and its jobs' processes within seconds (Snakemake's own
  handler waits for running jobs, and can deadlock on its scheduler's lock).
- :func:`record_run`, :func:`stale_model` -- a failed run's record in the results folder, and why the model on disk
  no longer stands for the inputs (older than a failed job, or than a capture file): the run's closing summary
  and ``sellip view`` say so.
"""

from __future__ import annotations

import csv
import errno
import hashlib
import json
import os
import re
import signal
import threading
import time
from collections.abc import Iterable, Mapping
from datetime import datetime
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


class ConfigKeyError(ValueError):
    """A config key that is not a setting (a typo), or one that was renamed."""


def config_key_errors(value, schema: Mapping, path: str = "") -> list[str]:
    """What is wrong with the keys of ``value`` (the config, or a section of it at ``path``) at every level: a key
    that ``schema`` (the config schema) does not declare where it admits no other (``additionalProperties:
    false``), named with the nearest valid key (:func:`sellip.settings.unknown_key_message`), or a key that was
    renamed (the section's ``x-renamed``: old key -> new dotted name). Empty when every key is known."""
    from sellip.settings import unknown_key_message

    if not isinstance(value, Mapping) or not isinstance(schema, Mapping):
        return []
    properties = schema.get("properties") or {}
    renamed = schema.get("x-renamed") or {}
    found = []
    for key, item in value.items():
        where = f"{path}.{key}" if path else str(key)
        if key in properties:
            found += config_key_errors(item, properties[key], where)
        elif key in renamed:
            found.append(f"config: '{where}' was renamed '{renamed[key]}': set {renamed[key]} instead")
        elif schema.get("additionalProperties") is False:
            found.append("config: " + unknown_key_message(where, properties))
    return found


def check_config_keys(config: Mapping, schema: Mapping) -> None:
    """ConfigKeyError listing every unknown or renamed key of ``config`` (:func:`config_key_errors`)."""
    found = config_key_errors(config, schema)
    if found:
        raise ConfigKeyError("\n".join(found))


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


def capture_view_ids(capture: str | Path) -> list[str] | None:
    """The view ids of ``capture``/frames.csv in order of first appearance, or None when it cannot be read (the
    stage that reads it reports that)."""
    try:
        with open(Path(capture) / FRAMES_CSV, newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle, skipinitialspace=True))
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    if not rows or "view_id" not in rows[0]:
        return None
    return list(dict.fromkeys(row["view_id"] for row in rows if row.get("view_id") is not None))


_UNSET = object()


def declared_setting(config: Mapping, schema: Mapping, path: str):
    """The value of the dotted config key ``path`` (``init.max_vertices``): the config's where it sets the key, else
    the declared default the schema states (``x-default``, written from the settings record); None where neither."""
    node, value = schema, config
    for part in path.split("."):
        node = (node.get("properties") or {}).get(part) or {}
        value = value.get(part, _UNSET) if isinstance(value, Mapping) else _UNSET
    return node.get("x-default") if value is _UNSET else value


VIEW_LIST_KEYS = ("held_out_views", "render_views")
"""The config keys of section ``evaluate`` that name views of the capture."""


def check_config_views(evaluate: Mapping, view_ids: list[str] | None, capture: str | Path) -> None:
    """ValueError naming the config key (``evaluate.held_out_views`` or ``evaluate.render_views``), the views it
    names that ``capture``/frames.csv lacks (quoted, so white space shows) and the valid ids; nothing when frames.csv
    could not be read (``view_ids`` None)."""
    if view_ids is None:
        return
    known = set(view_ids)
    for key in VIEW_LIST_KEYS:
        unknown = [v for v in (evaluate.get(key) or []) if str(v) not in known]
        if unknown:
            shown = view_ids[:20] + (["..."] if len(view_ids) > 20 else [])
            raise ValueError(f"config: evaluate.{key} names view(s) {unknown} that {Path(capture) / FRAMES_CSV} does "
                             f"not have; expected some of its {len(view_ids)} view ids {shown} (or [] for none), "
                             f"e.g. --config 'evaluate={{{key}: [{view_ids[0]}]}}'")


def optional_file(capture: str | Path, relative: str) -> list[str]:
    """``[capture/relative]`` when that file exists, else ``[]`` (an optional input: poses.csv, the ground truth)."""
    path = Path(capture) / relative
    return [str(path)] if path.is_file() else []


DIGEST_CACHE = ".snakemake/sellip/input_digests.json"
"""Where the workflow keeps :class:`ContentDigests`' cache, relative to Snakemake's working directory."""


def file_digest(path: str | Path, chunk: int = 1 << 20) -> str:
    """``'SIZE:HEX'``: the file's size in bytes and the BLAKE2b (128-bit) digest of its content."""
    hasher = hashlib.blake2b(digest_size=16)
    size = 0
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            hasher.update(block)
            size += len(block)
    return f"{size}:{hasher.hexdigest()}"


class ContentDigests:
    """Digests of files' content for the DAG (docs/reliability.md, "Every input is tracked by its content").

    :meth:`digest` of a list of files is one short string that changes when, and only when, a file's content
    changes, a file is added or one is removed: a rule carries it as a ``params`` value, and Snakemake's ``params``
    rerun trigger then re-runs the rule for a changed content even when the file is older than the outputs (``cp
    -p``, ``rsync -a``, a restored backup), while a file touched but unchanged has the same digest. Each file is
    read once: its digest is kept in the JSON file ``cache_file`` under its absolute path with its size,
    modification time, change time and inode (any write or ``utime`` changes the change time, which no user can set
    back, so a cached digest is never taken for a file whose content may have changed). The cache is written
    atomically; a cache that cannot be read or written is only slower."""

    def __init__(self, cache_file: str | Path):
        self.cache_file = Path(cache_file)
        self._entries: dict[str, list] | None = None
        self.computed = 0
        """How many files this object has read (those not found in the cache): for tests."""

    def _load(self) -> dict[str, list]:
        if self._entries is None:
            try:
                entries = json.loads(self.cache_file.read_text(encoding="utf-8"))
                self._entries = entries if isinstance(entries, dict) else {}
            except (OSError, ValueError):
                self._entries = {}
        return self._entries

    def _save(self) -> None:
        tmp = self.cache_file.with_name(f".{self.cache_file.name}.tmp-{os.getpid()}")
        try:
            self.cache_file.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(self._entries, sort_keys=True), encoding="utf-8")
            tmp.replace(self.cache_file)
        except OSError:
            tmp.unlink(missing_ok=True)

    def file_digest(self, path: str | Path) -> str:
        """``'SIZE:HEX'`` of :func:`file_digest`, from the cache when the file's stat matches the cached one."""
        path = Path(path).absolute()
        stat = path.stat()
        key = [stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino]
        entries = self._load()
        cached = entries.get(str(path))
        if isinstance(cached, list) and cached[:4] == key and len(cached) == 5:
            return cached[4]
        digest = file_digest(path)
        self.computed += 1
        entries[str(path)] = key + [digest]
        return digest

    def digest(self, files: Iterable[str | Path], root: str | Path = ".") -> str:
        """One digest of ``files`` (names relative to ``root``, so that it does not depend on where the work folder
        is), e.g. ``'3 file(s), blake2b 5c0f...'``: their names, sizes and contents. A file that does not exist
        counts as ``missing``. ``''`` for no files."""
        lines = []
        before = self.computed
        for path in files:
            name = os.path.relpath(Path(path).absolute(), Path(root).absolute())
            try:
                lines.append(f"{name}\t{self.file_digest(path)}")
            except OSError:
                lines.append(f"{name}\tmissing")
        if self.computed != before:
            self._save()
        if not lines:
            return ""
        total = hashlib.blake2b("\n".join(sorted(lines)).encode("utf-8"), digest_size=16).hexdigest()
        return f"{len(lines)} file(s), blake2b {total}"


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


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants (from /proc on Linux; elsewhere ``[pid]``), parents first."""
    children: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return [pid]
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="utf-8", errors="replace") as handle:
                parent = int(handle.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(parent, []).append(int(entry))
    tree, todo = [], [pid]
    while todo:
        current = todo.pop(0)
        tree.append(current)
        todo += children.get(current, [])
    return tree


def start_time(pid: int) -> int | None:
    """The process's start time in clock ticks since boot (/proc/PID/stat field 22), None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8", errors="replace") as handle:
            return int(handle.read().rsplit(")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def signal_processes(pids: Mapping[int, int | None], signum: int) -> None:
    """Send ``signum`` to each process of ``pids`` (pid -> its :func:`start_time`) that is still that process (not
    gone, its pid not taken by another since)."""
    for pid, started in pids.items():
        if start_time(pid) != started:
            continue
        try:
            os.kill(pid, signum)
        except (ProcessLookupError, PermissionError):
            continue


def end_jobs_on_sigterm(scheduler, grace_s: float = 5.0) -> None:
    """Make SIGTERM end a Snakemake run and its running jobs within seconds (the workflow's ``onstart``, after
    Snakemake installed its own handler).

    Snakemake's handler lets the running jobs finish (a fit job: minutes), and takes its scheduler's lock, which
    the main thread may hold at that moment (the handler runs in the main thread): the run then hangs with no job
    left. This handler takes no lock: it sends SIGTERM to every running local job's process and its descendants
    (the shell and the ``sellip`` under it), SIGKILL to those left after ``grace_s``, and tells the scheduler to stop
    as Snakemake's own handler would. The killed jobs fail, so Snakemake removes their outputs and the workflow's
    ``onerror`` records the failed run. Without the attributes it needs (another Snakemake), it leaves the
    previous handler in place."""
    if not (hasattr(scheduler, "_user_kill") and hasattr(scheduler, "_open_jobs")):
        return
    try:
        from snakemake.shell import shell
    except ImportError:
        return

    def handler(signum, frame):
        pids = {pid: start_time(pid) for process in list(getattr(shell, "_processes", {}).values())
                for pid in process_tree(process.pid)}
        signal_processes(pids, signal.SIGTERM)
        timer = threading.Timer(grace_s, signal_processes, (pids, signal.SIGKILL))
        timer.daemon = True
        timer.start()
        scheduler._user_kill = "graceful"  # what Snakemake's handler sets; one assignment, no lock needed
        scheduler._open_jobs.release()

    signal.signal(signal.SIGTERM, handler)


LAST_RUN = "last_run.json"
"""The record of the last run that ended (results/NAME/last_run.json): written by the workflow's onsuccess and
onerror."""

MODEL = "final/model.ply"
"""The final model, the file whose age :func:`stale_model` compares."""


def record_run(results: str | Path, status: str, snakemake_log=None, started: float | None = None,
               now: float | None = None) -> Path:
    """Write ``results``/last_run.json at the end of a run: ``{"status": "failed" | "complete", "started": epoch
    seconds, "ended": epoch seconds, "failed": [{"rule", "logs"}]}`` (the failed rules from Snakemake's log,
    :func:`failed_job_logs`; an interrupted run fails too). Atomic; a folder that cannot be written is left as it
    is."""
    now = time.time() if now is None else now
    record = {"status": status, "started": now if started is None else started, "ended": now,
              "failed": [{"rule": rule, "logs": logs} for rule, logs in failed_job_logs(snakemake_log)]
              if status == "failed" else []}
    path = Path(results) / LAST_RUN
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(record, indent=1), encoding="utf-8")
        tmp.replace(path)
    except OSError:  # a read-only or full results folder: the run's own message says more
        tmp.unlink(missing_ok=True)
    return path


def _when(epoch: float) -> str:
    return datetime.fromtimestamp(epoch).strftime("%Y-%m-%d %H:%M:%S")


def stale_model(results: str | Path, capture: str | Path | None = None) -> list[str]:
    """Why the model in ``results`` (final/model.ply) and what was made from it may not stand for the current
    inputs, one sentence (empty when nothing says so, or when there is no model): the last run failed or was
    interrupted (last_run.json) before it wrote a new model, or after (then its renders, metrics and viewer are
    missing or an earlier run's); and, given ``capture``, capture files
    (capture.yaml, frames.csv, poses.csv, the raw frames) modified after the model was made."""
    results = Path(results)
    model = results / MODEL
    try:
        made = model.stat().st_mtime
    except OSError:
        return []
    try:
        record = json.loads((results / LAST_RUN).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        record = {}
    record = record if isinstance(record, dict) else {}
    reasons, after = [], False
    if record.get("status") == "failed" and made < float(record.get("ended") or 0):  # else a later run made it
        started = float(record.get("started") or 0)
        rules = [f"rule {entry.get('rule')} (log: {', '.join(entry.get('logs') or []) or 'none'})"
                 for entry in record.get("failed") or []]
        what = f"the last run (started {_when(started)}) failed" + (f" at {'; '.join(rules)}" if rules else "")
        after = made >= started
        reasons.append(what + (" after it wrote the model: the renders, metrics and viewer are missing or an "
                               "earlier run's" if after else ""))
    if capture is not None:
        changed = []
        for path in [*(Path(capture) / name for name in ("capture.yaml", FRAMES_CSV, "poses.csv")),
                     *map(Path, raw_frame_files(capture))]:
            try:
                if path.stat().st_mtime > made:
                    changed.append(str(path))
            except OSError:
                continue
        if changed:
            after = False
            reasons.append(f"{len(changed)} capture file(s) changed after it ({changed[0]}"
                           + (f" and {len(changed) - 1} more)" if len(changed) > 1 else ")"))
    if not reasons:
        return []
    head = f"{model} (made {_when(made)})" + (" is this run's, but" if after else " is out of date:")
    tail = ("" if after else ". Its metrics, renders and viewer are those of an earlier run")
    return [f"{head} {'; '.join(reasons)}{tail}: fix that and run the same command again"]


def load_yaml(path: str | Path):
    """A YAML file (the config schema) as Python objects; a key given twice is refused
    (:class:`sellip.yaml_files.DuplicateKeyError`)."""
    from sellip.yaml_files import load_yaml_file

    return load_yaml_file(path)


def check_config_files(paths: Iterable[str | Path]) -> None:
    """Raise ValueError naming the file, the key and both lines when a config file (config/config.yaml, a
    ``--configfile``) gives a key twice in one mapping: Snakemake's reader keeps the second value silently."""
    from sellip.yaml_files import DuplicateKeyError

    for path in paths:
        try:
            load_yaml(path)
        except DuplicateKeyError as exc:
            raise ValueError(f"{path}: {exc}") from None


NO_SPACE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""A write that failed for want of room: a full disk, a quota, a file-size limit."""


def no_space_message(exc: OSError) -> str:
    """What a stage says when a write fails for want of room (``exc.errno`` in NO_SPACE_ERRNOS)."""
    where = f" while writing {exc.filename}" if getattr(exc, "filename", None) else ""
    return (f"no room to write{where} ({exc.strerror or exc}): free disk space (or raise the quota / file-size "
            "limit) and run the same command again; nothing half-written is kept (outputs are written under a "
            "temporary name and renamed when complete)")
