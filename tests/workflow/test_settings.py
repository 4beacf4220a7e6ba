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

from sellip import cli
from sellip.fit.records import FitSettings
from sellip.fit.selection import SelectionSettings
from sellip.geometry.pose_refinement import PoseRefinementSettings
from sellip.geometry.silhouettes import SilhouetteOptions
from sellip.settings import SettingsError, nearest, record_from_mapping, record_schema

REPO = Path(__file__).resolve().parents[2]
RECORDS = (FitSettings, SelectionSettings, PoseRefinementSettings, SilhouetteOptions)


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
    sections = {"fit.settings": (config["fit"]["settings"], FitSettings),
                "augment.settings": (config["augment"]["settings"], FitSettings),
                "final.settings": (config["final"]["settings"], FitSettings),
                "model_selection": (config["model_selection"], SelectionSettings),
                "refine_poses": (config["refine_poses"], PoseRefinementSettings),
                "silhouette": (config["silhouette"], SilhouetteOptions)}
    for section, (values, record) in sections.items():
        for key, value in values.items():
            field = {f.name: f for f in dataclasses.fields(record)}.get(key)
            assert field is None or value != field.default, f"{section}.{key}: the declared default, written again"
    rules = "".join(p.read_text() for p in sorted((REPO / "workflow" / "rules").glob("*.smk")))
    assert "mask_threshold" not in rules and "sigma_ss_fixed" not in rules.replace("`sigma_ss_fixed`", "")


@pytest.mark.parametrize("argv, message", [
    (["fit", "--observations", "o", "--output", "x", "--fixed-sigma-ss", "0.8"], "--fixed-sigma-ss was replaced by "
                                                                                  "--model2-sigma-ss"),
    (["cluster-lobes", "--params", "p", "--observations", "o", "--output", "x", "--set", "lobes=full"],
     "--set was replaced by --settings"),
    (["observe", "--mask-threshold", "0.05"], "--mask-threshold was replaced by --silhouette-settings"),
])
def test_a_replaced_command_line_option_names_its_replacement(argv, message, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err
