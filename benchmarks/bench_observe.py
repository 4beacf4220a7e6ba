"""Time and peak memory of ``sellip observe`` (rule gather_observations) on a synthetic scene.

    python benchmarks/bench_observe.py [--vertices 100000] [--views 50] [--width 306 --height 256]
                                       [--view-chunk 8] [--threads 2] [--workdir DIR]

Writes the stage's inputs in their documented formats: a mesh (a sphere with a ring around it,
so that there are occlusions and flash shadows; ``--vertices`` in total, with vertex normals),
cameras.csv from a handheld orbit (:func:`sellip.capture.scenes.handheld_orbit`), an hdr.zarr of
``--views`` smooth HDR images of ``--width`` x ``--height`` (Blosc lz4 like ``sellip merge-hdr``;
a small invalid patch per view) and a minimal capture folder. Then runs ``sellip observe`` in a
child process and prints its wall time, peak resident memory (the child's ru_maxrss) and the
store's size, one JSON line; also the child's CPU time (user + system) and the 1-minute load
average, since wall time on a shared machine depends on what else runs.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def ring_and_sphere(vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 5 cm sphere and a torus (7 cm, tube 1.5 cm) around it: vertices (N, 3), faces (F, 3), normals (N, 3)."""
    import open3d as o3d

    sphere_res = max(8, int(round(np.sqrt(vertices / 2 / 2))))  # create_sphere: ~2 r^2 vertices
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=sphere_res)
    torus_rest = max(vertices - len(sphere.vertices), 64)
    radial = max(8, int(round(np.sqrt(torus_rest * 3))))
    torus = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.07, tube_radius=0.015, radial_resolution=radial,
                                                   tubular_resolution=max(4, torus_rest // radial))
    torus.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0.5, 0.2, 0.0)), center=(0, 0, 0))
    mesh = sphere + torus
    mesh.compute_vertex_normals()
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_normals)


def write_inputs(folder: Path, vertices: int, views: int, width: int, height: int) -> dict:
    import zarr

    from sellip.capture.hdr import HDR_CODEC
    from sellip.capture.ingest import output_intrinsics
    from sellip.capture.scenes import handheld_orbit
    from sellip.capture.sensor import SensorModel
    from sellip.capture.writer import CaptureWriter
    from sellip.geometry.cameras import write_cameras
    from sellip.model.ply import write_ply

    points, faces, normals = ring_and_sphere(vertices)
    write_ply(folder / "mesh.ply", {**{n: points[:, k].astype(np.float32) for k, n in enumerate("xyz")},
                                    **{n: normals[:, k].astype(np.float32) for k, n in enumerate(("nx", "ny", "nz"))}},
                faces)
    raw_width, raw_height = 2 * width, 2 * height
    cameras = handheld_orbit(views, raw_width, raw_height, np.random.default_rng(0), distance_m=(0.5, 0.6))
    view_ids = [f"v{k:04d}" for k in range(views)]
    write_cameras(folder / "cameras.csv", view_ids, np.stack([c.rotation for c in cameras]),
                  np.stack([c.translation for c in cameras]))
    k = cameras[0].intrinsics
    camera = {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2]}
    group = zarr.open_group(str(folder / "hdr.zarr"), mode="w")
    analyzers = group.create_array("analyzers", shape=(views, height, width, 4, 3), chunks=(1, height, width, 4, 3),
                                   dtype="float32", compressors=HDR_CODEC)
    valid = group.create_array("valid", shape=(views, height, width), chunks=(1, height, width), dtype="bool")
    rows, cols = np.mgrid[0:height, 0:width].astype(np.float32)
    base = np.exp(-((cols - width / 2) ** 2 + (rows - height / 2) ** 2) / (0.1 * width * height))
    image = base[..., None, None] * np.array([1.0, 0.8, 0.6, 0.8], np.float32)[:, None] * np.array(
        [0.5, 0.4, 0.3], np.float32)
    mask = np.ones((height, width), bool)
    mask[height // 3: height // 3 + 8, width // 3: width // 3 + 8] = False
    for v in range(views):
        analyzers[v] = image * (1 + 0.01 * v)
        valid[v] = mask
    group.attrs.update({"view_id": view_ids, "intrinsics": output_intrinsics(camera, raw_height, raw_width),
                        "analyzer_angles_deg": [0, 45, 90, 135], "channels": 3})
    sensor = SensorModel(width=8, height=8)
    config = {"sensor": sensor.capture_sensor(), "camera": {"fx": 100.0, "fy": 100.0, "cx": 4.0, "cy": 4.0},
              "light": {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0}, "scene": {"distance_m": 0.55}}
    with CaptureWriter(folder / "capture", config, raw_format="png") as writer:
        for view in view_ids:
            writer.add_frame(f"{view}_f0", view, np.full((8, 8), 100, np.uint16), flash_level=0.25, exposure_s=0.005)
        writer.finish()
    return {"mesh": folder / "mesh.ply", "cameras": folder / "cameras.csv", "hdr": folder / "hdr.zarr",
            "capture": folder / "capture", "vertices": len(points), "faces": len(faces)}


def directory_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vertices", type=int, default=100_000)
    parser.add_argument("--views", type=int, default=50)
    parser.add_argument("--width", type=int, default=306, help="HDR image width (half the raw width)")
    parser.add_argument("--height", type=int, default=256)
    parser.add_argument("--view-chunk", type=int, default=8)
    parser.add_argument("--vertex-chunk", type=int, default=4096)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=None, help="where inputs and the store go (default: temp)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(dir=args.workdir, prefix="bench-observe-") as work:
        work = Path(work)
        started = time.perf_counter()
        paths = write_inputs(work, args.vertices, args.views, args.width, args.height)
        setup_s = time.perf_counter() - started
        output = work / "observations.zarr"
        command = [sys.executable, "-m", "sellip.cli", "observe", "--mesh", str(paths["mesh"]),
                   "--cameras", str(paths["cameras"]), "--hdr", str(paths["hdr"]), "--capture", str(paths["capture"]),
                   "--output", str(output), "--view-chunk", str(args.view_chunk),
                   "--vertex-chunk", str(args.vertex_chunk), "--threads", str(args.threads)]
        started = time.perf_counter()
        run = subprocess.run(command, capture_output=True, text=True)
        wall_s = time.perf_counter() - started
        if run.returncode:
            sys.exit(run.stderr)
        print(run.stderr.strip().splitlines()[-1], file=sys.stderr)
        import zarr

        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        summary = dict(zarr.open_group(str(output), mode="r").attrs["summary"])
        result = {"vertices": paths["vertices"], "faces": paths["faces"], "views": args.views,
                  "image": f"{args.width}x{args.height}", "view_chunk": args.view_chunk, "threads": args.threads,
                  "setup_s": round(setup_s, 1), "wall_s": round(wall_s, 1), "stage_s": round(summary["total_s"], 1),
                  "cpu_s": round(usage.ru_utime + usage.ru_stime, 1), "load_average": round(os.getloadavg()[0], 1),
                  "peak_rss_mb": round(usage.ru_maxrss / 1024),
                  "store_mb": round(directory_bytes(output) / 2**20),
                  "usable_views_per_vertex": summary["usable_views_per_vertex"],
                  "passed_fraction": {k: round(v, 3) for k, v in summary["passed_fraction"].items()}}
        print(json.dumps(result))


if __name__ == "__main__":
    main()
