"""Peak memory of one fit job (``sellip fit``) against its vertices and views: the measurement behind
:data:`sellip.fit.shard_plan.SHARD_MEMORY` (docs/speed.md, "Memory of a fit shard").

    python benchmarks/shard_memory.py [--views 36] [--vertices 4096 65536 262144] [--chunk-size 8192]
        [--max-iterations 3] [--out DIR]

For each size an observation store of simulated observations (:func:`sellip.fit.simulate.vertex_observations`,
1,024 distinct vertices tiled to the size) is fitted by ``sellip fit`` in its own process, and that process's
peak resident memory is read from the kernel (``getrusage`` of the child). A first fit of the smallest store
fills the compilation cache and is printed apart (a job that compiles peaks higher). The LM iterations are capped
(``--max-iterations``): memory does not depend on them, time does. Printed: one row per size with the measured
peak, the model's prediction and their ratio, then the least-squares constants of the model
``base + loaded * N * V + working * min(N, chunk) * V`` (bytes) fitted to these rows.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path


def write_store(path: Path, vertices: int, views: int, seed: int = 0) -> None:
    """An observation store of ``vertices`` simulated vertices seen by ``views`` views."""
    import numpy as np

    from sellip.fit.observe import ObservationWriter, ObserveMesh, ObserveSettings
    from sellip.fit.simulate import vertex_observations
    from sellip.model.pbrdf import PBRDFParams

    rng = np.random.default_rng(seed)
    base = min(vertices, 1024)
    normals = rng.normal(size=(base, 3)) * [0.3, 0.3, 1] + [0, 0, 1]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    truth = PBRDFParams(eta=rng.uniform(1.3, 1.8, base), rho_d=rng.uniform(0.2, 0.8, (base, 3)),
                        rho_s=np.full(base, 0.5), sigma_s=rng.uniform(0.1, 0.4, base),
                        rho_ss=np.zeros((base, 3)), sigma_ss=np.full(base, 0.6))
    obs = vertex_observations(rng, truth, normals, n_views=views, flash_offset_m=0.055, noise=0.01,
                              dtype=np.float32)
    tile = np.arange(vertices) % base
    positions = rng.normal(size=(vertices, 3)).astype(np.float32) * 0.05
    mesh = ObserveMesh(positions, normals[tile].astype(np.float32), np.zeros((0, 3), np.int64))
    axes = {"camera_up": np.asarray(obs.camera_up)[0], "light_axis": np.asarray(obs.light_axis)[0]}
    writer = ObservationWriter(path, mesh, [f"v{k:03d}" for k in range(views)], axes,
                               ObserveSettings(vertex_chunk=1024, view_chunk=views))
    for name in ("diffuse", "diffuse_pol", "specular", "to_light", "to_camera", "light_distance", "usable"):
        writer.arrays[name][...] = np.asarray(getattr(obs, name))[tile]


def peak_of_fit(store: Path, output: Path, chunk_size: int, cache: Path, iterations: int) -> tuple[float, float]:
    """(peak resident bytes, seconds) of ``sellip fit`` on the whole store, in a fresh process."""
    command = [sys.executable, "-m", "sellip.cli", "fit", "--observations", str(store), "--output", str(output),
               "--settings", json.dumps({"chunk_size": chunk_size, "max_iterations": iterations}),
               "--job-settings", json.dumps({"compilation_cache": str(cache)})]
    # getrusage(RUSAGE_CHILDREN) is the maximum over every child waited for: one measuring process per fit.
    probe = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
             "r = subprocess.run(sys.argv[1:], capture_output=True, text=True); "
             "sys.stderr.write(r.stderr[-3000:] if r.returncode else ''); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, time.perf_counter() - t, r.returncode)")
    result = subprocess.run([sys.executable, "-c", probe, *command], capture_output=True, text=True, check=True)
    kib, seconds, code = result.stdout.split()
    if int(code):
        raise RuntimeError(f"sellip fit failed:\n{result.stderr}")
    return 1024.0 * float(kib), float(seconds)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=36)
    parser.add_argument("--vertices", type=int, nargs="+", default=[4096, 65536, 262144])
    parser.add_argument("--chunk-size", type=int, default=8192, help="FitSettings.chunk_size of the fits")
    parser.add_argument("--max-iterations", type=int, default=3, help="FitSettings.max_iterations of the fits")
    parser.add_argument("--out", type=Path, default=None, help="keep the stores here (default: a temporary folder)")
    args = parser.parse_args(argv)
    import numpy as np

    from sellip.fit.shard_plan import SHARD_MEMORY, ShardMemory

    folder = args.out or Path(tempfile.mkdtemp(prefix="shard_memory_"))
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    smallest = min(args.vertices)
    first = folder / f"obs_{smallest}.zarr"
    if not first.exists():
        write_store(first, smallest, args.views)
    peak, seconds = peak_of_fit(first, folder / "compile.npz", args.chunk_size, folder / "jax_cache",
                                args.max_iterations)
    print(f"first job ({smallest} vertices, compiling the kernels): peak {peak / 1e6:.0f} MB, {seconds:.1f} s")
    print(f"{'vertices':>9} {'views':>5} {'peak MB':>9} {'model MB':>9} {'ratio':>6} {'fit s':>7}")
    for vertices in args.vertices:
        store = folder / f"obs_{vertices}.zarr"
        if not store.exists():
            write_store(store, vertices, args.views)
        peak, seconds = peak_of_fit(store, folder / f"fit_{vertices}.npz", args.chunk_size, folder / "jax_cache",
                                    args.max_iterations)
        predicted = SHARD_MEMORY.bytes(vertices, args.views, args.chunk_size)
        rows.append((vertices, peak))
        print(f"{vertices:>9} {args.views:>5} {peak / 1e6:>9.0f} {predicted / 1e6:>9.0f} {peak / predicted:>6.2f} "
              f"{seconds:>7.1f}", flush=True)
    if len(rows) >= 3:
        n = np.array([r[0] for r in rows], float)
        design = np.stack([np.ones_like(n), n * args.views, np.minimum(n, args.chunk_size) * args.views], 1)
        solution, *_ = np.linalg.lstsq(design, np.array([r[1] for r in rows]), rcond=None)
        fitted = ShardMemory(*map(float, solution))
        print(f"fitted: {fitted}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
