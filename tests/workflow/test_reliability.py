"""Never a stale or misplaced result (issue #38), on the real workflow: every file and config value a stage reads is
an input of the DAG (an edit re-runs exactly the jobs that depend on it, `snakemake -n`); paths with spaces and
non-ASCII letters; results names that are not one folder are refused; nested `--config` overrides keep their types;
a failing job's message and the run's warnings reach the console.

The capture is the tiny sphere, 8 views of 128x96 raw pixels, in a folder whose name has a space and an 'é', one raw
frame missing (run with `ingest.bad_frames: skip`) and its ground-truth mesh given as a scan (`init.mode: mesh`);
the run goes as far as the initial mesh (about 20 s on 2 cores)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from sellip import workflow_support

pytestmark = pytest.mark.slow  # the whole module: `make test-fast` leaves it out

REPO = Path(__file__).resolve().parents[2]
NAME = "tïny run"
INGEST = {"linearize_frames", "merge_hdr", "run_sfm", "init_mesh"}
"""The jobs up to the initial mesh."""
OLD = 946684800  # 2000-01-01: an mtime older than every output, so that only a changed input set can re-run a job


def snakemake(workdir: Path, capture: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    """`snakemake` on the repository's workflow in ``workdir`` with the test's capture and settings."""
    command, env = snakemake_command(workdir, capture, *args)
    result = subprocess.run(command, capture_output=True, text=True, env=env, timeout=900, check=False)
    if check and result.returncode != 0:
        raise AssertionError(f"snakemake {' '.join(args)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}")
    return result


def snakemake_command(workdir: Path, capture: Path, *args: str) -> tuple[list[str], dict]:
    """The command line and environment of :func:`snakemake`."""
    override = workdir / "over ride.yaml"
    override.write_text(yaml.safe_dump({
        "capture": str(capture), "name": NAME,
        "ingest": {"bad_frames": "skip"},
        "init": {"mode": "mesh", "mesh_path": "scan.ply", "max_vertices": 600},
    }, allow_unicode=True), encoding="utf-8")
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), "--cores", "2", *args]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO / "src"), os.environ.get("PYTHONPATH")]))}
    return command, env


def planned(result: subprocess.CompletedProcess) -> set[str]:
    """The rules of the jobs a dry run would run (its 'Job stats' table); empty for 'Nothing to be done'."""
    text = result.stdout + result.stderr
    if "Nothing to be done" in text:
        return set()
    table = text.split("Job stats:")[1]
    return {m.group(1) for m in re.finditer(r"^(\w+)\s+\d+\s*$", table, re.MULTILINE) if m.group(1) != "total"}


def planned_counts(result: subprocess.CompletedProcess) -> dict[str, int]:
    """Jobs per rule of a dry run's 'Job stats' table."""
    table = (result.stdout + result.stderr).split("Job stats:")[1]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)\s*$", table, re.MULTILINE)}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A finished run up to the initial mesh, in a work folder and capture folder with spaces and non-ASCII
    letters; one raw frame was missing (skipped) during it and sits beside the capture."""
    from sellip.capture.synthetic import synthesize_capture

    workdir = tmp_path_factory.mktemp("reliability") / "work dir ø"
    capture = synthesize_capture("tiny", workdir / "my capture é", views=8, width=128, height=96, seed=3,
                                 supersample=1, progress=False)
    shutil.copy(capture / "ground_truth" / "model.ply", capture / "scan.ply")
    missing = capture / "raw" / "v003_f1.dng"
    aside = workdir / "v003_f1.dng"
    shutil.move(missing, aside)
    target = f"results/{NAME}/mesh/init.ply"
    first = snakemake(workdir, capture, target)
    assert (workdir / target).is_file(), first.stderr[-3000:]
    return {"workdir": workdir, "capture": capture, "target": target, "missing": missing, "aside": aside,
            "log": first.stdout + first.stderr}


def dry_run(run, *config: str) -> set[str]:
    args = (run["target"], "-n") + (("--config", *config) if config else ())
    return planned(snakemake(run["workdir"], run["capture"], *args))


def test_an_unchanged_capture_needs_nothing(run):
    assert dry_run(run) == set()


@pytest.mark.parametrize("edit, expected", [
    ("raw/v000_f0.dng", INGEST),           # a raw frame replaced (a good file for a truncated one)
    ("frames.csv", INGEST),
    ("capture.yaml", INGEST),
    ("poses.csv", {"run_sfm", "init_mesh"}),  # a pose corrected
    ("scan.ply", {"init_mesh"}),           # the scan of init.mode mesh edited in place
])
def test_an_edited_capture_file_reruns_exactly_what_reads_it(run, edit, expected):
    """New content (Snakemake also compares checksums: a file touched but unchanged re-runs nothing); the original
    put back (new mtime, old content), nothing is to be done."""
    path = run["capture"] / edit
    original = path.read_bytes()
    path.write_bytes(original + (b"\n" if path.suffix in (".csv", ".yaml") else b"\0"))
    try:
        assert dry_run(run) == expected
    finally:
        path.write_bytes(original)
    assert dry_run(run) == set()


@pytest.mark.parametrize("edit, expected", [
    ("raw/v000_f0.dng", INGEST),
    ("capture.yaml", INGEST),
    ("poses.csv", {"run_sfm", "init_mesh"}),
    ("scan.ply", {"init_mesh"}),
])
def test_a_changed_file_older_than_the_outputs_reruns_what_reads_it(run, edit, expected):
    """Content changed but the file's mtime set back before the outputs (what `cp -p`, `rsync -a` or a restored
    backup does): the content digest in the rule's params re-runs it (before: "Nothing to be done"). The original
    put back, with the same old mtime, needs nothing again."""
    path = run["capture"] / edit
    original, stat = path.read_bytes(), path.stat()
    changed = bytearray(original)
    changed[-2] = (changed[-2] + 1) % 256 if path.suffix not in (".csv", ".yaml") else changed[-2]
    path.write_bytes(bytes(changed) if path.suffix not in (".csv", ".yaml") else original + b"\n")
    os.utime(path, ns=(OLD * 10**9, OLD * 10**9))
    try:
        assert dry_run(run) == expected
    finally:
        path.write_bytes(original)
        os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert dry_run(run) == set()


@pytest.mark.parametrize("edit", ["raw/v000_f0.dng", "raw/v005_f2.dng", "scan.ply", "poses.csv", "capture.yaml"])
def test_a_touched_but_unchanged_file_reruns_nothing(run, edit):
    """A newer mtime, the same content: nothing to be done, for files of any size (the raw frames and the scan are
    tracked by their content digest only; Snakemake's own checksum covers only inputs under 1 MB)."""
    path = run["capture"] / edit
    path.touch()
    assert dry_run(run) == set()


def test_content_digests_are_read_once_and_follow_the_content(tmp_path):
    """ContentDigests: a digest per file list that changes with content, name, or a file added or removed, not
    with the mtime; each file read once while its stat is the cached one (also from a new process's cache)."""
    files = [tmp_path / "a.dng", tmp_path / "b.dng"]
    files[0].write_bytes(b"A" * 5000)
    files[1].write_bytes(b"B" * 7000)
    cache = tmp_path / "cache" / "digests.json"
    digests = workflow_support.ContentDigests(cache)
    first = digests.digest(files, tmp_path)
    assert first.startswith("2 file(s), blake2b ") and digests.computed == 2 and cache.is_file()
    assert digests.digest(files, tmp_path) == first and digests.computed == 2            # cached
    again = workflow_support.ContentDigests(cache)
    assert again.digest(files, tmp_path) == first and again.computed == 0                 # the cache file
    os.utime(files[0], (OLD, OLD))
    assert again.digest(files, tmp_path) == first and again.computed == 1                 # read again, same digest
    files[0].write_bytes(b"A" * 4999 + b"a")
    os.utime(files[0], (OLD, OLD))
    changed = again.digest(files, tmp_path)
    assert changed != first and again.computed == 2                                       # same size and mtime
    assert again.digest(files[:1], tmp_path) != changed                                   # a file removed
    assert again.digest([*files, tmp_path / "c.dng"], tmp_path).startswith("3 file(s)")   # missing counts
    assert again.digest([], tmp_path) == ""
    cache.write_text("not json")
    assert workflow_support.ContentDigests(cache).digest(files, tmp_path) == changed     # a broken cache: re-read


def test_a_frame_that_was_skipped_and_is_now_there_reruns_ingest(run):
    """The frame missing during the run (left out with a warning) is put back with an old mtime: the input set
    changed, so ingest and all that follows run again; taken away again, nothing is to be done."""
    shutil.copy2(run["aside"], run["missing"])
    os.utime(run["missing"], (OLD, OLD))
    try:
        assert dry_run(run) == INGEST
    finally:
        run["missing"].unlink()
    assert dry_run(run) == set()


def test_a_removed_poses_csv_reruns_the_poses(run):
    poses = run["capture"] / "poses.csv"
    aside = run["workdir"] / "poses.csv"
    shutil.move(poses, aside)
    try:
        assert dry_run(run) == {"run_sfm", "init_mesh"}
    finally:
        shutil.move(aside, poses)
    assert dry_run(run) == set()


def test_a_changed_config_value_reruns_exactly_the_rules_that_use_it(run):
    """Nested overrides of each type (item 6) re-run the rules whose params hold them."""
    assert dry_run(run, "init={max_vertices: 700}") == {"init_mesh"}            # integer
    assert dry_run(run, "silhouette={threshold: 0.05}") == {"run_sfm", "init_mesh"}  # number (a record's setting)
    assert dry_run(run, "ingest={saturation: 0.9}") == INGEST                    # number, first stage
    assert dry_run(run, "sfm={refine_intrinsics: true}") == {"run_sfm", "init_mesh"}  # boolean
    assert dry_run(run, "init={max_vertices: 600}") == set()                    # the run's own value


def test_no_shell_command_reads_config_directly():
    """Config values reach a command only through `params:` (whose changes Snakemake's default rerun trigger sees),
    never formatted into the shell text, where a change would go unnoticed."""
    for smk in sorted((REPO / "workflow" / "rules").glob("*.smk")):
        text = smk.read_text()
        for block in re.findall(r"^    shell:\n((?:        .*\n?)+)", text, re.MULTILINE):
            assert "config" not in block, f"{smk.name}: a shell command reads config directly:\n{block}"


def test_every_path_in_a_shell_command_is_quoted():
    """{input}, {output}, {log} and the capture path are shell-quoted (`:q`): a space cannot split them."""
    for smk in sorted((REPO / "workflow" / "rules").glob("*.smk")):
        text = smk.read_text()
        for block in re.findall(r"^    shell:\n((?:        .*\n?)+)", text, re.MULTILINE):
            unquoted = re.findall(r"\{(?:input|output|log|params\.capture)(?:\.\w+)?\}", block)
            assert not unquoted, f"{smk.name}: unquoted {unquoted}"


def test_the_run_with_spaces_and_non_ascii_wrote_its_results(run):
    results = run["workdir"] / "results" / NAME
    assert (results / "mesh" / "init.ply").is_file() and (results / "cameras.csv").is_file()
    assert "unrecognized arguments" not in run["log"]


def test_warnings_reach_the_console_at_the_end(run):
    """The skipped frame's warning, from the linearize log, is in the summary printed at the end of the run."""
    assert "sellip: " in run["log"] and "warning(s)" in run["log"]
    assert "v003_f1" in run["log"].split("warning(s)")[1]


@pytest.mark.parametrize("name", ["..", ".", "a/b", "../up", "", "-n"])
def test_a_results_name_that_is_not_one_folder_is_refused(tmp_path, name):
    result = snakemake(tmp_path, tmp_path / "none", "-n", "--config", f"name={name}", check=False)
    assert result.returncode != 0
    assert "is not a usable results name" in result.stderr + result.stdout
    assert not (tmp_path / "hdr.zarr").exists() and not (tmp_path / "results").exists()


@pytest.mark.parametrize("name", ["owl", "owl 2", "eulenspiegel-ü", "v1.2"])
def test_check_results_name_accepts_plain_folder_names(name):
    assert workflow_support.check_results_name(name) == name


@pytest.mark.parametrize("name", ["..", ".", "a/b", "a\\b", "", "x\ny", " x", "-x"])
def test_check_results_name_refuses_others(name):
    with pytest.raises(ValueError, match="not a usable results name"):
        workflow_support.check_results_name(name)


def test_nested_overrides_take_the_schema_types():
    """Snakemake reads `--config 'augment={min_coherence: 0}'` with YAML's BaseLoader: every nested value a
    string. coerce_to_schema gives each the schema's type, and leaves strings where strings are expected."""
    schema = workflow_support.load_yaml(REPO / "config" / "config.schema.yaml")
    given = {"augment": {"min_coherence": "0", "enabled": ["true", "false"]},
             "observe": {"max_views": "null", "min_cos": "-0.5", "missing_poses": "skip"},
             "fit": {"settings": {"lambda_d": ["1", "2.5"], "sigma_ss_fixed": "0.9", "max_iterations": "7"},
                     "dtype": "float64"},
             "refine_geometry": {"smoothness": "0.02"},
             "sfm": {"refine_intrinsics": "false"}, "name": "007", "capture": "123"}
    out = workflow_support.coerce_to_schema(given, schema)
    assert out["augment"] == {"min_coherence": 0, "enabled": [True, False]}
    assert out["observe"] == {"max_views": None, "min_cos": -0.5, "missing_poses": "skip"}
    assert out["fit"]["settings"] == {"lambda_d": [1, 2.5], "sigma_ss_fixed": 0.9, "max_iterations": 7}
    assert out["fit"]["dtype"] == "float64" and out["refine_geometry"] == {"smoothness": 0.02}
    assert out["sfm"]["refine_intrinsics"] is False and out["name"] == "007" and out["capture"] == "123"
    assert given["augment"]["min_coherence"] == "0"  # the input is left as it was
    assert workflow_support.coerce_to_schema({"capture": None}, schema) == {"capture": ""}  # `--config capture=`
    # A value of the wrong kind stays a string, for the schema to report.
    assert workflow_support.coerce_to_schema({"augment": {"k_max": "many"}}, schema)["augment"]["k_max"] == "many"


CONFIG_TYPOS = [
    # (--config value, the message that names the key and what to do)
    ("iteratons=2", "config: unknown setting 'iteratons'; did you mean 'iterations'?"),
    ("fit={shard: 3}", "config: unknown setting 'fit.shard'; did you mean 'fit.shards'?"),
    ("fit={settings: {min_veiws: 3}}", "config: unknown setting 'fit.settings.min_veiws'; did you mean "
                                        "'fit.settings.min_views'?"),
    ("refine_poses={blur: [1, 0]}", "config: unknown setting 'refine_poses.blur'; did you mean "
                                    "'refine_poses.blur_px'?"),
    ("sfm={mask_threshold: 0.05}", "config: 'sfm.mask_threshold' was renamed 'silhouette.threshold': set "
                                   "silhouette.threshold instead"),
    ("model_selection={sigma_ss_fixed: 1.0}", "config: 'model_selection.sigma_ss_fixed' was renamed "
                                              "'model_selection.model2_sigma_ss'"),
]


@pytest.mark.parametrize("override, message", CONFIG_TYPOS)
def test_an_unknown_or_renamed_config_key_is_named_with_the_valid_one(override, message):
    """Every config key, at every level, must be a setting (the schema's additionalProperties: false): a typo stops
    the workflow naming the key and the nearest valid one, a renamed key naming its new name."""
    schema = workflow_support.load_yaml(REPO / "config" / "config.schema.yaml")
    key, _, value = override.partition("=")
    config = {**workflow_support.load_yaml(REPO / "config" / "config.yaml"), key: yaml.safe_load(value)}
    with pytest.raises(workflow_support.ConfigKeyError) as error:
        workflow_support.check_config_keys(config, schema)
    assert str(error.value).startswith(message), str(error.value)


@pytest.mark.parametrize("override, message", CONFIG_TYPOS[:2])
def test_a_config_typo_stops_the_workflow_before_any_job(tmp_path, override, message):
    """The two typos of the bad-input table through Snakemake itself: an error, no job, nothing written."""
    result = snakemake(tmp_path, tmp_path / "none", "-n", "--config", "capture=", override, check=False)
    assert result.returncode != 0
    assert message in result.stderr + result.stdout, (result.stderr + result.stdout)[-3000:]
    assert not (tmp_path / "results").exists()


def test_every_config_section_rejects_unknown_keys():
    """additionalProperties: false on every object of the schema (demo.overrides, which holds other settings and is
    checked once merged, excepted)."""
    schema = workflow_support.load_yaml(REPO / "config" / "config.schema.yaml")
    open_objects = []

    def visit(node, path):
        if isinstance(node, dict):
            if node.get("type") == "object" and node.get("additionalProperties") is not False:
                open_objects.append(path)
            for key, value in (node.get("properties") or {}).items():
                visit(value, f"{path}.{key}" if path else key)

    visit(schema, "")
    assert open_objects == ["demo.overrides"]


def test_nested_overrides_of_each_type_pass_the_workflow(tmp_path):
    """`--config` with a nested number, integer, boolean and null: the dry run plans them (the shell shows them)."""
    result = snakemake(tmp_path, tmp_path / "none", "-n", "-p", "--config", "capture=", "name=demo",
                       "augment={min_coherence: 0, k_max: 3}", "sfm={refine_intrinsics: true}",
                       "observe={max_views: null}", "init={mode: hull}", "fit={shards: 3}", check=False)
    text = result.stdout + result.stderr
    assert result.returncode == 0, text[-3000:]
    jobs = planned_counts(result)
    assert jobs["fit_pbrdf"] == 3 * jobs["gather_fit"]  # three shards per pass
    assert """--augment-settings '{"k_max": 3, "min_coherence": 0}'""" in text and '"refine_intrinsics": true' in text
    assert '"max_views": null' in text  # null: every view (the record's declared default too)


def test_the_fit_shards_are_raised_to_what_the_jobs_memory_holds(tmp_path):
    """fit.shards 2 at a fit.mem_mb that two shards of the vertex budget overrun: the plan (before any job) runs
    three, the count sellip.fit.shard_plan's memory model says fits, and says why; --set-scatter still sets it."""
    from sellip.fit.shard_plan import SHARD_MEMORY, largest_shard

    vertices, views, chunk = 60_000, 32, 8192  # the demo: 36 views, 4 held out; the fit's chunk_size
    mem_mb = int(SHARD_MEMORY.bytes(largest_shard(vertices, 4096, 3), views, chunk) / 1e6) + 1
    assert SHARD_MEMORY.bytes(largest_shard(vertices, 4096, 2), views, chunk) > mem_mb * 1e6
    result = snakemake(tmp_path, tmp_path / "none", "-n", "--config", "capture=", "name=demo",
                       f"init={{mode: hull, max_vertices: {vertices}}}", f"fit={{mem_mb: {mem_mb}}}", check=False)
    text = result.stdout + result.stderr
    assert result.returncode == 0, text[-3000:]
    jobs = planned_counts(result)
    assert jobs["fit_pbrdf"] == 3 * jobs["gather_fit"], text[-3000:]
    assert f"fit.shards 2 raised to 3: {vertices:,} vertices (init.max_vertices) of {views} views" in text
    result = snakemake(tmp_path, tmp_path / "none", "-n", "--config", "capture=", "name=demo",
                       f"init={{mode: hull, max_vertices: {vertices}}}", f"fit={{mem_mb: {mem_mb}}}",
                       "--set-scatter", "fit=5", check=False)
    jobs = planned_counts(result)
    assert jobs["fit_pbrdf"] == 5 * jobs["gather_fit"], (result.stdout + result.stderr)[-3000:]


def test_the_gpu_profile_gives_the_fit_shards_and_only_them_the_gpu(tmp_path):
    """workflow/profiles/gpu (docs/speed.md, "On a GPU"): a dry run plans every fit shard with resource gpu=1 and no
    other job with a GPU; the machine's limit of one GPU is the profile's."""
    result = snakemake(tmp_path, tmp_path / "none", "-n", "--workflow-profile", str(REPO / "workflow/profiles/gpu"),
                       "--config", "capture=", "name=demo", "init={mode: hull}", check=False)
    text = result.stdout + result.stderr
    assert result.returncode == 0, text[-3000:]
    jobs = re.findall(r"^rule (\w+):.*?^\s+resources: ([^\n]*)$", text, re.MULTILINE | re.DOTALL)
    gpu = {rule for rule, resources in jobs if "gpu=1" in resources}
    assert gpu == {"fit_pbrdf"}, jobs[:5]
    assert sum(rule == "fit_pbrdf" for rule, _ in jobs) == planned_counts(result)["fit_pbrdf"] > 0
    profile = yaml.safe_load((REPO / "workflow/profiles/gpu/config.yaml").read_text())
    assert profile["resources"] == ["gpu=1"] and profile["set-resources"]["fit_pbrdf"]["gpu"] == 1


def test_a_failed_jobs_message_reaches_the_console(run):
    """With `ingest.bad_frames: error` the missing frame stops linearize: the console shows the stage's own message
    (file, frames.csv row) and where the full log is, not only Snakemake's 'check log file(s)'."""
    result = snakemake(run["workdir"], run["capture"], f"results/{NAME} strict/hdr.zarr", "--config",
                       f"name={NAME} strict", "ingest={bad_frames: error}", check=False)
    assert result.returncode != 0
    text = result.stdout + result.stderr
    shown = text.split("sellip: rule linearize_frames failed")[1]
    assert f"results/{NAME} strict/logs/linearize_frames.log" in shown.splitlines()[0]
    assert "v003_f1.dng" in shown and "row 10 (line 12)" in shown and "does not exist" in shown
    assert not (run["workdir"] / "results" / f"{NAME} strict" / "hdr.zarr").exists()


def test_failed_job_logs_and_their_error_lines(tmp_path):
    """The parts of the console message, on a Snakemake log and a job log of the formats they have."""
    job_log = tmp_path / "results" / "x" / "logs" / "fit_pbrdf" / "0.log"
    job_log.parent.mkdir(parents=True)
    job_log.write_text("2026-01-01 10:00:00,000 INFO sellip.stages.fit: started\n"
                       "2026-01-01 10:00:01,000 WARNING sellip.stages.fit: 3 vertices without views\n"
                       "2026-01-01 10:00:02,000 ERROR sellip.stages.fit: obs.zarr: shard 2 of 2: out of memory\n")
    snake_log = tmp_path / "snake.log"
    snake_log.write_text("Error in rule fit_pbrdf:\n    message: None\n    jobid: 3\n"
                         "    log: results/x/logs/fit_pbrdf/0.log (check log file(s) for error details)\n"
                         "    shell:\n        sellip fit ...\nShutting down, this might take some time.\n")
    assert workflow_support.failed_job_logs(snake_log) == [("fit_pbrdf", ["results/x/logs/fit_pbrdf/0.log"])]
    shown = workflow_support.format_failures(snake_log, tmp_path)
    assert shown.splitlines()[:2] == ["sellip: rule fit_pbrdf failed (full log: results/x/logs/fit_pbrdf/0.log)",
                                      "  obs.zarr: shard 2 of 2: out of memory"]
    assert "run the same command again" in shown.splitlines()[2]
    assert workflow_support.format_failures(tmp_path / "no such log") == ""
    assert workflow_support.collect_warnings(tmp_path / "results" / "x" / "logs") == [
        ("fit_pbrdf/0.log", "3 vertices without views")]
    # A log without sellip's ERROR lines (a traceback): its last lines.
    job_log.write_text("Traceback (most recent call last):\n  File x\nValueError: bad\n")
    assert workflow_support.error_lines(job_log)[-1] == "ValueError: bad"


def test_camera_distances_are_those_to_the_point_the_cameras_look_at():
    import numpy as np

    from sellip.capture.checks import camera_distances

    rotations, translations = orbit(0.9)
    distances = camera_distances(rotations, translations)
    assert np.median(distances) == pytest.approx(0.9, rel=0.05)
    # The same poses in millimetres: the same distances, times 1000.
    np.testing.assert_allclose(camera_distances(rotations, 1000 * translations), 1000 * distances, rtol=1e-9)


# --------------------------------------------------------------------------- units (item 4)

def orbit(distance_m: float = 0.9, views: int = 12, seed: int = 0):
    """Poses of a handheld orbit about the origin at about ``distance_m``: rotations (V, 3, 3), translations (V, 3)."""
    import numpy as np

    from sellip.capture.scenes import handheld_orbit

    cameras = handheld_orbit(views, 256, 208, np.random.default_rng(seed), distance_m=(distance_m * 0.9,
                                                                                        distance_m * 1.1))
    return np.stack([c.rotation for c in cameras]), np.stack([c.translation for c in cameras])


@pytest.mark.parametrize("scale, distance, expected", [
    (1000.0, 0.9, r"translations look like millimetres.*divide tx, ty, tz by 1000"),
    (100.0, 0.9, r"translations look like centimetres.*divide tx, ty, tz by 100"),
    (1 / 0.0254, 0.9, r"translations look like inches.*by 39.37"),
    (1.0, 900.0, r"scene.distance_m looks like millimetres.*0.9 m would fit"),
    (20.0, 0.9, r"expected translations in metres"),
])
def test_poses_in_other_units_than_scene_distance_are_named(scale, distance, expected):
    from sellip.capture.checks import PoseUnitsError, check_pose_units

    rotations, translations = orbit(0.9)
    with pytest.raises(PoseUnitsError, match=expected) as info:
        check_pose_units(rotations, scale * translations, distance, "cap/poses.csv")
    assert str(info.value).startswith("cap/poses.csv: columns tx, ty, tz: the cameras are a median")


def test_poses_in_metres_pass_also_with_missing_rows():
    import numpy as np

    from sellip.capture.checks import check_pose_units

    rotations, translations = orbit(0.9)
    translations[3] = np.nan
    assert check_pose_units(rotations, translations, 0.9) == pytest.approx(0.9, rel=0.05)
    assert check_pose_units(rotations, translations, 0.5) == pytest.approx(0.9, rel=0.05)  # within 4x: rough
    assert np.isnan(check_pose_units(rotations[:1], translations[:1], 0.9))  # one view: nothing to check


def test_the_sfm_stage_stops_on_poses_in_millimetres(run, tmp_path, caplog):
    """The workflow's poses stage on the run's HDR images with poses.csv in millimetres: exit 1 with the message,
    no cameras.csv. (Before: it ran to the end with a model 1000 times too large.)"""
    import pandas as pd

    from sellip.cli import main

    capture = tmp_path / "mm capture"
    capture.mkdir()
    for name in ("capture.yaml", "frames.csv"):
        shutil.copy(run["capture"] / name, capture / name)
    poses = pd.read_csv(run["capture"] / "poses.csv", dtype={"view_id": str})
    poses[["tx", "ty", "tz"]] *= 1000
    poses.to_csv(capture / "poses.csv", index=False)
    hdr = run["workdir"] / "results" / NAME / "hdr.zarr"
    status = main(["sfm", "--hdr", str(hdr), "--capture", str(capture), "--cameras", str(tmp_path / "cameras.csv"),
                   "--output", str(tmp_path / "sfm"), "--settings", '{"mode": "known"}'])
    assert status == 1 and not (tmp_path / "cameras.csv").exists() and not (tmp_path / "sfm").exists()
    assert "translations look like millimetres" in caplog.text and "poses.csv" in caplog.text


# --------------------------------------------------------------------------- a failed run is visible (issue 52)

def test_stale_model_says_when_the_model_is_an_earlier_runs(tmp_path):
    """stale_model on a results folder: nothing without a record or after a complete run; a failed run that
    started after the model was made names the model out of date with the failed rule and its log; a failed run
    that wrote the model and failed later says the renders are not complete; a later run's model is fine; a
    capture file newer than the model is named."""
    results, capture = tmp_path / "results" / "owl", tmp_path / "capture"
    model = results / workflow_support.MODEL
    model.parent.mkdir(parents=True)
    model.write_text("ply")
    capture.mkdir()
    for name in ("capture.yaml", "frames.csv"):
        (capture / name).write_text("x")
        os.utime(capture / name, (OLD, OLD))
    os.utime(model, (OLD + 100, OLD + 100))
    assert workflow_support.stale_model(results, capture) == []
    snake_log = tmp_path / "snake.log"
    snake_log.write_text("Error in rule merge_hdr:\n    jobid: 2\n    log: results/owl/logs/merge_hdr.log (check log "
                         "file(s) for error details)\n")
    workflow_support.record_run(results, "complete", started=OLD + 50, now=OLD + 200)
    assert workflow_support.stale_model(results, capture) == []
    workflow_support.record_run(results, "failed", snake_log, started=OLD + 150, now=OLD + 200)
    [line] = workflow_support.stale_model(results, capture)
    assert line.startswith(f"{model} (made ") and " is out of date: the last run (started " in line
    assert "failed at rule merge_hdr (log: results/owl/logs/merge_hdr.log)" in line
    assert "those of an earlier run" in line and "run the same command again" in line
    workflow_support.record_run(results, "failed", snake_log, started=OLD + 50, now=OLD + 200)
    [line] = workflow_support.stale_model(results, capture)
    assert "is this run's, but the last run" in line and "after it wrote the model" in line
    workflow_support.record_run(results, "failed", snake_log, started=OLD, now=OLD + 60)
    assert workflow_support.stale_model(results, capture) == []  # the model is a later run's
    (capture / "frames.csv").touch()
    [line] = workflow_support.stale_model(results, capture)
    assert "1 capture file(s) changed after it" in line and str(capture / "frames.csv") in line
    assert workflow_support.stale_model(tmp_path / "no results", capture) == []


def test_process_tree_and_signal_processes_reach_the_grandchild(tmp_path):
    """A job's shell and the command under it (what a SIGTERM to the run must end): both found from the shell's
    pid, both ended; a pid whose start time differs (taken by another process since) is not signalled."""
    import signal
    import time

    shell = subprocess.Popen(["bash", "-c", "set -e; sleep 300; echo"], start_new_session=True)
    try:
        for _ in range(50):
            tree = workflow_support.process_tree(shell.pid)
            if len(tree) == 2:
                break
            time.sleep(0.1)
        assert tree[0] == shell.pid and len(tree) == 2, tree
        sleep = tree[1]
        workflow_support.signal_processes({sleep: -1}, signal.SIGTERM)  # not that process: left alone
        time.sleep(0.2)
        assert shell.poll() is None
        workflow_support.signal_processes({pid: workflow_support.start_time(pid) for pid in tree}, signal.SIGTERM)
        assert shell.wait(timeout=10) == -signal.SIGTERM
        for _ in range(50):
            state = Path(f"/proc/{sleep}/stat").read_text().rsplit(")", 1)[1].split()[0] if Path(
                f"/proc/{sleep}").exists() else "gone"
            if state in ("Z", "gone"):
                break
            time.sleep(0.1)
        assert state in ("Z", "gone")
    finally:
        if shell.poll() is None:
            os.killpg(shell.pid, signal.SIGKILL)


def _session_processes(sid: int) -> list[str]:
    """Command lines of the live (not zombie) processes of session ``sid``."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            found.append(f"{entry}: {cmdline}")
    return found


@pytest.mark.parametrize("target", ["snakemake", "process group"])
def test_sigterm_ends_the_run_and_its_jobs_within_seconds(run, target):
    """SIGTERM during a fit job (the run's first iteration, after its initial mesh), to Snakemake alone (`kill
    PID`) or to its whole process group (a terminal, a batch system): Snakemake and every job process are gone
    within 15 s (before: Snakemake let the running jobs finish, a fit taking minutes, and its handler could
    deadlock on the scheduler's lock with no job left), and the run is recorded as failed."""
    import json
    import signal
    import time

    results = run["workdir"] / "results" / NAME
    command, env = snakemake_command(run["workdir"], run["capture"], f"results/{NAME}/iter/0/fit.zarr",
                                     "--rerun-incomplete")
    console = run["workdir"] / f"sigterm {target}.log"
    with open(console, "w") as sink:
        process = subprocess.Popen(command, env=env, stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        began = time.monotonic()
        while not any(" fit --observations" in line for line in _session_processes(process.pid)):
            assert process.poll() is None, console.read_text()[-3000:]
            assert time.monotonic() - began < 900, "no fit job started"
            time.sleep(0.2)
        time.sleep(2)  # inside the fit
        sent = time.monotonic()
        if target == "snakemake":
            os.kill(process.pid, signal.SIGTERM)
        else:
            os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            pass
        took = time.monotonic() - sent
        left = [line for line in _session_processes(process.pid) if str(process.pid) != line.split(":")[0]]
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    output = console.read_text()
    assert took < 15, f"snakemake took {took:.1f} s to end:\n{output[-3000:]}"
    assert left == [], left
    assert process.returncode != 0
    assert json.loads((results / "last_run.json").read_text())["status"] == "failed", output[-3000:]
