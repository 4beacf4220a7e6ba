"""Load time and frame rate of the viewer (issue #40, docs/viewer.md) in headless Chromium with software WebGL2
(SwiftShader), for synthetic models of a given number of vertices, or for real results folders.

    python benchmarks/bench_viewer.py --vertices 6000 100000 500000 [--results results/demo ...]
                                      [--size 612 512] [--frames 30] [--out /tmp/bench_viewer] [--screenshots DIR]

A synthetic model is a bumpy sphere of 4 cm on a latitude-longitude grid (two triangles per grid cell) with
per-vertex parameters varying smoothly, 36 cameras at 0.9 m (cameras.csv) and an hdr.zarr holding only the
intrinsics of a 612x512 capture (the demo's HDR grid). Load time: navigation start to the first frame drawn
(parsing model.js, decoding base64, uploading, compiling, drawing; ``performance.now()`` at ready). Frame rate:
``sellipViewer.benchmark(frames)``: full redraws of the relit model while orbiting, each waited for by a 1-pixel read,
with shadows (the flash moves with the camera: the shadow map is redrawn every frame) and without.
Prints one Markdown row per model.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sellip.geometry.cameras import write_cameras

BROWSER_ARGS = ["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def bumpy_sphere(vertices: int, radius: float = 0.04):
    """(positions (V, 3), normals (V, 3), faces (F, 3)) of a bumpy lat-long sphere with about ``vertices`` vertices."""
    rows = max(4, round(np.sqrt(vertices / 2)))
    cols = max(8, round(vertices / rows))
    theta = np.linspace(0.02, np.pi - 0.02, rows)
    phi = np.linspace(0, 2 * np.pi, cols, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    r = radius * (1 + 0.03 * np.sin(5 * p) * np.sin(4 * t))
    pos = np.stack([r * np.sin(t) * np.cos(p), r * np.sin(t) * np.sin(p), r * np.cos(t)], -1).reshape(-1, 3)
    index = np.arange(rows * cols).reshape(rows, cols)
    a, b = index[:-1], np.roll(index, -1, axis=1)[:-1]
    c, d = index[1:], np.roll(index, -1, axis=1)[1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    from sellip.geometry.meshes import vertex_normals

    return pos, vertex_normals(pos, faces), faces


def synthetic_results(root: Path, vertices: int) -> Path:
    import zarr

    from sellip.capture.scenes import handheld_orbit
    from sellip.model.ply import write_ply

    pos, normals, faces = bumpy_sphere(vertices)
    n = len(pos)
    u = 0.5 + 0.5 * np.sin(20 * pos[:, 0] / 0.04)
    vertex = {"x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2], "nx": normals[:, 0], "ny": normals[:, 1],
              "nz": normals[:, 2], "eta": 1.4 + 0.2 * u, "rho_d_r": 0.2 + 0.1 * u, "rho_d_g": 0.15 + 0 * u,
              "rho_d_b": 0.1 + 0.05 * (1 - u), "rho_s": 0.8 + 0 * u, "sigma_s": 0.1 + 0.2 * u,
              "rho_ss_r": 0.05 * u, "rho_ss_g": 0.03 * u, "rho_ss_b": 0.02 * u, "sigma_ss": 0.5 + 0 * u}
    vertex = {k: np.asarray(v, np.float32) for k, v in vertex.items()}
    vertex.update(confidence=np.ones(n, np.float32), model=np.full(n, 3, np.uint8))
    results = root / f"v{n}"
    (results / "final").mkdir(parents=True, exist_ok=True)
    write_ply(results / "final" / "model.ply", vertex, faces)
    cameras = handheld_orbit(36, 612, 512, np.random.default_rng(0))
    write_cameras(results / "cameras.csv", [f"v{i:03d}" for i in range(len(cameras))],
                  np.stack([c.rotation for c in cameras]), np.stack([c.translation for c in cameras]))
    k = cameras[0].intrinsics
    zarr.open_group(str(results / "hdr.zarr"), mode="w").attrs["intrinsics"] = {
        "fx": float(k[0, 0]), "fy": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]), "width": 612,
        "height": 512}
    return results


def measure(results: Path, size: tuple[int, int], frames: int, screenshots: Path | None = None) -> dict:
    from playwright.sync_api import sync_playwright

    from sellip.report.viewer import load_inputs, write_viewer

    started = time.perf_counter()
    inputs = load_inputs(results)
    if inputs.light is None:
        inputs.light = {"position_m": [0.0, 0.05, 0.0], "polarizer_deg": 0.0}
    index = write_viewer(results / "viewer.bench", inputs)
    write_s = time.perf_counter() - started
    size_mb = sum(p.stat().st_size for p in index.parent.iterdir()) / 1e6
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=shutil.which("chromium") or "/usr/bin/chromium", args=BROWSER_ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 1000}, device_scale_factor=1)
        page.goto(index.resolve().as_uri(), timeout=300_000)
        page.wait_for_function("window.sellipViewer && (window.sellipViewer.ready || window.sellipViewer.error)",
                               timeout=300_000, polling=100)
        error = page.evaluate("window.sellipViewer.error || null")
        if error:
            raise RuntimeError(error)
        load_ms = page.evaluate("window.sellipViewer.loadMs")
        renderer = page.evaluate("""(() => { const gl = document.createElement('canvas').getContext('webgl2');
            const e = gl.getExtension('WEBGL_debug_renderer_info');
            return e ? gl.getParameter(e.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER); })()""")
        page.evaluate(f"window.sellipViewer.setSize({size[0]}, {size[1]})")
        fps = page.evaluate(f"window.sellipViewer.benchmark({frames})")  # shadows on: the flash moves every frame
        page.evaluate("window.sellipViewer.set({shadows: false})")
        fps_plain = page.evaluate(f"window.sellipViewer.benchmark({frames})")
        if screenshots is not None:
            screenshots.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(screenshots / f"{results.name}.png"))
        browser.close()
    shutil.rmtree(index.parent)
    return {"model": results.name, "vertices": inputs.vertex["x"].size, "faces": len(inputs.faces),
            "viewer_mb": size_mb, "write_s": write_s, "load_s": load_ms / 1000, "fps": fps, "fps_plain": fps_plain,
            "renderer": renderer}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vertices", type=int, nargs="*", default=[6000, 100000, 500000])
    parser.add_argument("--results", type=Path, nargs="*", default=[], help="real results folders to measure too")
    parser.add_argument("--size", type=int, nargs=2, default=(612, 512), help="canvas pixels (default 612 512)")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--out", type=Path, default=None, help="where synthetic models go (default: a temp folder)")
    parser.add_argument("--screenshots", type=Path, default=None)
    args = parser.parse_args(argv)
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_viewer_"))
    print("| model | vertices | triangles | viewer/ MB | page written s | load s | frames/s | frames/s, no shadows "
          "| renderer |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for target in [*args.results, *args.vertices]:
        results = target if isinstance(target, Path) else synthetic_results(root, target)
        r = measure(results, tuple(args.size), args.frames, args.screenshots)
        print(f"| {r['model']} | {r['vertices']} | {r['faces']} | {r['viewer_mb']:.1f} | {r['write_s']:.1f} | "
              f"{r['load_s']:.2f} | {r['fps']:.1f} | {r['fps_plain']:.1f} | {r['renderer']} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
