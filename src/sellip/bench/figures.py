"""The documented figures (issue #49 item 6): every number of the README's accuracy table that a recorded command
measures, where in that command's output it is read, and how far a rerun may land from it.

The documented value has one home, the document: :func:`documented` reads it from the document's table row (the row
is found by its command, written in backticks in its first cell, so a row and its command cannot drift apart) and
:func:`check` compares it with the finished run's output. The registry holds no documented values, only where
they are (:class:`Figure`) and how they are measured (:class:`Run`). A row whose format changed stops the check
with the file, line, column and cell text (:class:`FiguresError`).

Tolerances are per kind (:data:`TOLERANCES`), chosen from the spread measured between runs that should agree
(another machine, another seed: docs/reproducibility.md, docs/benchmarks.md); the README states them in the line
:func:`tolerance_line` writes, and :func:`document_problems` fails the check when that line is not in the README.

Sizes: ``small`` runs are what a 2-core machine runs in minutes (the demo); ``large`` ones take an hour or more.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from sellip.bench.ladder import capture_tag, workflow_run_name

README = "README.md"


class FiguresError(ValueError):
    """A registered figure cannot be read from its document or its run (names the file, line and what to do)."""


@dataclass(frozen=True)
class Run:
    """A recorded command whose outputs carry documented figures.

    ``command``: what to run from the repository root, as the document writes it (``python`` is the project's
    interpreter); ``results``: the run's folder under the results root (its ``metrics.json``); ``size``: ``small``
    (minutes on 2 cores) or ``large``; ``minutes``: its run time on 2 cores as documented; ``seeds``: the seeds that
    make it what it is (all from config/config.yaml unless said)."""

    name: str
    command: str
    results: str
    size: str
    minutes: int
    seeds: str


@dataclass(frozen=True)
class Figure:
    """One documented number: in ``doc``, the table row whose first cell holds ``run``'s command in backticks, the
    column headed ``column``, group ``group`` of the regular expression ``pattern`` on that cell, times ``scale``.

    ``source``: where the run's output holds it: ``metrics:<dotted.key.path>`` in its metrics.json (list items and
    dict keys alike), or ``clusters:k`` (every iteration's ``iter/<it>/clusters/clusters.json`` ``k``: each must
    match), in the run's results folder, or in its sub-folder ``folder`` where one command makes several workflow
    runs (the accuracy ladder's rungs). ``kind``: the key of its tolerance in :data:`TOLERANCES`."""

    name: str
    run: str
    column: str
    pattern: str
    source: str
    kind: str
    group: int = 1
    scale: float = 1.0
    doc: str = README
    folder: str = ""


# kind -> (tolerance, unit, what it is), absolute, but relative where the unit is "%" (the vertex count, which the
# documents round to hundreds or thousands). η per material: a material's median η moved 0.05 points between
# two machines (plumage 0.09 / 0.14 %) and 0.4 points between runs of one setting (docs/benchmarks.md, the sweep's
# noise); a small material (the demo's eyes, 54 vertices) moves more: 1.76-2.29 % over runs and replays, and
# the README's own capture gave 1.47 % on an AMD EPYC and 0.31 % on an Intel Xeon (1.19 points apart, the same code;
# each inside the other's 95 % interval, about ±2.1 % of eta: docs/reproducibility.md).
# Normals 0.730 / 0.733 deg, held-out PSNR 31.6-31.73 dB and Chamfer 0.063-0.064 mm across machines and versions.
TOLERANCES: dict[str, tuple[float, str, str]] = {
    "eta_pct": (0.5, "points", "η per material"),
    "eta_small_pct": (2.0, "points", "η of a small material (the demo's eyes, 54 vertices)"),
    "normal_deg": (0.05, "°", "normals (median)"),
    "psnr_db": (0.3, "dB", "held-out PSNR"),
    "chamfer_mm": (0.005, "mm", "Chamfer"),
    "vertices": (2, "%", "vertices"),
    "materials": (0, "", "the number of materials"),
}

# The painted cow's workflow rungs: the settings of its command and of its results folders (one declaration).
_COW_RUNS = {"iterations": 3, "max_vertices": 10000, "hull_resolution": 128}

RUNS: tuple[Run, ...] = (
    Run("demo", "make demo", "demo", "small", 7, "seed 0, demo.seed 0 (the capture's sensor noise)"),
    Run("sphere_ior_scale", "python benchmarks/scale.py --sizes 72x1224x1024:100000:10",
        "bench/scale/sphere_ior_72v_1224x1024_100000n_10it/results/run", "large", 58,
        "seed 0; the capture's seed 0 (sellip.capture.synthetic.synthesize_capture default)"),
    Run("sphere_ior_mitsuba",
        "python benchmarks/accuracy_ladder.py --scene sphere_ior --renderer mitsuba --views 72 --width 1224 "
        "--height 1024 --rungs hull --iterations 3 --max-vertices 30000",
        "bench/ladder/sphere_ior_72v_1224x1024_mitsuba/results/sphere_ior_72v_1224x1024_mitsuba_hull_3it_30000v",
        "large", 25, "seed 0; the capture's seed 0 (sellip.capture.synthetic.synthesize_capture default)"),
    *(Run(f"cow_painted_{renderer}",
          f"python benchmarks/accuracy_ladder.py --scene cow_painted{flag} --views 72 --width 1224 --height 1024 "
          f"--seed 3 --rungs hull sfm --iterations {_COW_RUNS['iterations']} --max-vertices "
          f"{_COW_RUNS['max_vertices']} --hull-resolution {_COW_RUNS['hull_resolution']}",
          f"bench/ladder/{capture_tag('cow_painted', 72, 1224, 1024, renderer, 3)}/results", "large", minutes,
          "seed 0; the capture's seed 3 (orbit and sensor noise)")
      for renderer, flag, minutes in (("sellip", "", 21), ("mitsuba", " --renderer mitsuba", 19))),
)

_ETA = "η per material"


def _vertices(run: str) -> Figure:
    return Figure(f"{run}: vertices", run, "what is measured (command)", r"([\d.]+)k vertices",
                  "metrics:vertices.model", "vertices", scale=1000)


def _headline(run: str) -> tuple[Figure, ...]:
    """The normals, held-out PSNR and Chamfer columns of ``run``'s row."""
    return (Figure(f"{run}: normals median (°)", run, "normals (median)", r"([\d.]+)°",
                   "metrics:normal_error_deg.all.median", "normal_deg"),
            Figure(f"{run}: held-out PSNR (dB)", run, "held-out PSNR", r"([\d.]+) dB", "metrics:psnr_held_out.mean_db",
                   "psnr_db"),
            Figure(f"{run}: Chamfer (mm)", run, "surface", r"Chamfer ([\d.]+) mm", "metrics:geometry.chamfer_mm",
                   "chamfer_mm"))


def _sphere(run: str) -> tuple[Figure, ...]:
    """A ``sphere_ior`` row: vertices, η per material mean and worst ("0.25 % mean, 0.48 % worst"), the headline."""
    eta = r"([\d.]+) % mean, ([\d.]+) % worst"
    return (_vertices(run),
            Figure(f"{run}: η mean (%)", run, _ETA, eta, "metrics:eta_per_material.mean_error_pct", "eta_pct"),
            Figure(f"{run}: η worst (%)", run, _ETA, eta, "metrics:eta_per_material.max_error_pct", "eta_pct",
                   group=2),
            *_headline(run))


def _known_and_sfm(run: str) -> tuple[Figure, ...]:
    """A row of two rungs of one accuracy-ladder command, "known / SfM" in each cell: the run from the capture's
    poses (rung ``hull``) and the run from SfM's (rung ``sfm``), each in its own results folder."""
    tag = Path(next(r.results for r in RUNS if r.name == run)).parent.name
    out = []
    for group, rung in ((1, "hull"), (2, "sfm")):
        folder = workflow_run_name(tag, rung, **_COW_RUNS)
        poses = ("known poses", "SfM")[group - 1]
        out += [Figure(f"{run}, {poses}: η (%)", run, _ETA, r"([\d.]+) / ([\d.]+) %",
                       "metrics:eta_per_material.mean_error_pct", "eta_pct", group=group, folder=folder),
                Figure(f"{run}, {poses}: normals median (°)", run, "normals (median)", r"([\d.]+)° / ([\d.]+)°",
                       "metrics:normal_error_deg.all.median", "normal_deg", group=group, folder=folder),
                Figure(f"{run}, {poses}: held-out PSNR (dB)", run, "held-out PSNR", r"([\d.]+) / ([\d.]+) dB",
                       "metrics:psnr_held_out.mean_db", "psnr_db", group=group, folder=folder),
                Figure(f"{run}, {poses}: Chamfer (mm)", run, "surface", r"Chamfer ([\d.]+) / ([\d.]+) mm",
                       "metrics:geometry.chamfer_mm", "chamfer_mm", group=group, folder=folder)]
    return tuple(out)


# The demo's η per material: its true materials' labels are 0 plumage (η 1.48), 1 facial disc (1.36), 2 eyes and
# beak (1.62) (sellip.capture.scenes), the README's order.
FIGURES: tuple[Figure, ...] = (
    _vertices("demo"),
    *(Figure(f"demo: η {material} (%)", "demo", _ETA, r"([\d.]+) / ([\d.]+) / ([\d.]+) %",
             f"metrics:eta_per_material.materials.{label}.error_pct", kind, group=label + 1)
      for label, material, kind in ((0, "plumage", "eta_pct"), (1, "disc", "eta_pct"), (2, "eyes", "eta_small_pct"))),
    Figure("demo: materials at every iteration", "demo", _ETA, r"(\w+) materials at every iteration", "clusters:k",
           "materials"),
    *_headline("demo"),
    *_sphere("sphere_ior_scale"),
    *_sphere("sphere_ior_mitsuba"),
    *_known_and_sfm("cow_painted_sellip"),
    *_known_and_sfm("cow_painted_mitsuba"),
)

# Documented figures without a registered command, and why (docs/benchmarks.md, "Paper figures by one command").
NOT_COVERED: dict[str, str] = {
    "README: the stability suite's row": "a pointer to docs/benchmarks.md, not a number",
    "README: views, sizes, iterations and run times in a row's first cell":
        "settings of the recorded command, or the machine's time (not a figure of the method)",
    "docs/benchmarks.md: every table":
        "each table names its command; none is registered yet (the sweep and the stability suite take 50-60 min "
        "on 2 cores, their tables are written by the commands themselves)",
}

_WORDS = {"one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8, "nine": 9}


def run_named(name: str) -> Run:
    for run in RUNS:
        if run.name == name:
            return run
    raise FiguresError(f"no registered run {name!r}; the runs are {', '.join(r.name for r in RUNS)}")


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def table_row(text: str, command: str, doc: str = README) -> tuple[int, dict[str, str]]:
    """(line number, {column header: cell}) of the one markdown table row of ``text`` whose first cell holds
    ```command``` (in backticks); the header is the table's first line."""
    lines = text.splitlines()
    hits = [i for i, line in enumerate(lines)
            if line.lstrip().startswith("|") and f"`{command}`" in _cells(line)[0]]
    if len(hits) != 1:
        raise FiguresError(f"{doc}: {len(hits)} table rows have `{command}` in their first cell, expected one: the row "
                           "of this command was reworded or duplicated; keep the command in backticks in the row's "
                           "first cell, or change sellip.bench.figures.RUNS with it")
    start = hits[0]
    while start > 0 and lines[start - 1].lstrip().startswith("|"):
        start -= 1
    header, row = _cells(lines[start]), _cells(lines[hits[0]])
    if len(header) != len(row):
        raise FiguresError(f"{doc}:{hits[0] + 1}: the row has {len(row)} cells and its table's header "
                           f"(line {start + 1}) {len(header)}")
    return hits[0] + 1, dict(zip(header, row))


def _number(text: str) -> float:
    word = text.lower()
    if word in _WORDS:
        return float(_WORDS[word])
    return float(text)


def documented(figure: Figure, text: str) -> float:
    """``figure``'s documented value in ``text`` (its document's contents), in the run's units."""
    run = run_named(figure.run)
    line, row = table_row(text, run.command, figure.doc)
    if figure.column not in row:
        raise FiguresError(f"{figure.doc}:{line}: no column {figure.column!r} in the table of `{run.command}`; the "
                           f"columns are {list(row)}")
    cell = row[figure.column]
    found = re.search(figure.pattern, cell)
    if found is None:
        raise FiguresError(f"{figure.doc}:{line}: column {figure.column!r} reads {cell!r}, which does not match "
                           f"{figure.pattern!r} ({figure.name}); write the number as before or change its Figure in "
                           "sellip.bench.figures.FIGURES")
    try:
        return _number(found.group(figure.group)) * figure.scale
    except ValueError:
        raise FiguresError(f"{figure.doc}:{line}: {found.group(figure.group)!r} in column {figure.column!r} is not "
                           f"a number ({figure.name})") from None


def _dig(record, path: str, where: Path):
    value = record
    for key in path.split("."):
        if isinstance(value, list) and key.isdigit() and int(key) < len(value):
            value = value[int(key)]
        elif isinstance(value, dict) and key in value:
            value = value[key]
        else:
            raise FiguresError(f"{where}: no key {path!r} (stopped at {key!r}); was the run made by another version?")
    return value


def measured(figure: Figure, results: Path) -> list[float]:
    """``figure``'s measured value(s) in the finished run under ``results`` (the results root): one value, or one
    per iteration (``clusters:k``). Raises :class:`FiguresError` naming the missing file and the command."""
    run = run_named(figure.run)
    folder = Path(results) / run.results / figure.folder
    kind, _, path = figure.source.partition(":")
    if kind == "metrics":
        metrics = folder / "metrics.json"
        if not metrics.is_file():
            raise FiguresError(f"{metrics}: missing; run `{run.command}` first (about {run.minutes} min on 2 cores)")
        value = _dig(json.loads(metrics.read_text()), path, metrics)
        if value is None:
            raise FiguresError(f"{metrics}: {path} is null (the run has no such figure)")
        return [float(value)]
    if kind == "clusters":
        from sellip.fit.lobe_store import pass_clusters

        records = pass_clusters(folder)
        if not records:
            raise FiguresError(f"{folder}/iter/*/clusters/clusters.json: none; run `{run.command}` first")
        return [float(_dig(record, path, p)) for p, record in records]
    raise FiguresError(f"{figure.name}: unknown source {figure.source!r} (metrics:<key path> or clusters:<key>)")


@dataclass(frozen=True)
class Comparison:
    """One figure checked: documented against measured, ``status`` PASS, FAIL or MISSING (``note`` says why)."""

    figure: Figure
    documented: float
    measured: tuple[float, ...]
    tolerance: float
    status: str
    note: str = ""

    @property
    def difference(self) -> float | None:
        """The measured value farthest from the documented one, minus it."""
        if not self.measured:
            return None
        return max((m - self.documented for m in self.measured), key=abs)


def tolerance_of(figure: Figure, value: float) -> float:
    """``figure``'s absolute tolerance around its documented ``value``."""
    amount, unit, _ = TOLERANCES[figure.kind]
    return amount * abs(value) / 100 if unit == "%" else amount


def compare(figure: Figure, text: str, results: Path) -> Comparison:
    """``figure`` read from its document's ``text`` and from the run under ``results``, within its tolerance."""
    value = documented(figure, text)
    tolerance = tolerance_of(figure, value)
    try:
        values = measured(figure, results)
    except FiguresError as error:
        return Comparison(figure, value, (), tolerance, "MISSING", str(error))
    ok = all(abs(m - value) <= tolerance + 1e-9 for m in values)
    return Comparison(figure, value, tuple(values), tolerance, "PASS" if ok else "FAIL")


def select(only: list[str] | None = None, size: str = "all") -> tuple[Run, ...]:
    """The runs named in ``only`` (all when None), of ``size`` (``small``: the small ones; ``all``)."""
    if size not in ("small", "all"):
        raise FiguresError(f"size {size!r}: expected small or all")
    names = [run.name for run in RUNS]
    for name in only or []:
        if name not in names:
            raise FiguresError(f"no registered run {name!r}; the runs are {', '.join(names)}")
    return tuple(run for run in RUNS if (only is None or run.name in only) and size in ("all", run.size))


def tolerance_line() -> str:
    """The README's sentence of the tolerances (it must appear as it is, line breaks aside:
    :func:`document_problems`)."""
    def amount(value: float, unit: str) -> str:
        unit = "point" if unit == "points" and value == 1 else unit
        return "exact" if value == 0 else f"±{value:g}" + ("" if unit in ("°", "") else " ") + unit

    parts = [f"{what} {amount(value, unit)}" for value, unit, what in TOLERANCES.values()]
    return "Tolerances of `sellip figures check`: " + "; ".join(parts) + "."


def document_problems(root: Path) -> list[str]:
    """What is wrong in the documents under ``root``: the tolerance line missing from the README, a row or cell that
    no longer parses (each figure is read once)."""
    problems = []
    readme = (Path(root) / README).read_text()
    if " ".join(tolerance_line().split()) not in " ".join(readme.split()):
        problems.append(f"{README}: the tolerance sentence is not there (line breaks aside); it must read: "
                        f"{tolerance_line()}")
    for figure in FIGURES:
        try:
            documented(figure, (Path(root) / figure.doc).read_text())
        except FiguresError as error:
            problems.append(str(error))
    return problems


def check(root: Path, results: Path, runs: tuple[Run, ...]) -> list[Comparison]:
    """Every registered figure of ``runs``: documented (documents under ``root``) against measured (runs under
    ``results``)."""
    names = {run.name for run in runs}
    texts: dict[str, str] = {}
    out = []
    for figure in FIGURES:
        if figure.run in names:
            text = texts.setdefault(figure.doc, (Path(root) / figure.doc).read_text())
            out.append(compare(figure, text, results))
    return out


def _shown(value: float) -> str:
    return f"{value:.6g}"


def report_lines(comparisons: list[Comparison]) -> list[str]:
    """A table of the comparisons: figure, documented, measured, tolerance, difference, status (and why)."""
    rows = [("figure", "documented", "measured", "tolerance", "difference", "status")]
    for c in comparisons:
        difference = c.difference
        rows.append((c.figure.name, _shown(c.documented), ", ".join(_shown(m) for m in c.measured) or "-",
                     f"±{c.tolerance:g}", "-" if difference is None else f"{difference:+.6g}",
                     c.status + (f": {c.note}" if c.note else "")))
    widths = [max(len(row[i]) for row in rows) for i in range(5)]
    return ["  ".join(cell.ljust(width) for cell, width in zip(row[:5], widths)) + "  " + row[5] for row in rows]


def provenance(root: Path, runs: tuple[Run, ...]) -> dict:
    """What a check ran on: the checkout's commit, the versions of the packages that compute the figures, the
    machine, and each run's command and seeds."""
    import importlib.metadata
    import os
    import platform
    import subprocess

    def version(package: str) -> str | None:
        try:
            return importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            return None

    git = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True)
    return {"commit": git.stdout.strip() or None,
            "modified": bool(dirty.stdout.strip()) if git.returncode == 0 else None,
            "versions": {p: version(p) for p in ("sellip", "jax", "jaxlib", "numpy", "scipy", "scikit-learn",
                                                  "snakemake", "open3d", "pycolmap")},
            "python": platform.python_version(), "machine": platform.machine(), "processor": platform.processor(),
            "cpus": os.cpu_count(),
            "runs": {run.name: {"command": run.command, "results": run.results, "seeds": run.seeds} for run in runs}}


def record(comparisons: list[Comparison], root: Path, runs: tuple[Run, ...]) -> dict:
    """The check as a JSON-able record: :func:`provenance` and each comparison."""
    return {**provenance(root, runs), "tolerances": {k: v[0] for k, v in TOLERANCES.items()},
            "figures": [{"figure": c.figure.name, "run": c.figure.run, "doc": c.figure.doc, "source": c.figure.source,
                         "documented": c.documented, "measured": list(c.measured), "tolerance": c.tolerance,
                         "difference": c.difference, "status": c.status, "note": c.note} for c in comparisons]}
