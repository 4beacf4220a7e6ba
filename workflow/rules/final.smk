# The final model (docs/design.md §4), its renders and its figures of merit (docs/design.md §8).
# The last pass of the loop (iteration ITERATIONS) refits the pBRDF on the final geometry with
# its normals held (config `final.settings`); finalize_model writes it as model.ply + params.zarr,
# with each vertex's model (docs/design.md §7) from the last pass's store.


rule finalize_model:
    input:
        params=params_of(ITERATIONS),
        mesh=mesh_of(ITERATIONS),
        clusters=[f"{RESULTS}/iter/{ITERATIONS}/clusters"] if augmented(ITERATIONS) else [],
    output:
        model=f"{RESULTS}/final/model.ply",
        params=directory(f"{RESULTS}/final/params.zarr"),
    log:
        f"{RESULTS}/logs/finalize_model.log",
    benchmark:
        f"{RESULTS}/benchmarks/finalize_model.tsv"
    conda:
        "../../envs/fit.yaml"
    params:
        clusters=lambda wildcards, input: f"--clusters {shlex.join(input.clusters)}" if input.clusters else "",
        # sellip.fit.finalize.FinalSettings: the keys of config final that are set (settings: the final pass's fit).
        settings=section_settings("final", ("settings",)),
    shell:
        sellip_shell(
            "finalize --params {input.params:q} --mesh {input.mesh:q} --output-model {output.model:q}"
            " --output-params {output.params:q} {params.clusters} --settings {params.settings} > {log:q} 2>&1"
        )


rule render_outputs:
    input:
        model=f"{RESULTS}/final/model.ply",
        cameras=cameras_of(ITERATIONS),
        hdr=f"{RESULTS}/hdr.zarr",
        capture=capture_file("capture.yaml"),
    output:
        report(
            directory(f"{RESULTS}/final/renders"),
            patterns=["{image}.png"],
            caption="../report/renders.rst",
            category="Renders",
            labels={"image": "{image}"},
        ),
    log:
        f"{RESULTS}/logs/render_outputs.log",
    benchmark:
        f"{RESULTS}/benchmarks/render_outputs.tsv"
    conda:
        "../../envs/report.yaml"
    params:
        capture=lambda wildcards, input: Path(input.capture).parent,
        # sellip.report.outputs.EvaluateSettings: the keys of config evaluate this job takes that are set.
        settings=section_settings("evaluate", keys=("render_views", "supersample")),
    shell:
        sellip_shell(
            "render-outputs --model {input.model:q} --cameras {input.cameras:q} --hdr {input.hdr:q}"
            " --capture {params.capture:q} --output {output:q} --settings {params.settings} > {log:q} 2>&1"
        )


rule evaluate_model:
    input:
        model=f"{RESULTS}/final/model.ply",
        params=f"{RESULTS}/final/params.zarr",
        cameras=cameras_of(ITERATIONS),
        hdr=f"{RESULTS}/hdr.zarr",
        capture=capture_file("capture.yaml"),
        renders=f"{RESULTS}/final/renders",  # evaluated last: its timings cover every other stage
        meshes=[mesh_of(it) for it in range(ITERATIONS + 1)],
        fits=[f"{RESULTS}/iter/{it}/fit.zarr" for it in range(ITERATIONS)],
        poses=poses_file(),  # with sfm.mode sfm, the SfM cameras are aligned to poses.csv for the figures
        sfm=f"{RESULTS}/sfm",  # its report.json says where the cameras came from
        initial_cameras=f"{RESULTS}/cameras.csv",  # the poses stage's, measured beside the refined ones
    output:
        metrics=report(f"{RESULTS}/metrics.json", caption="../report/metrics.rst", category="Metrics"),
        timings=report(f"{RESULTS}/final/timings.png", caption="../report/timings.rst", category="Metrics"),
        convergence=report(
            f"{RESULTS}/final/geometry_convergence.png", caption="../report/convergence.rst", category="Metrics"
        ),
    log:
        f"{RESULTS}/logs/evaluate_model.log",
    benchmark:
        f"{RESULTS}/benchmarks/evaluate_model.tsv"
    conda:
        "../../envs/report.yaml"
    params:
        capture=lambda wildcards, input: Path(input.capture).parent,
        benchmarks=f"{RESULTS}/benchmarks",
        logs=f"{RESULTS}/logs",
        # sellip.report.outputs.EvaluateSettings: the keys of config evaluate this job takes that are set.
        settings=section_settings("evaluate", keys=("held_out_views", "metrics_supersample", "geometry_samples")),
        content=content_of(ground_truth_file, poses_file),  # the ground truth, by its content
    shell:
        sellip_shell(
            "evaluate --model {input.model:q} --params {input.params:q} --cameras {input.cameras:q}"
            " --hdr {input.hdr:q} --capture {params.capture:q} --benchmarks {params.benchmarks:q}"
            " --settings {params.settings} --output {output.metrics:q} --timings-plot {output.timings:q}"
            " --iteration-meshes {input.meshes:q} --iteration-fits {input.fits:q} --convergence-plot {output.convergence:q}"
            " --logs {params.logs:q} --sfm-report {input.sfm:q}/report.json --initial-cameras {input.initial_cameras:q}"
            " > {log:q} 2>&1"
        )


rule export_viewer:
    # The last rule (issue #40, docs/viewer.md): the per-material table, the glTF and map-PLY exports and the offline
    # browser viewer of the final model. After evaluate_model, so that the page is the run's last word.
    input:
        model=f"{RESULTS}/final/model.ply",
        params=f"{RESULTS}/final/params.zarr",
        cameras=cameras_of(ITERATIONS),
        hdr=f"{RESULTS}/hdr.zarr",
        capture=capture_file("capture.yaml"),
        metrics=f"{RESULTS}/metrics.json",
    output:
        materials=report(f"{RESULTS}/final/materials.csv", caption="../report/materials.rst", category="Metrics"),
        glb=f"{RESULTS}/final/model.glb",
        maps=directory(f"{RESULTS}/final/maps"),
        viewer=directory(f"{RESULTS}/viewer"),
    log:
        f"{RESULTS}/logs/export_viewer.log",
    benchmark:
        f"{RESULTS}/benchmarks/export_viewer.tsv"
    conda:
        "../../envs/report.yaml"
    params:
        results=lambda wildcards, output: Path(output.viewer).parent,
        capture=lambda wildcards, input: Path(input.capture).parent,
    shell:
        sellip_shell("view {params.results:q} --capture {params.capture:q} > {log:q} 2>&1")


RUN_STARTED = []
"""When the run's first job was about to start (onstart): last_run.json records it."""


onstart:
    # SIGTERM (kill, a scheduler's time limit) ends the run and its jobs within seconds (docs/reliability.md).
    workflow_support.end_jobs_on_sigterm(workflow.scheduler)
    RUN_STARTED.append(time.time())


onsuccess:
    workflow_support.record_run(RESULTS, "complete", started=(RUN_STARTED or [None])[0])
    # The run's warnings (a frame left out, a view without a pose), from the jobs' logs (docs/reliability.md).
    if warnings := workflow_support.format_warnings(workflow_support.collect_warnings(f"{RESULTS}/logs")):
        print(warnings)
    # Where everything is (README: the main command ends by saying so).
    if Path(f"{RESULTS}/metrics.json").is_file():
        import json

        metrics = json.loads(Path(f"{RESULTS}/metrics.json").read_text())
        normal = (metrics.get("normal_error_deg") or {}).get("all") or {}
        eta = metrics.get("eta_relative_error_pct") or {}
        psnr = (metrics.get("psnr_held_out") or {}).get("mean_db")
        print(
            f"\nsellip: reconstruction of {capture_dir()} in {RESULTS}/",
            "  model:    final/model.ply (+ final/params.zarr)",
            "  renders:  final/renders/ (index.json lists them)",
            "  metrics:  metrics.json, final/timings.png",
            f"  viewer:   open {Path(RESULTS).resolve()}/viewer/index.html in a browser (or: sellip view {RESULTS} --serve)",
            "  exports:  final/materials.csv, final/model.glb, final/maps/map_*.ply",
            "  report:   make report (or snakemake --report results/report.html)",
            sep="\n",
        )
        if normal:
            print(
                f"  normal error mean {normal['mean']:.2f} deg, eta error mean {eta.get('mean', float('nan')):.2f} %, "
                f"held-out PSNR {psnr if psnr is None else round(psnr, 1)} dB"
            )


onerror:
    # A failed job's own message (file, row, what was expected) on the console, not only in its log file; then,
    # when a model from an earlier run is on disk, that it no longer stands for the inputs (docs/reliability.md).
    workflow_support.record_run(RESULTS, "failed", log, started=(RUN_STARTED or [None])[0])
    for text in (
        workflow_support.format_failures(log),
        workflow_support.format_warnings(workflow_support.collect_warnings(f"{RESULTS}/logs")),
        *(f"sellip: {line}" for line in workflow_support.stale_model(RESULTS, capture_dir())),
    ):
        if text:
            print(text, file=sys.stderr)
