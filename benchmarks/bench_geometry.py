"""Wall time and accuracy of the geometry bootstrap: SfM (pycolmap) and the initial mesh.

    python benchmarks/bench_geometry.py [--views 100] [--width 1224] [--height 1024] [--cores 2]
    python benchmarks/bench_geometry.py --capture captures/demo --hdr results/demo/hdr.zarr [--cores 2]

Rendered mode (default): renders I_d = 2 I90 of a scene (:mod:`sellip.capture.scenes`, default ``demo``)
from a handheld orbit directly at the demosaiced size (the sensor and ingest are not part of the
measurement; rendering is not timed), then times :func:`sellip.geometry.sfm.run_sfm` (with the stage's
silhouettes and magnification) and :func:`sellip.geometry.hull.hull_mesh` fused with the SfM points.
Capture mode: times the stages as the workflow runs them (``sellip sfm --mode verify`` and
``sellip init-mesh``) on an ingested capture with poses.csv and ground_truth/.

Accuracy: registered views, rotation and centre errors after Sim(3) alignment to the true poses,
Chamfer/Hausdorff distance of the initial mesh to the true mesh. One line per measurement, a JSON
summary on the last line. Runs on ``--cores`` CPU cores (process affinity).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def rendered(args) -> dict:
    from sellip.capture.scenes import build_scene, handheld_orbit
    from sellip.geometry import hull as geometry_hull
    from sellip.geometry import meshes, sfm
    from sellip.geometry import silhouettes as geometry_silhouettes
    from sellip.geometry.poses import compare_to_known
    from sellip.model.render import Renderer, flash_light

    scene = build_scene(args.scene)
    cameras = handheld_orbit(args.views, args.width, args.height, np.random.default_rng(args.seed),
                             distance_m=scene.distance_m, elevation_deg=scene.elevation_deg)
    renderer = Renderer(scene.mesh)
    started = time.perf_counter()
    diffuse = np.stack([2 * renderer.render(c, flash_light(c), supersample=args.supersample).analyzers[..., 2, :]
                        for c in cameras])
    print(f"rendered {args.views} views of {args.width}x{args.height} in {time.perf_counter() - started:.1f} s "
          "(not timed)", flush=True)
    intrinsics = cameras[0].intrinsics
    rotations = np.array([c.rotation for c in cameras])
    translations = np.array([c.translation for c in cameras])
    distance_m = float(np.mean(scene.distance_m))

    started = time.perf_counter()
    masks = geometry_silhouettes.silhouette_masks(diffuse)
    upscale = sfm.feature_upscale(masks, args.feature_object_px, args.max_upscale)
    features = [sfm.feature_image(d, m, upscale) for d, m in zip(diffuse, masks)]
    view_ids = [f"v{k:03d}" for k in range(args.views)]
    with tempfile.TemporaryDirectory() as work:
        result = sfm.run_sfm(np.stack([f[0] for f in features]), np.stack([f[1] for f in features]),
                             sfm.scale_intrinsics(intrinsics, upscale), view_ids, work,
                             sfm.SfmOptions(threads=args.cores))
    result = sfm.transform_result(result, sfm.metric_normalization(result, distance_m))
    sfm_s = time.perf_counter() - started
    align, summary, _ = compare_to_known(result, rotations, translations, distance_m)
    result = sfm.transform_result(result, align)
    registered = int(result.registered.sum())
    print(f"sfm: {sfm_s:.1f} s ({result.stats['timings']}), x{upscale}, registered {registered}/{args.views}, "
          f"rotation error median {summary['rotation_error_deg']['median']:.3f} max "
          f"{summary['rotation_error_deg']['max']:.3f} deg, centre error median "
          f"{100 * summary['centre_error_fraction']['median']:.2f}% max "
          f"{100 * summary['centre_error_fraction']['max']:.2f}% of {distance_m} m", flush=True)

    started = time.perf_counter()
    ok = result.registered
    index = -np.ones(args.views, np.int64)
    index[ok] = np.arange(ok.sum())
    views = [index[t] for t in result.tracks]
    mesh = geometry_hull.hull_mesh(masks[ok], intrinsics, result.rotations[ok], result.translations[ok],
                                 geometry_hull.InitMeshOptions(max_vertices=args.max_vertices, threads=args.cores),
                                 result.points, views, result.errors / upscale)
    init_s = time.perf_counter() - started
    distances = meshes.mesh_distances(mesh.vertices, mesh.faces, scene.mesh.vertices, scene.mesh.faces)
    size = float(np.linalg.norm(np.ptp(scene.mesh.vertices, axis=0)))
    print(f"init_mesh: {init_s:.1f} s ({mesh.stats['timings']}), {len(mesh.vertices)} vertices, Chamfer "
          f"{1e3 * distances.chamfer:.2f} mm ({100 * distances.chamfer / size:.2f}% of {1e3 * size:.0f} mm), "
          f"Hausdorff {1e3 * distances.hausdorff:.2f} mm", flush=True)
    return {"scene": args.scene, "views": args.views, "width": args.width, "height": args.height,
            "upscale": upscale, "sfm_s": sfm_s, "sfm_timings": result.stats["timings"], "registered": registered,
            "verify": summary, "init_mesh_s": init_s, "init_timings": mesh.stats["timings"],
            "vertices": len(mesh.vertices), "chamfer_m": distances.chamfer, "hausdorff_m": distances.hausdorff,
            "object_size_m": size}


def capture(args) -> dict:
    from sellip.capture.files import GROUND_TRUTH_MESH
    from sellip.geometry import hull as geometry_hull
    from sellip.geometry import initial as geometry_initial
    from sellip.geometry import meshes
    from sellip.geometry import poses as geometry_poses
    from sellip.geometry.cameras import read_cameras
    from sellip.model.ply import read_ply
    from sellip.stages import sfm as sfm_stage

    out = Path(args.workdir or tempfile.mkdtemp(prefix="bench-geometry-"))
    started = time.perf_counter()
    report = geometry_poses.solve_poses(args.hdr, args.capture, out / "cameras.csv", out / "sfm",
                                        options=sfm_stage.sfm.SfmOptions(mode="verify", min_registered_fraction=0.0,
                                                                         threads=args.cores))
    sfm_s = time.perf_counter() - started
    print(f"sfm (verify): {sfm_s:.1f} s, registered {report['registered']}/{report['views']}, "
          f"verify {json.dumps(report.get('verify'))}", flush=True)
    started = time.perf_counter()
    mesh_report = geometry_initial.make_initial_mesh(args.hdr, out / "cameras.csv", out / "sfm", out / "init.ply",
                                       options=geometry_hull.InitMeshOptions(max_vertices=args.max_vertices,
                                                                        threads=args.cores))
    init_s = time.perf_counter() - started
    vertex, faces = read_ply(out / "init.ply")
    truth, truth_faces = read_ply(Path(args.capture) / GROUND_TRUTH_MESH)
    points = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64)
    truth_points = np.stack([truth[k] for k in "xyz"], axis=1).astype(np.float64)
    distances = meshes.mesh_distances(points, faces, truth_points, truth_faces)
    size = float(np.linalg.norm(np.ptp(truth_points, axis=0)))
    print(f"init_mesh: {init_s:.1f} s, {mesh_report['vertices']} vertices, Chamfer {1e3 * distances.chamfer:.2f} mm "
          f"({100 * distances.chamfer / size:.2f}% of {1e3 * size:.0f} mm)", flush=True)
    _, rotations, _ = read_cameras(out / "cameras.csv")
    return {"capture": str(args.capture), "views": report["views"], "registered": report["registered"],
            "sfm_s": sfm_s, "sfm_timings": report.get("timings"), "verify": report.get("verify"),
            "init_mesh_s": init_s, "vertices": mesh_report["vertices"], "chamfer_m": distances.chamfer,
            "object_size_m": size, "cameras": len(rotations)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--views", type=int, default=100)
    parser.add_argument("--width", type=int, default=1224, help="demosaiced image width")
    parser.add_argument("--height", type=int, default=1024)
    parser.add_argument("--supersample", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--feature-object-px", type=float, default=400.0)
    parser.add_argument("--max-upscale", type=int, default=3)
    parser.add_argument("--max-vertices", type=int, default=30000)
    parser.add_argument("--capture", type=Path, help="time the stages on this ingested capture instead")
    parser.add_argument("--hdr", type=Path, help="its hdr.zarr (with --capture)")
    parser.add_argument("--workdir", type=Path, help="where capture mode writes (default: a temporary folder)")
    parser.add_argument("--cores", type=int, default=2, help="CPU cores the process may use (default: 2)")
    args = parser.parse_args()
    available = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, available[: args.cores])
    summary = capture(args) if args.capture else rendered(args)
    print(json.dumps({"cores": len(os.sched_getaffinity(0)), **summary}))


if __name__ == "__main__":
    main()
