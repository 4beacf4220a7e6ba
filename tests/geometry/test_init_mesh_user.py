"""init.mode mesh: a mesh the user supplies (a scan) as the initial mesh, resampled to the vertex budget and
checked against the silhouettes; wrong units, wrong place and unreadable files are clear errors (the stage on a
small synthetic capture; the check itself on a box's rendered silhouettes, including wrong scale and rotation);
the rule passes the file (relative paths in the capture folder) and lists it as an input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from sellip.capture.files import GROUND_TRUTH_MESH
from sellip.geometry import hull as geometry_hull
from sellip.geometry import initial as geometry_initial
from sellip.geometry import meshes
from sellip.geometry import scan as geometry_scan
from sellip.geometry.initial import InitMeshError
from sellip.model.ply import read_ply

pytestmark = pytest.mark.slow  # the whole module: `make test-fast` leaves it out

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The tiny sphere (4 cm radius), 8 views of 320x256 raw pixels, ingested, with its known poses."""
    from sellip.capture.hdr import merge_capture
    from sellip.capture.linearize import linearize_capture
    from sellip.capture.synthetic import synthesize_capture
    from sellip.geometry import poses as geometry_poses

    root = tmp_path_factory.mktemp("user_mesh")
    folder = synthesize_capture("tiny", root / "capture", views=8, width=320, height=256, seed=3, supersample=1,
                                progress=False)
    hdr = merge_capture(linearize_capture(folder, root / "linear.zarr"), root / "hdr.zarr")
    geometry_poses.solve_poses(hdr, folder, root / "cameras.csv", root / "sfm")  # sfm.mode known
    vertex, faces = read_ply(folder / GROUND_TRUTH_MESH)
    truth = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64)
    return {"folder": folder, "root": root, "hdr": hdr, "truth": (truth, faces)}


def write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces))
    assert o3d.io.write_triangle_mesh(str(path), mesh)
    return path


def run(capture, mesh_path, output: Path, max_vertices: int = 3000) -> dict:
    root = capture["root"]
    return geometry_initial.make_initial_mesh(capture["hdr"], root / "cameras.csv", root / "sfm", output,
                                              options=geometry_hull.InitMeshOptions(mode="mesh",
                                                                                    max_vertices=max_vertices),
                                              mesh_path=mesh_path)


def read_mesh(path: Path):
    vertex, faces = read_ply(path)
    return (np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64),
            np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float64), faces)


def test_the_true_mesh_becomes_the_initial_mesh(capture, tmp_path):
    """The ground truth as the scan, twice: the PLY as shipped (2.6k vertices and normals: subdivided to the
    budget), and as an OBJ without normals, inward-wound, 16x denser and with a stray blob (decimated, the blob
    dropped, turned outward). Both: close to the truth, normals outward, within the budget, the check reported."""
    import open3d as o3d

    from sellip.capture.scenes import icosphere

    truth, truth_faces = capture["truth"]
    dense = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(truth),
                                      o3d.utility.Vector3iVector(truth_faces)).subdivide_midpoint(2)
    dense_vertices = np.asarray(dense.vertices)
    dense_vertices = 0.04 * dense_vertices / np.linalg.norm(dense_vertices, axis=1, keepdims=True)
    blob, blob_faces = icosphere(1)
    scan = write_mesh(tmp_path / "scan.obj", np.concatenate([dense_vertices, 0.003 * blob + [0.0, 0.0, 0.07]]),
                      np.concatenate([np.asarray(dense.triangles)[:, ::-1], blob_faces + len(dense_vertices)]))
    for source, budget in ((capture["folder"] / GROUND_TRUTH_MESH, 4000), (scan, 3000)):
        output = tmp_path / source.stem / "init.ply"
        report = run(capture, source, output, max_vertices=budget)
        vertices, normals, faces = read_mesh(output)
        info = json.loads(output.with_suffix(".json").read_text())
        assert info == json.loads(json.dumps(report)) and info["mode"] == "mesh" and info["mesh_path"] == str(source)
        assert 0.5 * budget < len(vertices) == info["vertices"] <= 1.1 * budget
        distances = meshes.mesh_distances(vertices, faces, truth, truth_faces, count=20000)
        assert distances.chamfer < 5e-5 and distances.hausdorff < 2e-4  # measured 0.016-0.018 mm and 0.07 mm
        assert np.all(np.einsum("ij,ij->i", normals, vertices) > 0)  # outward, from the sphere's centre
        check = info["check"]
        assert sorted(check["inside_fraction"]) == [f"v{k:03d}" for k in range(8)]
        assert min(check["inside_fraction"].values()) > 0.97 and 0.9 < check["scale_ratio"] < 1.1
        assert check["problems"] == [] and info["disagreeing_views"] == []
    assert info["source_vertices"] == len(dense_vertices) + len(blob) > 8 * 3000  # decimated first
    assert info["component_vertices"] == len(dense_vertices)  # the blob dropped


def test_a_mesh_in_millimetres_is_a_units_error(capture, tmp_path):
    truth, faces = capture["truth"]
    scan = write_mesh(tmp_path / "scan_mm.ply", 1000 * truth, faces)
    with pytest.raises(InitMeshError) as error:
        run(capture, scan, tmp_path / "out" / "init.ply")
    message = str(error.value)
    assert str(scan) in message and "wrong units?" in message and "millimetres" in message
    assert "a factor of 1000" in message
    assert not (tmp_path / "out").exists()


def test_a_displaced_mesh_is_a_place_error(capture, tmp_path):
    truth, faces = capture["truth"]
    scan = write_mesh(tmp_path / "scan_moved.obj", truth + [0.3, 0.0, 0.0], faces)
    with pytest.raises(InitMeshError) as error:
        run(capture, scan, tmp_path / "out" / "init.ply")
    message = str(error.value)
    assert str(scan) in message and "wrong place?" in message and "0.300 m" in message and "+0.300" in message
    assert "units" not in message


def test_unreadable_missing_or_triangle_free_files_are_named(capture, tmp_path, caplog):
    garbage = tmp_path / "scan.ply"
    garbage.write_bytes(b"not a mesh\x00\x01")
    with pytest.raises(InitMeshError, match=f"{garbage}: cannot be read as a triangle mesh"):
        run(capture, garbage, tmp_path / "out" / "init.ply")
    cloud = tmp_path / "cloud.ply"
    cloud.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                     "end_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InitMeshError, match=f"{cloud}: has 3 vertices but no triangles"):
        run(capture, cloud, tmp_path / "out" / "init.ply")
    with pytest.raises(InitMeshError, match="needs the mesh file"):
        run(capture, None, tmp_path / "out" / "init.ply")
    # Through the command line: exit status 1 and the file named in the log.
    from sellip.cli import main

    root = capture["root"]
    missing = tmp_path / "missing.obj"
    status = main(["init-mesh", "--hdr", str(capture["hdr"]), "--cameras", str(root / "cameras.csv"), "--sfm",
                   str(root / "sfm"), "--output", str(tmp_path / "out" / "init.ply"),
                   "--settings", '{"mode": "mesh"}', "--mesh-path", str(missing)])
    assert status == 1 and f"{missing}: the mesh file of init.mode 'mesh' (init.mesh_path) does not exist" in (
        caplog.text)
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def box_views():
    """A 8 x 4 x 2 cm box (remeshed to ~2k vertices) and its silhouettes from a 12-view orbit."""
    import open3d as o3d
    from test_geometry import camera_arrays, orbit

    from sellip.model.render import coverage_masks

    box = o3d.geometry.TriangleMesh.create_box(0.08, 0.04, 0.02).translate((-0.04, -0.02, -0.01))
    vertices, faces = meshes.remesh_to_count(np.asarray(box.vertices), np.asarray(box.triangles), 2000)
    cameras = orbit(12)
    masks = coverage_masks(vertices, faces, cameras)
    arrays = camera_arrays(cameras)
    return vertices, masks, arrays, geometry_hull.visual_hull(masks, *arrays, resolution=48)


@pytest.mark.parametrize("change, expected", [
    (lambda v: v, None),
    (lambda v: v @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T, "rotated, or in another world"),
    (lambda v: 0.01 * v, "the cameras (poses.csv) look like centimetres and the mesh metres; scaling the mesh by 100 "
                         "(a factor of 100)"),
    (lambda v: 1.5 * v, "wrong scale? the mesh is 1.5 times the size of the silhouettes (median over views"),
    (lambda v: v + [0.0, 0.0, 0.05], "wrong place?"),
])
def test_the_silhouette_check_says_what_is_off(box_views, change, expected):
    vertices, masks, arrays, carving = box_views
    check = geometry_scan.check_against_silhouettes(change(vertices), masks, *arrays, carving)
    if expected is None:
        assert check.problems == [] and check.median_inside_fraction > 0.97 and 0.95 < check.scale_ratio < 1.05
        assert check.inside_fraction.shape == (12,) and np.isfinite(check.extent_ratio).all()
    else:
        assert len(check.problems) == 2 and expected in check.problems[0], check.problems
        assert check.problems[1].startswith("median share of its vertices inside the silhouettes")


def _dry_run(workdir: Path, capture_folder: Path, init: dict) -> subprocess.CompletedProcess:
    override = workdir / "override.yaml"
    override.write_text(yaml.safe_dump({"name": "scan", "capture": str(capture_folder), "init": init}))
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir),
               "--configfile", str(REPO / "config" / "config.yaml"), str(override), "-n", "-p",
               "results/scan/mesh/init.ply"]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=300, check=False)


def _init_mesh_job(out: str) -> str:
    return out[out.index("rule init_mesh:"):].split("\n\n")[0]


def test_the_rule_passes_the_mesh_and_tracks_it_by_content(capture, tmp_path):
    """The scan is passed to the job and tracked by its content (a params digest, docs/reliability.md), not as an
    input file; a scan that does not exist stops the workflow before any job, naming init.mesh_path."""
    folder = capture["folder"]
    relative = _dry_run(tmp_path, folder, {"mode": "mesh", "mesh_path": GROUND_TRUTH_MESH})
    assert relative.returncode == 0, relative.stderr[-3000:]
    job = _init_mesh_job(relative.stdout + relative.stderr)
    resolved = folder / GROUND_TRUTH_MESH  # relative to the capture folder
    assert """--settings '{"mode": "mesh"}' """ f"--mesh-path {resolved}" in job

    absolute = _dry_run(tmp_path, folder, {"mode": "mesh", "mesh_path": str(tmp_path / "elsewhere.ply")})
    said = absolute.stdout + absolute.stderr
    assert absolute.returncode != 0 and "init.mesh_path" in said and "elsewhere.ply" in said

    hull = _dry_run(tmp_path, folder, {"mode": "hull"})
    job = _init_mesh_job(hull.stdout + hull.stderr)
    assert """--settings '{"mode": "hull"}'""" in job and "--mesh-path" not in job
    assert ".ply," not in job.split("output:")[0]

    unset = _dry_run(tmp_path, folder, {"mode": "mesh"})
    assert unset.returncode != 0 and "init.mode 'mesh' needs init.mesh_path" in unset.stdout + unset.stderr


def test_cameras_that_disagree_with_the_silhouettes_stop_the_stage(capture, tmp_path):
    """The silhouettes against the hull: cameras.csv with every camera moved 3 cm sideways (0.75 sphere radii at
    0.9 m) is not this capture's; the hull (what all cones share) covers a fraction of each silhouette, and the
    stage stops naming what to check, writing nothing. The true cameras' hull covers all of it."""
    import pandas as pd

    table = pd.read_csv(capture["root"] / "cameras.csv", dtype={"view_id": str})
    angle = np.random.default_rng(1).uniform(0, 2 * np.pi, len(table))
    table["tx"] += 0.03 * np.cos(angle)
    table["ty"] += 0.03 * np.sin(angle)
    bad = tmp_path / "cameras.csv"
    table.to_csv(bad, index=False)
    options = geometry_hull.InitMeshOptions(max_vertices=2000)
    with pytest.raises(InitMeshError) as error:
        geometry_initial.make_initial_mesh(capture["hdr"], bad, capture["root"] / "sfm", tmp_path / "out" / "init.ply",
                                           options=options)
    message = str(error.value)
    assert str(bad) in message and "covers a median" in message and "do not describe these photographs" in message
    assert "cam_from_world" in message and "camera.fx, fy, cx, cy" in message
    assert not (tmp_path / "out").exists()
    report = geometry_initial.make_initial_mesh(capture["hdr"], capture["root"] / "cameras.csv",
                                                capture["root"] / "sfm", tmp_path / "good" / "init.ply",
                                                options=options)
    assert min(report["silhouette_coverage"].values()) > 0.95


def test_one_misplaced_view_is_named_as_an_outlier(capture, tmp_path, caplog):
    """Issue #52: one view's camera moved 3 cm sideways (its photograph belongs elsewhere: a swapped or misplaced
    view). The robust hull keeps what the other views agree on, so the stage goes on, but a WARNING names that
    view as disagreeing far more than the rest; the true cameras name none."""
    import logging

    import pandas as pd

    table = pd.read_csv(capture["root"] / "cameras.csv", dtype={"view_id": str})
    table.loc[3, "tx"] += 0.03
    bad = tmp_path / "cameras.csv"
    table.to_csv(bad, index=False)
    options = geometry_hull.InitMeshOptions(max_vertices=2000)
    with caplog.at_level(logging.WARNING):
        report = geometry_initial.make_initial_mesh(capture["hdr"], bad, capture["root"] / "sfm",
                                                    tmp_path / "out" / "init.ply", options=options)
    print(report["others_disagreement"])
    assert report["outlier_views"] == [table.loc[3, "view_id"]]
    warning = [r.getMessage() for r in caplog.records if "far more than the other views" in r.getMessage()]
    assert warning and f"view(s) '{table.loc[3, 'view_id']}'" in warning[0] and "swapped or misplaced" in warning[0]
    report = geometry_initial.make_initial_mesh(capture["hdr"], capture["root"] / "cameras.csv",
                                                capture["root"] / "sfm", tmp_path / "good" / "init.ply",
                                                options=options)
    assert report["outlier_views"] == []


def test_outlier_views_are_robust_z_scores_above_a_floor():
    values = np.array([0.004, 0.006, 0.005, 0.30, 0.007, 0.003])
    assert geometry_initial.outlier_views(values).tolist() == [False, False, False, True, False, False]
    # views that differ among themselves by a few percent: none stands out
    assert not geometry_initial.outlier_views(np.array([0.02, 0.03, 0.04, 0.06, 0.03])).any()
    assert not geometry_initial.outlier_views(np.array([0.004, 0.3, 0.005])).any()  # 3 views: no rest to compare
    assert not geometry_initial.outlier_views(np.array([0.001, 0.002, 0.001, 0.04, 0.001]), minimum=0.05).any()
