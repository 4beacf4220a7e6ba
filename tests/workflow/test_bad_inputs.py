"""The bad-input suite (issue #38, docs/reliability.md): one tiny capture is built once; each case copies it,
breaks one thing, and runs the first stage that reads it (`sellip linearize`, as the rule `linearize_frames` runs
it) through the command line's entry point. Every case must stop with exit status 1 and the message the table in
docs/reliability.md promises (the file, the row / line / key, and what was expected), and leave no output behind;
the `skip` cases run to the end with a warning instead.

The workflow-level cases (stale inputs, paths with spaces, bad results names, nested overrides, the console
message of a failed job, poses in millimetres) are in tests/test_reliability.py."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from sellip.cli import main

HEIGHT, WIDTH = 48, 64


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    """A tiny synthetic capture: 4 views x 3 flash levels of 64x48 raw pixels, with poses.csv."""
    from sellip.capture.synthetic import synthesize_capture

    return synthesize_capture("tiny", tmp_path_factory.mktemp("bad_inputs") / "capture", views=4, width=WIDTH,
                              height=HEIGHT, seed=1, supersample=1, progress=False)


def edit_yaml(edit):
    def apply(capture: Path):
        config = yaml.safe_load((capture / "capture.yaml").read_text())
        edit(config)
        (capture / "capture.yaml").write_text(yaml.safe_dump(config))
    return apply


def edit_csv(name: str, edit):
    def apply(capture: Path):
        table = pd.read_csv(capture / name, dtype=str, keep_default_na=False)
        edit(table).to_csv(capture / name, index=False)
    return apply


def set_cell(name: str, row: int, column: str, value: str):
    def edit(table):
        table.loc[row, column] = value
        return table
    return edit_csv(name, edit)


def write_file(relative: str, data: bytes):
    return lambda capture: (capture / relative).write_bytes(data)


def raw_array(relative: str, array: np.ndarray):
    from sellip.capture.writer import write_raw_file

    return lambda capture: write_raw_file(capture / relative, array, {"black_level": 64, "white_level": 4095})


def truncate(relative: str, keep: int = 1000):
    return lambda capture: (capture / relative).write_bytes((capture / relative).read_bytes()[:keep])


def duplicate_yaml_key(capture: Path):
    """capture.yaml with sensor.width given twice (a corrected value written above the stale one)."""
    text = (capture / "capture.yaml").read_text()
    (capture / "capture.yaml").write_text(text.replace("sensor:\n", f"sensor:\n  width: {WIDTH * 2}\n", 1))


def separator(name: str, sep: str):
    def apply(capture: Path):
        table = pd.read_csv(capture / name, dtype=str, keep_default_na=False)
        table.to_csv(capture / name, index=False, sep=sep)
    return apply


def copy_file(source: str, target: str):
    return lambda capture: shutil.copyfile(capture / source, capture / target)


def every_raw_frame(value: int):
    def apply(capture: Path):
        for name in pd.read_csv(capture / "frames.csv")["file"]:
            raw_array(name, np.full((HEIGHT, WIDTH), value, np.uint16))(capture)
    return apply


def several_frames_problems(table):
    table.loc[1, "flash_level"] = "0"
    table.loc[2, "exposure_s"] = "-1"
    table.loc[3, "frame_id"] = table.loc[0, "frame_id"]
    return table


CASES = {
    # case: (how the capture is broken, the pieces of the message the user sees)
    "capture.yaml missing": (lambda c: (c / "capture.yaml").unlink(), ["capture.yaml", "missing"]),
    "frames.csv missing": (lambda c: (c / "frames.csv").unlink(), ["frames.csv", "missing"]),
    "capture.yaml not YAML": (write_file("capture.yaml", b"sensor: [unclosed\n"), ["capture.yaml", "not valid YAML"]),
    "capture.yaml not a mapping": (write_file("capture.yaml", b"- a list\n"), ["capture.yaml", "expected a mapping"]),
    "required key missing": (edit_yaml(lambda c: c["camera"].pop("fx")), ["key 'camera.fx'", "required"]),
    "unknown key in a section": (edit_yaml(lambda c: c["light"].update(colour=1)),
                                 ["key 'light.colour'", "unknown key"]),
    "unknown top-level key": (edit_yaml(lambda c: c.update(scenes={"distance_m": 0.9})),
                              ["key 'scenes'", "unknown key", "x_..."]),
    "wrong type": (edit_yaml(lambda c: c["sensor"].update(width="wide")), ["key 'sensor.width'", "integer"]),
    "white level above the bit depth": (edit_yaml(lambda c: c["sensor"].update(white_level=65520)),
                                        ["key 'sensor.white_level'", "at most 4095"]),
    "black level at the white level": (edit_yaml(lambda c: c["sensor"].update(black_level=4095)),
                                       ["key 'sensor.black_level'", "below white_level"]),
    "unknown colour layout": (edit_yaml(lambda c: c["sensor"].update(color_layout="RGBW")),
                              ["key 'sensor.color_layout'"]),
    "unknown polarizer layout": (edit_yaml(lambda c: c["sensor"].update(polarizer_layout=[[0, 45], [90, 90]])),
                                 ["key 'sensor.polarizer_layout'"]),
    "width not a multiple of the mosaic": (edit_yaml(lambda c: c["sensor"].update(width=WIDTH + 2)),
                                           ["key 'sensor.width'", "multiple of the mosaic period"]),
    "singular colour matrix": (edit_yaml(lambda c: c["camera"].update(color_matrix=[[1, 0, 0]] * 3)),
                               ["key 'camera.color_matrix'", "invertible"]),
    "focal length in millimetres": (edit_yaml(lambda c: c["camera"].update(fx=2.0)),  # 176 deg over 64 px
                                    ["key 'camera.fx'", "field of view", "wrong units?", "not millimetres"]),
    "non-positive scene distance": (edit_yaml(lambda c: c["scene"].update(distance_m=0)),
                                    ["key 'scene.distance_m'", "> 0"]),
    "duplicate frame_id": (set_cell("frames.csv", 4, "frame_id", "v000_f0"), ["frames.csv", "duplicate frame_id"]),
    "flash level zero": (set_cell("frames.csv", 2, "flash_level", "0"),
                         ["row 2 (line 4), column 'flash_level'", "(0, 1]"]),
    "flash level above one": (set_cell("frames.csv", 5, "flash_level", "1.5"), ["row 5 (line 7)", "(0, 1]"]),
    "exposure not a number": (set_cell("frames.csv", 3, "exposure_s", "fast"),
                              ["row 3 (line 5), column 'exposure_s'", "got 'fast'"]),
    "empty file name": (set_cell("frames.csv", 1, "file", ""), ["row 1 (line 3), column 'file'"]),
    "column missing": (edit_csv("frames.csv", lambda t: t.drop(columns="exposure_s")),
                       ["column 'exposure_s'", "missing"]),
    "several problems, all listed": (edit_csv("frames.csv", several_frames_problems),
                                     ["(and 3 more problem(s):", "row 1 (line 3), column 'flash_level'",
                                      "row 2 (line 4), column 'exposure_s'", "duplicate frame_id"]),
    "frames.csv without rows": (write_file("frames.csv", b"frame_id,view_id,file,flash_level,exposure_s\n"),
                                ["frames.csv", "no rows"]),
    "frames.csv not text": (write_file("frames.csv", bytes(range(256)) * 4), ["frames.csv", "not a readable CSV"]),
    "raw frame missing": (lambda c: (c / "raw" / "v001_f1.dng").unlink(),
                          ["frames.csv: row 4 (line 6), column 'file'", "v001_f1.dng", "does not exist"]),
    "raw frame truncated": (truncate("raw/v002_f0.dng"), ["v002_f0.dng", "row 6 (line 8)", "cannot be read",
                                                           "bad_frames: skip"]),
    "raw frame not a raw file": (write_file("raw/v000_f0.dng", b"not a dng at all" * 10),
                                 ["v000_f0.dng", "cannot be read"]),
    "raw frame of the wrong size": (raw_array("raw/v000_f1.dng", np.zeros((HEIGHT, WIDTH + 4), np.uint16)),
                                    ["v000_f1.dng", f"got shape ({HEIGHT}, {WIDTH + 4})"]),
    "raw frame of the wrong bit depth": (raw_array("raw/v000_f2.dng", np.full((HEIGHT, WIDTH), 65520, np.uint16)),
                                         ["v000_f2.dng", "12-bit"]),
    "pose of a view without frames": (edit_csv("poses.csv", lambda t: pd.concat([t, t.iloc[[0]].assign(
        view_id="ghost")])), ["poses.csv", "'ghost'", "no frame"]),
    "pose not a unit quaternion": (set_cell("poses.csv", 1, "qw", "2"),
                                   ["poses.csv: row 1 (line 3), columns qw..qz", "unit quaternion"]),
    "pose translation not a number": (set_cell("poses.csv", 2, "tx", "far"), ["poses.csv", "row 2 (line 4)",
                                                                              "column 'tx'"]),
    "duplicate pose": (set_cell("poses.csv", 2, "view_id", "v000"), ["poses.csv", "duplicate view_id"]),
    # issue #52: files a user writes
    "capture.yaml key given twice": (duplicate_yaml_key, ["capture.yaml: key 'sensor.width'", "given twice",
                                                          "(lines 2 and "]),
    "frames.csv separated by ';'": (separator("frames.csv", ";"), ["frames.csv: line 1 (the header)",
                                                                   "uses ';' as separator", "expected ','"]),
    "frames.csv separated by tabs": (separator("frames.csv", "\t"), ["frames.csv", "uses a tab as separator"]),
    "poses.csv separated by ';'": (separator("poses.csv", ";"), ["poses.csv", "uses ';' as separator"]),
    "trailing space in a view_id": (set_cell("frames.csv", 3, "view_id", "v001 "),
                                    ["frames.csv: row 3 (line 5), column 'view_id'", "'v001 '", "white space"]),
    "trailing space in a posed view_id": (set_cell("poses.csv", 1, "view_id", "v001 "),
                                          ["poses.csv: row 1 (line 3), column 'view_id'", "'v001 '"]),
    # issue #52: frames checked against their labels, from the data
    "one raw file listed for two frames": (set_cell("frames.csv", 4, "file", "raw/v000_f0.dng"),
                                           ["frames.csv: rows 0 (line 2) and 4 (line 6), column 'file'",
                                            "'v000_f0' (view 'v000'", "'v001_f1' (view 'v001'", "same raw file"]),
    "two frames with identical content": (copy_file("raw/v000_f0.dng", "raw/v001_f1.dng"),
                                          ["frames.csv: rows 0 (line 2) and 4 (line 6)", "identical pixels",
                                           "'v000_f0'", "'v001_f1'"]),
    "every frame black": (every_raw_frame(64), ["frames.csv: all 12 frames are black", "0.00% of a frame's pixels "
                                                "are usable", "lens cap"]),
    "every frame saturated": (every_raw_frame(4095), ["frames.csv: all 12 frames are saturated", "usable",
                                                      "white_level"]),
}


def linearize(capture: Path, output: Path, *extra: str) -> int:
    return main(["linearize", "--capture", str(capture), "--output", str(output), *extra])


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_input_stops_with_its_message_and_leaves_nothing(pristine, tmp_path, case, caplog):
    capture = tmp_path / "capture"
    shutil.copytree(pristine, capture)
    break_it, pieces = CASES[case]
    break_it(capture)
    output = tmp_path / "out" / "linear.zarr"
    with caplog.at_level(logging.INFO):
        status = linearize(capture, output)
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert status == 1 and errors, caplog.text[-2000:]
    for piece in pieces:
        assert piece in errors[-1], f"{piece!r} not in {errors[-1]!r}"
    assert "more problem" not in errors[-1] or case in ("several problems, all listed", "duplicate frame_id",
                                                       "duplicate pose"), errors[-1]  # no problem said twice
    assert str(capture) in errors[-1]  # the file is named with its path
    leftovers = list((tmp_path / "out").iterdir()) if (tmp_path / "out").exists() else []
    assert leftovers == [], leftovers


def test_mislabelled_flash_levels_stop_the_merge_naming_view_and_frames(pristine, tmp_path, caplog):
    """All three frames of view v001 labelled with the same flash level (they are 1, 1/2 and 1/4 as bright): the
    merge names the view, the two frames that disagree with the third and both ratios, and writes nothing."""
    capture = tmp_path / "capture"
    shutil.copytree(pristine, capture)
    edit_csv("frames.csv", lambda t: t.assign(flash_level=t["flash_level"].where(t["view_id"] != "v001",
                                                                                 "0.125")))(capture)
    assert linearize(capture, tmp_path / "linear.zarr") == 0
    with caplog.at_level(logging.INFO):
        status = main(["merge-hdr", "--linear", str(tmp_path / "linear.zarr"), "--output", str(tmp_path / "hdr.zarr")])
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert status == 1 and errors, caplog.text[-2000:]
    for piece in [f"{capture}/frames.csv: view 'v001'", "frame 'v001_f0' (frames.csv row 3, line 5) is 2x as bright "
                  "as frame 'v001_f1' but labelled 1x", "frame 'v001_f2' (frames.csv row 5, line 7) is 0.4",
                  "ingest.flash_ratio_tolerance"]:
        assert piece in errors[-1], f"{piece!r} not in {errors[-1]!r}"
    assert "v000" not in errors[-1] and not (tmp_path / "hdr.zarr").exists()
    # the same labels within the tolerance: a factor 4 allowed
    assert main(["merge-hdr", "--linear", str(tmp_path / "linear.zarr"), "--output", str(tmp_path / "hdr.zarr"),
                 "--settings", '{"flash_ratio_tolerance": 4.5}']) == 0


def test_the_pristine_merge_passes_the_flash_check(pristine, tmp_path):
    assert linearize(pristine, tmp_path / "linear.zarr") == 0
    assert main(["merge-hdr", "--linear", str(tmp_path / "linear.zarr"), "--output", str(tmp_path / "hdr.zarr")]) == 0


def test_a_dark_noisy_capture_passes_the_flash_check_and_a_mislabel_on_it_does_not(tmp_path, caplog):
    """The stability case dark_noisy (scene tiny_dark, rho_d 0.02-0.05, sensor noise x4; 4 of its views at its
    320x256): the frames' measured brightness ratios lie within 10 % of their labels (1, 1/2, 1/4), where choosing
    the samples on the measured frame's own values kept those its noise lifted above the floor (0.62 for 1/2, 0.50
    for 1/4: merge_hdr stopped the case); the same capture with one view's flash levels all labelled alike still
    stops the merge."""
    import zarr

    from sellip.capture import ingest
    from sellip.capture.synthetic import synthesize_capture

    capture = synthesize_capture("tiny_dark", tmp_path / "capture", views=4, width=320, height=256, seed=3,
                                 supersample=1, noise_scale=4.0, progress=False)
    assert linearize(capture, tmp_path / "linear.zarr") == 0
    group = zarr.open_group(str(tmp_path / "linear.zarr"), mode="r")
    attrs = dict(group.attrs)
    for view in dict.fromkeys(attrs["view_id"]):
        rows = [i for i, v in enumerate(attrs["view_id"]) if v == view]
        _, measured, labelled = ingest.brightness_ratios([np.asarray(group["linear"][i]) for i in rows],
                                                         [attrs["flash_level"][i] * attrs["exposure_s"][i]
                                                          for i in rows])
        assert np.isfinite(measured).all() and np.all(np.abs(np.log(measured / labelled)) < np.log(1.1)), \
            (view, measured, labelled)
    assert main(["merge-hdr", "--linear", str(tmp_path / "linear.zarr"), "--output", str(tmp_path / "hdr.zarr")]) == 0
    edit_csv("frames.csv", lambda t: t.assign(flash_level=t["flash_level"].where(t["view_id"] != "v002",
                                                                                 "0.125")))(capture)
    assert linearize(capture, tmp_path / "mislabelled.zarr") == 0
    with caplog.at_level(logging.INFO):
        assert main(["merge-hdr", "--linear", str(tmp_path / "mislabelled.zarr"), "--output",
                     str(tmp_path / "mislabelled_hdr.zarr")]) == 1
    assert "view 'v002'" in caplog.text and not (tmp_path / "mislabelled_hdr.zarr").exists()


@pytest.mark.parametrize("case", ["raw frame missing", "raw frame truncated", "raw frame not a raw file"])
def test_bad_frames_skip_leaves_the_frame_out_with_a_warning(pristine, tmp_path, case, caplog):
    capture = tmp_path / "capture"
    shutil.copytree(pristine, capture)
    CASES[case][0](capture)
    with caplog.at_level(logging.INFO):
        status = linearize(capture, tmp_path / "linear.zarr", "--settings", '{"bad_frames": "skip"}')
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert status == 0 and (tmp_path / "linear.zarr").is_dir()
    assert any("left out 1 of 12 frames" in w for w in warnings), warnings


def test_the_pristine_capture_passes(pristine, tmp_path):
    assert linearize(pristine, tmp_path / "linear.zarr") == 0 and (tmp_path / "linear.zarr" / "zarr.json").is_file()


def test_many_problems_are_listed_up_to_a_cap(pristine, tmp_path, caplog):
    """Every flash level of the 12 frames out of range: the first in detail, ten more listed, one counted."""
    from sellip.capture import files, reader

    capture = tmp_path / "capture"
    shutil.copytree(pristine, capture)
    edit_csv("frames.csv", lambda t: t.assign(flash_level="2"))(capture)
    with pytest.raises(files.FlashLevelError) as info:
        reader.read_capture(capture)
    message = str(info.value)
    assert "(and 11 more problem(s):" in message and "; and 1 more)" in message
    assert message.count("column 'flash_level'") == 1 + files.MAX_LISTED_PROBLEMS


LIMITED = ("import resource, runpy, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
           "resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]),) * 2); sys.argv = ['sellip'] + sys.argv[2:]; "
           "runpy.run_module('sellip.cli', run_name='__main__')")
"""`python -c LIMITED BYTES ARGS...`: `sellip ARGS...` whose files may not grow past BYTES (a full disk, for that
process: writes beyond fail with EFBIG instead of killing it with SIGXFSZ)."""


def test_no_room_to_write_is_a_clear_error_and_leaves_nothing(pristine, tmp_path):
    """`sellip linearize` with no room for its store (a file-size limit of 2 kB for the process, as a full disk
    would): exit 1, a message that says what is wrong and what to do, and no store, whole or partial."""
    import os
    import subprocess
    import sys

    out = tmp_path / "out"
    out.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).parents[2] / "src"),
                                                                     os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, "-c", LIMITED, "2048", "linearize", "--capture", str(pristine),
                             "--output", str(out / "linear.zarr")], capture_output=True, text=True, env=env,
                            timeout=300, check=False)
    print(result.stderr[-1500:])
    assert result.returncode == 1, result.stderr[-3000:]
    assert "ERROR sellip: no room to write" in result.stderr and "File too large" in result.stderr
    assert "run the same command again" in result.stderr and "Traceback" not in result.stderr
    assert list(out.iterdir()) == []


@pytest.fixture
def full_disk(tmp_path):
    """A real file system of 256 kB (tmpfs), where the machine lets this process mount one (root, not in a
    container without CAP_SYS_ADMIN); skipped elsewhere (the file-size limit above stands in for it)."""
    import subprocess

    mount = tmp_path / "small disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)], capture_output=True,
                          text=True, check=False)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=False)


def test_a_full_file_system_is_a_clear_error_and_leaves_nothing(pristine, full_disk):
    """`sellip linearize` writing its store onto a real 256 kB file system, which its 12 frames overflow: exit 1,
    ENOSPC said in words, and nothing on that file system afterwards, whole or partial."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).parents[2] / "src"),
                                                                     os.environ.get("PYTHONPATH")]))}
    result = subprocess.run([sys.executable, "-m", "sellip.cli", "linearize", "--capture", str(pristine),
                             "--output", str(full_disk / "linear.zarr")], capture_output=True, text=True, env=env,
                            timeout=300, check=False)
    assert result.returncode == 1, result.stderr[-3000:]
    assert "ERROR sellip: no room to write" in result.stderr and "No space left on device" in result.stderr
    assert "Traceback" not in result.stderr
    assert list(full_disk.iterdir()) == []


# --------------------------------------------------------------------------- a user's files are never replaced

def capture_new(raw_dir: Path, device: Path, *extra: str) -> None:
    main(["capture", "new", str(raw_dir), "--device", str(device), "--distance-m", "0.9", "--pattern",
          "{view}_f{level}.dng", "--exposure-s", "0.005", *extra])


@pytest.fixture
def frame_folder(pristine, tmp_path):
    """A folder of the pristine capture's raw frames (renamed to a pattern) and a device.yaml that describes them."""
    from sellip.calibrate import device as devices

    raw_dir = tmp_path / "owl" / "raw"
    raw_dir.mkdir(parents=True)
    frames = pd.read_csv(pristine / "frames.csv", dtype=str)
    for row in frames.itertuples():
        shutil.copy(pristine / row.file, raw_dir / f"{row.view_id}_f{float(row.flash_level):g}.dng")
    config = yaml.safe_load((pristine / "capture.yaml").read_text())
    device = devices.write_device(tmp_path / "device.yaml", {key: config[key] for key in ("sensor", "camera", "light")})
    return raw_dir, device


def test_capture_new_never_replaces_an_edited_capture_yaml(frame_folder):
    """`sellip capture new` twice: the same files again (exit 0); after the user edited capture.yaml it stops and
    names the file and --force, leaving the edit (before: overwritten, exit 0); with --force it replaces it."""
    raw_dir, device = frame_folder
    capture_new(raw_dir, device)
    written = raw_dir.parent / "capture.yaml"
    first = written.read_text()
    capture_new(raw_dir, device)  # the same content: fine
    assert written.read_text() == first
    edited = first.replace("distance_m: 0.9", "distance_m: 0.85")
    assert edited != first
    written.write_text(edited)
    with pytest.raises(SystemExit) as info:
        capture_new(raw_dir, device)
    message = str(info.value.code)
    assert message.startswith(f"sellip capture new: {written}: exists and differs from what sellip capture new "
                              "would write"), message
    assert "nothing was written" in message and "--force" in message
    assert written.read_text() == edited
    frames_csv = raw_dir.parent / "frames.csv"
    frames_csv.write_text(frames_csv.read_text().replace("0.005", "0.004"))
    written.write_text(first)
    with pytest.raises(SystemExit, match="frames.csv: exists and differs"):
        capture_new(raw_dir, device)
    capture_new(raw_dir, device, "--force")
    assert written.read_text() == first and "0.004" not in frames_csv.read_text()


def test_synth_never_replaces_a_folder_it_did_not_write(pristine, tmp_path):
    """`sellip synth --out` onto a user's capture (capture.yaml without a `synthetic` section) or a folder of other
    files stops before rendering; the folder is left as it was (before: replaced as a whole)."""
    capture = tmp_path / "capture"
    shutil.copytree(pristine, capture)
    config = yaml.safe_load((capture / "capture.yaml").read_text())
    config.pop("synthetic")
    (capture / "capture.yaml").write_text(yaml.safe_dump(config))
    before = sorted(p.relative_to(capture) for p in capture.rglob("*"))
    for out in (capture, tmp_path / "notes"):
        out.mkdir(exist_ok=True)
        if out.name == "notes":
            (out / "todo.txt").write_text("mine")
        with pytest.raises(SystemExit) as info:
            main(["synth", "--scene", "tiny", "--out", str(out), "--views", "2", "--width", "32", "--height", "24"])
        message = str(info.value.code)
        assert message.startswith(f"sellip synth: {out}: exists and is not a folder sellip synth wrote"), message
        assert "--force" in message and "another --out" in message
    assert sorted(p.relative_to(capture) for p in capture.rglob("*")) == before
    assert (tmp_path / "notes" / "todo.txt").read_text() == "mine"


def test_synth_calibration_never_replaces_a_folder_it_did_not_write(tmp_path):
    from sellip.calibrate.synthetic_set import synthesize_calibration
    from sellip.jobs import WouldReplaceError

    (tmp_path / "calib").mkdir()
    (tmp_path / "calib" / "board_00.dng").write_bytes(b"a user's frame")
    with pytest.raises(WouldReplaceError, match="calib: exists and is not a folder sellip synth-calibration wrote"):
        synthesize_calibration(tmp_path / "calib", 64, 48, board_frames=1, sphere_frames=1)
    assert (tmp_path / "calib" / "board_00.dng").read_bytes() == b"a user's frame"
