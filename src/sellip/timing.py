"""Where a job's time goes (docs/speed.md): start-up, imports, reading, tracing and compiling, work, writing.

``sellip`` (:func:`sellip.cli.main`) starts one :class:`JobClock` per process; stages mark what they
do with :func:`mark` (``mark("read")``: from here on, reading) or :func:`phase` (``with phase("read"):``). JAX's own
compile events are taken out of the phase they happen in and counted apart: ``trace`` (Python to jaxpr), ``lower``
(jaxpr to MLIR), ``compile`` (XLA, or a hit in the persistent cache: ``cache_load``). At the end of the job one log
line carries the seconds of every part::

    sellip job phases (s): {"startup": 0.4, "imports": 2.1, "read": 0.3, "trace": 1.2, ...}

``startup`` is from the process's creation to the clock's start (interpreter and ``sellip.cli``);
``other`` is what no phase claimed. :func:`read_job_phases` reads the line back from a log.

Public API::

    start() -> JobClock          # the process's clock (once, in cli.main)
    mark(name)                   # the time from here to the next mark counts for name
    phase(name)                  # context manager; nested phases count for the innermost
    JobClock.report() -> dict    # seconds per part, with "total"
    read_job_phases(log_path) -> dict | None
    phase_table(rules) -> str    # markdown, one row per rule of evaluate.stage_timings(...)["rules"]
"""

from __future__ import annotations

import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

MARKER = "sellip job phases (s): "

JAX_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/compilation_cache/cache_retrieval_time_sec": "cache_load",
}
"""JAX monitoring events (jax._src.dispatch / compiler) and the part each counts for. The backend
compile event includes a persistent-cache retrieval, which is moved from ``compile`` to ``cache_load``."""


def _process_start() -> float:
    """Wall-clock time (time.time()) at which this process was created."""
    try:
        import psutil

        return float(psutil.Process().create_time())
    except Exception:  # noqa: BLE001 - no psutil or no /proc: start-up unknown, counted as 0
        return time.time()


class JobClock:
    """Seconds per phase of one process. Use the module functions (:func:`start`, :func:`phase`)."""

    def __init__(self):
        self.started = time.perf_counter()
        self.startup = max(0.0, time.time() - _process_start())
        self.seconds: dict[str, float] = {}
        self.stack: list[list] = []  # [name, entered, seconds taken out by JAX events]

    def on_event(self, part: str, duration: float) -> None:
        """A JAX compile event of ``duration`` s (see :data:`JAX_EVENTS`)."""
        if part == "cache_load":  # already inside the backend compile event: move it
            self.seconds["compile"] = self.seconds.get("compile", 0.0) - duration
        elif self.stack:
            self.stack[-1][2] += duration
        self.seconds[part] = self.seconds.get(part, 0.0) + duration

    @contextmanager
    def phase(self, name: str):
        _listen()
        if self.stack:  # the outer phase pauses: its time so far is its own
            outer = self.stack[-1]
            self._add(outer[0], time.perf_counter() - outer[1] - outer[2])
        self.stack.append([name, time.perf_counter(), 0.0])
        try:
            yield
        finally:
            _listen()
            inner = self.stack.pop()
            self._add(inner[0], time.perf_counter() - inner[1] - inner[2])
            if self.stack:
                self.stack[-1][1], self.stack[-1][2] = time.perf_counter(), 0.0

    def mark(self, name: str) -> None:
        """From now on the innermost phase's time counts for ``name`` (one phase after another)."""
        _listen()
        if not self.stack:
            self.stack.append([name, time.perf_counter(), 0.0])
            return
        top = self.stack[-1]
        self._add(top[0], time.perf_counter() - top[1] - top[2])
        top[:] = [name, time.perf_counter(), 0.0]

    def _add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + max(0.0, seconds)

    def report(self) -> dict:
        """Seconds per part (rounded to ms): startup, each phase, the JAX parts, other and total."""
        elapsed = time.perf_counter() - self.started
        parts = {"startup": self.startup, **self.seconds}
        parts["other"] = max(0.0, elapsed - sum(self.seconds.values()))
        parts["total"] = self.startup + elapsed
        return {name: round(value, 3) for name, value in parts.items()}


_CLOCK: JobClock | None = None
_LISTENING = False


def _listen() -> None:
    """Count JAX's compile events for the running clock once JAX is imported (the stages import it lazily)."""
    global _LISTENING
    if _LISTENING or "jax" not in sys.modules:
        return
    from jax import monitoring

    def on_event(event: str, duration: float, **_) -> None:
        part = JAX_EVENTS.get(event)
        if part is not None and _CLOCK is not None:
            _CLOCK.on_event(part, duration)

    monitoring.register_event_duration_secs_listener(on_event)
    _LISTENING = True


def start() -> JobClock:
    """The process's clock, started now (a second call restarts it: ``cli.main`` called twice in one process)."""
    global _CLOCK
    _CLOCK = JobClock()
    return _CLOCK


@contextmanager
def phase(name: str):
    """Count the time of the block for ``name`` (nothing when no clock runs: library use)."""
    if _CLOCK is None:
        yield
        return
    with _CLOCK.phase(name):
        yield


def mark(name: str) -> None:
    """Count the time from here to the next mark (or the end of the enclosing phase) for ``name``."""
    if _CLOCK is not None:
        _CLOCK.mark(name)


def format_report(report: dict) -> str:
    return MARKER + json.dumps(report)


def read_job_phases(log: str | Path) -> dict | None:
    """The phases line of a job's log (the last one), or None when the log has none."""
    found = None
    try:
        with open(log, encoding="utf-8", errors="replace") as handle:
            for line in handle:
                at = line.find(MARKER)
                if at >= 0:
                    found = line[at + len(MARKER):]
    except OSError:
        return None
    return None if found is None else json.loads(found)


COLUMNS = (("startup", ("startup",)), ("imports", ("imports",)), ("read", ("read",)),
           ("trace + lower", ("trace", "lower")), ("compile", ("compile",)), ("cache load", ("cache_load",)),
           ("write", ("write",)))
"""Columns of :func:`phase_table`: the overheads; everything else a job's phases hold is its work."""


def phase_table(rules: dict) -> str:
    """Markdown table of where each rule's time went: per rule (``evaluate.stage_timings(...)["rules"]``, with
    ``phases``) the jobs, the summed wall time of the jobs (Snakemake benchmarks), the overhead columns of
    :data:`COLUMNS`, the work (every other phase), and ``snakemake`` = wall time minus the process's own
    (the shell and the job's start by Snakemake). Rules whose logs have no phases line show only their wall time."""
    header = ["rule", "jobs", "wall s", *(name for name, _ in COLUMNS), "work", "snakemake"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    total = {name: 0.0 for name in header[2:]}
    claimed = {part for _, parts in COLUMNS for part in parts} | {"total"}
    for rule, entry in sorted(rules.items(), key=lambda item: -item[1]["s"]):
        phases = entry.get("phases") or {}
        cells = [rule, str(entry["jobs"]), f"{entry['s']:.1f}"]
        total["wall s"] += entry["s"]
        if not phases:
            lines.append("| " + " | ".join(cells + ["–"] * (len(header) - 3)) + " |")
            continue
        values = {name: sum(phases.get(part, 0.0) for part in parts) for name, parts in COLUMNS}
        values["work"] = sum(v for k, v in phases.items() if k not in claimed)
        values["snakemake"] = entry["s"] - phases.get("total", 0.0) if entry.get("phases_jobs") == entry["jobs"] \
            else float("nan")
        for name, value in values.items():
            total[name] += value if value == value else 0.0
        lines.append("| " + " | ".join(cells + [f"{values[name]:.1f}" for name in header[3:]]) + " |")
    lines.append("| **all** | " + str(sum(e["jobs"] for e in rules.values())) + " | "
                 + " | ".join(f"**{total[name]:.1f}**" for name in header[2:]) + " |")
    return "\n".join(lines)


def read_benchmark(path: str | Path) -> dict:
    """One Snakemake ``benchmark:`` file (tab-separated, one row per repeat): ``wall_s`` (mean of ``s``), ``cpu_s``
    (mean of ``cpu_time``, user + system; NaN without the column) and ``max_rss_mb`` (max of ``max_rss``; NaN
    without it). ValueError naming the file when it has no row with an ``s`` column."""
    import math

    import pandas as pd

    table = pd.read_csv(path, sep="\t")
    if table.empty or "s" not in table.columns:
        raise ValueError(f"{path}: not a Snakemake benchmark file (no row with an 's' column)")
    return {"wall_s": float(table["s"].mean()),
            "cpu_s": float(table["cpu_time"].mean()) if "cpu_time" in table.columns else math.nan,
            "max_rss_mb": float(table["max_rss"].max()) if "max_rss" in table.columns else math.nan}
