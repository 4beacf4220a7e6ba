"""Settings declared once (sellip.settings): the schema's record sections are written from the records, a job's
``--settings`` JSON becomes its record (unknown keys named with the nearest valid one), and no declared default is
written again in the workflow's files."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import pytest

from sellip import cli, workflow_support
from sellip.capture.ingest import IngestSettings
from sellip.capture.synthetic import DemoSettings
from sellip.fit.clusters import AugmentSettings
from sellip.fit.finalize import FinalSettings
from sellip.fit.geometry_jobs import GeometryUpdateSettings
from sellip.fit.observe import ObserveSettings
from sellip.fit.records import FitJobSettings, FitSettings
from sellip.fit.selection import SelectionSettings
from sellip.geometry.hull import InitMeshOptions
from sellip.geometry.pose_refinement import PoseRefinementSettings
from sellip.geometry.sfm import SfmOptions
from sellip.geometry.silhouettes import SilhouetteOptions
from sellip.report.outputs import EvaluateSettings
from sellip.settings import SettingsError, nearest, record_from_mapping, record_schema

REPO = Path(__file__).resolve().parents[2]
RECORDS = (FitSettings, FitJobSettings, AugmentSettings, SelectionSettings, PoseRefinementSettings, SilhouetteOptions,
           IngestSettings, ObserveSettings, SfmOptions, InitMeshOptions, GeometryUpdateSettings, FinalSettings,
           EvaluateSettings, DemoSettings)

# Each config section that is a settings record: (section, record, the `sellip` command whose --settings carries it,
# a misspelt key and the key it means, a value out of its declared range).
SECTIONS = [
    ("ingest", IngestSettings, "linearize", "saturaton", "saturation", {"saturation": 1.5}),
    ("observe", ObserveSettings, "observe", "max_slop", "max_slope", {"view_chunk": 0}),
    ("sfm", SfmOptions, "sfm", "max_feature", "max_features", {"min_registered_fraction": 2.0}),
    ("init", InitMeshOptions, "init-mesh", "max_vertice", "max_vertices", {"poisson_depth": 20}),
    ("refine_geometry", GeometryUpdateSettings, "refine-geometry", "smothness", "smoothness", {"anchor": 0.0}),
    ("refine_poses", PoseRefinementSettings, "refine-poses", "min_motion", "min_motion_px", {"rounds": 0}),
    ("fit", FitJobSettings, "gather-fit", "min_fitted_shares", "min_fitted_share", {"min_fitted_share": 1.5}),
    ("augment", AugmentSettings, "cluster-lobes", "min_coherance", "min_coherence", {"min_coherence": 1.5}),
    ("final", FinalSettings, "finalize", "deviation_suport", "deviation_support", {"deviation_support": 7}),
    ("evaluate", EvaluateSettings, "evaluate", "metric_supersample", "metrics_supersample",
     {"metrics_supersample": 8}),
    ("evaluate", EvaluateSettings, "render-outputs", "render_view", "render_views", {"supersample": 0}),
]
# The argument that carries the section, where it is not --settings.
FLAG = {"gather-fit": "job_settings", "cluster-lobes": "augment_settings"}
REQUIRED = {"linearize": ["--capture", "c", "--output", "o"],
            "observe": ["--mesh", "m", "--cameras", "c", "--hdr", "h", "--capture", "c", "--output", "o"],
            "sfm": ["--hdr", "h", "--capture", "c", "--cameras", "c", "--output", "o"],
            "init-mesh": ["--hdr", "h", "--cameras", "c", "--sfm", "s", "--output", "o"],
            "refine-geometry": ["--params", "p", "--mesh", "m", "--output", "o"],
            "refine-poses": ["--params", "p", "--mesh", "m", "--cameras", "c", "--hdr", "h", "--capture", "c",
                             "--output", "o"],
            "gather-fit": ["--observations", "o", "--shards", "s", "--output", "o"],
            "cluster-lobes": ["--params", "p", "--observations", "o", "--output", "o"],
            "finalize": ["--params", "p", "--mesh", "m", "--output-model", "o", "--output-params", "o"],
            "evaluate": ["--model", "m", "--cameras", "c", "--hdr", "h", "--capture", "c", "--output", "o"],
            "render-outputs": ["--model", "m", "--cameras", "c", "--hdr", "h", "--capture", "c", "--output", "o"]}


def test_the_committed_schema_is_the_one_written_from_the_records():
    """config/config.schema.yaml's x-record sections equal what `sellip config-schema` writes (run it and commit)."""
    assert cli.main(["config-schema", "--schema", str(REPO / "config" / "config.schema.yaml"), "--check"]) == 0


def test_the_schema_check_fails_on_a_stale_section(tmp_path):
    stale = tmp_path / "schema.yaml"
    stale.write_text((REPO / "config" / "config.schema.yaml").read_text().replace(
        "renders per view and refinement", "renders per view"))
    assert cli.main(["config-schema", "--schema", str(stale), "--check"]) == 1
    assert cli.main(["config-schema", "--schema", str(stale)]) == 0
    assert stale.read_text() == (REPO / "config" / "config.schema.yaml").read_text()


@pytest.mark.parametrize("record", RECORDS)
def test_every_declared_setting_has_a_meaning_and_a_schema(record):
    schema = record_schema(record)
    assert schema["additionalProperties"] is False and schema["properties"]
    for name, spec in schema["properties"].items():
        assert spec["description"].strip(), name
        # The description names the declared default (sellip config-schema makes every default discoverable).
        default = getattr(record(), name)
        written = json.dumps(list(default) if isinstance(default, tuple) else default)
        assert spec["description"].endswith(f"(default: {written})"), name
    # A record built from an empty section is the record's defaults.
    assert record_from_mapping(record, {}) == record()


def test_a_section_becomes_its_record_and_is_checked():
    settings = record_from_mapping(PoseRefinementSettings, {"blur_px": [2, 0], "rounds": 3}, "refine_poses")
    assert settings == PoseRefinementSettings(blur_px=(2.0, 0.0), rounds=3)
    with pytest.raises(SettingsError, match=r"unknown setting 'refine_poses.round'; did you mean 'refine_poses.round"):
        record_from_mapping(PoseRefinementSettings, {"round": 3}, "refine_poses")
    with pytest.raises(SettingsError, match=r"'model_selection.model2_sigma_ss': 1.5 is not"):
        record_from_mapping(SelectionSettings, {"model2_sigma_ss": 1.5}, "model_selection")
    with pytest.raises(SettingsError, match=r"'silhouette.threshold': 'high' is not"):
        record_from_mapping(SilhouetteOptions, {"threshold": "high"}, "silhouette")
    # Only the fields declared as settings are settings (SilhouetteOptions' others are the library's own).
    with pytest.raises(SettingsError, match="unknown setting 'silhouette.percentile'"):
        record_from_mapping(SilhouetteOptions, {"percentile": 90}, "silhouette")
    assert nearest("iteratons", ["iterations", "seed"]) == "iterations" and nearest("zzz", ["seed"]) is None


def test_a_jobs_settings_argument_names_an_unknown_key():
    """`sellip refine-poses --settings` is derived from PoseRefinementSettings: a typo is an argument error naming
    it."""
    result = subprocess.run([sys.executable, "-m", "sellip.cli", "refine-poses", "--params", "p", "--mesh", "m",
                             "--cameras", "c", "--hdr", "h", "--capture", "x", "--output", "o",
                             "--settings", json.dumps({"min_motion": 0.5})], capture_output=True, text=True,
                            check=False, timeout=120)
    assert result.returncode == 2
    assert "unknown setting 'refine_poses.min_motion'; did you mean 'refine_poses.min_motion_px'?" in result.stderr


def test_a_declared_default_is_not_written_again_in_the_workflow():
    """config/config.yaml's record sections hold only what the workflow sets differently from the record's
    declaration (each with its reason); the rules read no moved or renamed key."""
    import yaml

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    sections = {"ingest": (config["ingest"], IngestSettings), "observe": (config["observe"], ObserveSettings),
                "sfm": (config["sfm"], SfmOptions), "init": (config["init"], InitMeshOptions),
                "refine_geometry": (config["refine_geometry"], GeometryUpdateSettings),
                "fit": (config["fit"], FitJobSettings), "augment": (config["augment"], AugmentSettings),
                "final": (config["final"], FinalSettings),
                "fit.settings": (config["fit"]["settings"], FitSettings),
                "augment.settings": (config["augment"]["settings"], FitSettings),
                "final.settings": (config["final"]["settings"], FitSettings),
                "model_selection": (config["model_selection"], SelectionSettings),
                "refine_poses": (config["refine_poses"], PoseRefinementSettings),
                "silhouette": (config["silhouette"], SilhouetteOptions),
                "evaluate": (config["evaluate"], EvaluateSettings), "demo": (config["demo"], DemoSettings)}
    for section, (values, record) in sections.items():
        for key, value in values.items():
            field = {f.name: f for f in dataclasses.fields(record) if "setting" in f.metadata}.get(key)
            # A key a user is expected to edit (sfm.mode, init.mode, evaluate.held_out_views, demo.scene: the workflow
            # reads them too) may stay, at the declared default; any other record key in config.yaml would be a
            # second default.
            if (section, key) in (("sfm", "mode"), ("init", "mode"), ("evaluate", "held_out_views"),
                                  ("demo", "scene")):
                value = tuple(value) if isinstance(value, list) else value
                assert value == field.default, f"{section}.{key}: {value!r}, the declaration says {field.default!r}"
            else:
                assert field is None or value != field.default, f"{section}.{key}: the declared default, written again"
    rules = "".join(p.read_text() for p in sorted((REPO / "workflow" / "rules").glob("*.smk")))
    assert "mask_threshold" not in rules and "sigma_ss_fixed" not in rules.replace("`sigma_ss_fixed`", "")


@pytest.mark.parametrize("argv, message", [
    (["fit", "--observations", "o", "--output", "x", "--fixed-sigma-ss", "0.8"], "--fixed-sigma-ss was replaced by "
                                                                                  "--model2-sigma-ss"),
    (["cluster-lobes", "--params", "p", "--observations", "o", "--output", "x", "--set", "lobes=full"],
     "--set was replaced by --settings"),
    (["observe", "--mask-threshold", "0.05"], "--mask-threshold was replaced by --silhouette-settings"),
    (["evaluate", "--held-out", "v001"], "--held-out was replaced by --settings '{\"held_out_views\""),
    (["evaluate", "--supersample", "2"], "--supersample was replaced by --settings '{\"metrics_supersample\""),
    (["render-outputs", "--supersample", "1"], "--supersample was replaced by --settings '{\"supersample\""),
    (["render-outputs", "--views", "v000"], "--views was replaced by --settings '{\"render_views\""),
])
def test_a_replaced_command_line_option_names_its_replacement(argv, message, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err


def _config_with(section: str, values: dict) -> dict:
    import yaml

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config[section] = {**config[section], **values}
    return config


@pytest.mark.parametrize("section, record, command, typo, meant, out_of_range", SECTIONS)
def test_a_section_rejects_a_misspelt_key_and_a_value_out_of_range(section, record, command, typo, meant,
                                                                   out_of_range):
    """Each record section of the config: a misspelt nested key is an error naming the key it means (before any
    job), a value out of the declared range fails the schema's validation, and the job refuses both too."""
    import jsonschema

    schema = workflow_support.load_yaml(REPO / "config" / "config.schema.yaml")
    with pytest.raises(workflow_support.ConfigKeyError, match=rf"unknown setting '{section}.{typo}'; did you mean "
                                                              rf"'{section}.{meant}'\?"):
        workflow_support.check_config_keys(_config_with(section, {typo: 1}), schema)
    workflow_support.check_config_keys(_config_with(section, {meant: getattr(record(), meant)}), schema)
    jsonschema.validate(_config_with(section, {}), schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(_config_with(section, out_of_range), schema)
    with pytest.raises(SettingsError, match=rf"unknown setting '{section}.{typo}'; did you mean '{section}.{meant}'"):
        record_from_mapping(record, {typo: 1}, section)
    with pytest.raises(SettingsError, match=rf"setting '{section}.{next(iter(out_of_range))}'"):
        record_from_mapping(record, out_of_range, section)


@pytest.mark.parametrize("section, record, command, typo, meant, out_of_range", SECTIONS)
def test_a_job_takes_the_declared_defaults_of_the_keys_left_out(section, record, command, typo, meant,
                                                                out_of_range):
    """The job's settings are the record's declaration where the config sets nothing (no default is written in
    the command line's parser), and the keys it is given where it does."""
    from sellip.cli import build_parser

    argv = [command, *REQUIRED[command]]
    parser = build_parser(command)
    name = FLAG.get(command, "settings")
    flag = "--" + name.replace("_", "-")
    assert getattr(parser.parse_args(argv), name) == record()
    given = getattr(parser.parse_args(argv + [flag, json.dumps({meant: getattr(record(), meant)})]), name)
    assert given == record()
    with pytest.raises(SystemExit):
        parser.parse_args(argv + [flag, json.dumps(out_of_range)])


def test_the_demo_jobs_get_only_the_keys_the_config_sets():
    """A dry run of the demo: each converted job's --settings holds only what config.yaml and the demo's overrides
    set (the record's declaration gives the rest)."""
    import os
    import re

    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    done = subprocess.run([sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory",
                           str(REPO), "-n", "-p", "--cores", "1"], capture_output=True, text=True, env=env,
                          timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    commands = [line for line in (done.stdout + done.stderr).splitlines() if "sellip" in line]

    def settings_of(command: str, flag: str = "--settings") -> list[dict]:
        return [json.loads(m) for line in commands if f" {command} --" in line
                for m in re.findall(rf"{flag} '([^']*)'", line)]

    assert settings_of("linearize") == settings_of("merge-hdr") == [{}]
    assert settings_of("sfm") == [{"mode": "known"}]
    assert settings_of("init-mesh") == [{"max_vertices": 6000, "mode": "hull"}]
    observe = settings_of("observe")
    assert len(observe) == 7 and all(s == {"max_slope": 0.4} for s in observe)  # 6 iterations and the final pass
    assert settings_of("refine-geometry") and all(s == {} for s in settings_of("refine-geometry"))
    for command in ("fit", "gather-fit", "cluster-lobes"):
        assert settings_of(command, "--job-settings") and all(s == {} for s in settings_of(command, "--job-settings"))
    assert settings_of("cluster-lobes", "--augment-settings") == [{}] * 7
    assert settings_of("finalize") == [{}]
    # evaluate: the demo's held-out and render views (its overrides); both supersamplings the declared ones
    assert settings_of("evaluate") == [{"held_out_views": ["v004", "v013", "v022", "v031"]}]
    assert settings_of("render-outputs") == [{"render_views": ["v000", "v009", "v018", "v027"]}]
    # demo: config.yaml sets no DemoSettings field but the scene (the wildcard): synth takes its declared defaults
    synth = [line for line in commands if " synth --" in line]
    assert len(synth) == 1 and "--scene demo --out captures/demo  --no-progress" in synth[0]
    # fit.settings sets nothing (min_views 4 is the declared default): the first passes get {}, the others only what
    # augment.settings and final.settings set
    assert {} in settings_of("fit") and not any("min_views" in s for s in settings_of("fit"))


def test_the_demo_section_rejects_a_misspelt_key_and_a_value_out_of_range():
    """config demo (DemoSettings): a misspelt key names the one it means; a width that is no multiple of 4, or below
    24, fails the schema and the record; overrides (a mapping of sections, written by hand) is kept."""
    import jsonschema

    schema = workflow_support.load_yaml(REPO / "config" / "config.schema.yaml")
    with pytest.raises(workflow_support.ConfigKeyError, match=r"unknown setting 'demo.noise_scal'; did you mean "
                                                              r"'demo.noise_scale'\?"):
        workflow_support.check_config_keys(_config_with("demo", {"noise_scal": 1}), schema)
    jsonschema.validate(_config_with("demo", {"width": 64, "renderer": "mitsuba"}), schema)
    jsonschema.validate(_config_with("demo", {"noise_seed": 3}), schema)
    jsonschema.validate(_config_with("demo", {"noise_seed": None}), schema)
    for bad in ({"width": 610}, {"height": 20}, {"views": 2}, {"noise_scale": 0}, {"scene": "teapot"},
                {"noise_seed": -1}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(_config_with("demo", bad), schema)
        with pytest.raises(SettingsError, match=rf"setting 'demo.{next(iter(bad))}'"):
            record_from_mapping(DemoSettings, bad, "demo")
    assert record_from_mapping(DemoSettings, {"width": 64}, "demo") == DemoSettings(width=64)


def test_the_jobs_defaults_are_the_declarations():
    """`sellip synth`'s options, and the library functions behind render-outputs and evaluate, default to the
    declarations: the evaluate job's renders (held-out PSNR) are supersampled 2x2 (metrics_supersample), the output
    renders 1x1 (supersample), as before they were declared."""
    import inspect

    from sellip.capture.synthetic import synthesize_capture
    from sellip.cli import build_parser
    from sellip.report.metrics import evaluate_model, view_psnr
    from sellip.report.outputs import render_outputs

    args = build_parser("synth").parse_args(["synth", "--out", "o"])
    declared = DemoSettings()
    assert (args.scene, args.renderer, args.views, args.width, args.height, args.seed, args.noise_scale,
            args.noise_seed) == (declared.scene, declared.renderer, declared.views, declared.width, declared.height,
                                 declared.seed, declared.noise_scale, declared.noise_seed)
    synth = inspect.signature(synthesize_capture).parameters
    assert all(synth[name].default == getattr(declared, name)
               for name in ("views", "width", "height", "seed", "noise_scale", "renderer", "noise_seed"))
    evaluate = EvaluateSettings()
    assert (evaluate.supersample, evaluate.metrics_supersample, evaluate.geometry_samples) == (1, 2, 50000)
    assert inspect.signature(evaluate_model).parameters["supersample"].default == evaluate.metrics_supersample
    assert inspect.signature(view_psnr).parameters["supersample"].default == evaluate.metrics_supersample
    assert inspect.signature(evaluate_model).parameters["geometry_samples"].default == evaluate.geometry_samples
    assert inspect.signature(render_outputs).parameters["supersample"].default == evaluate.supersample
