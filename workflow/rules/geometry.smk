# Geometry bootstrap (docs/design.md §2 sfm, mesh_init): camera poses, then the initial mesh.
# The numerics live in sellip.geometry.sfm and sellip.geometry; each rule calls one `sellip` command
# (sellip.stages.sfm, sellip.stages.init_mesh). sfm.mode decides whether poses.csv is used
# as is (known), checked against SfM (verify), or ignored (sfm); see docs/geometry.md.


rule run_sfm:
    input:
        hdr=f"{RESULTS}/hdr.zarr",
        capture=capture_file("capture.yaml"),
        # poses.csv (when the capture has one) is an input: adding, removing or editing it re-runs the poses.
        poses=poses_file(),
    output:
        cameras=f"{RESULTS}/cameras.csv",
        sfm=directory(f"{RESULTS}/sfm"),
    log:
        f"{RESULTS}/logs/run_sfm.log",
    benchmark:
        f"{RESULTS}/benchmarks/run_sfm.tsv"
    conda:
        "../../envs/geometry.yaml"
    threads: config["sfm"]["threads"]
    params:
        capture=lambda wildcards, input: Path(input.capture).parent,
        content=content_of(poses_file),
        # sellip.geometry.sfm.SfmOptions: the keys of config sfm that are set (threads: the job's).
        settings=section_settings("sfm", ("threads",)),
        silhouette_settings=settings_json(config["silhouette"]),
        seed=config["seed"],
    shell:
        sellip_shell(
            "sfm --hdr {input.hdr:q} --capture {params.capture:q} --cameras {output.cameras:q}"
            " --output {output.sfm:q} --settings {params.settings}"
            " --silhouette-settings {params.silhouette_settings} --seed {params.seed} --threads {threads} > {log:q} 2>&1"
        )


rule init_mesh:
    input:
        hdr=f"{RESULTS}/hdr.zarr",
        cameras=f"{RESULTS}/cameras.csv",
        sfm=f"{RESULTS}/sfm",
    output:
        mesh=f"{RESULTS}/mesh/init.ply",
        info=f"{RESULTS}/mesh/init.json",
    log:
        f"{RESULTS}/logs/init_mesh.log",
    benchmark:
        f"{RESULTS}/benchmarks/init_mesh.tsv"
    conda:
        "../../envs/geometry.yaml"
    threads: config["init"]["threads"]
    params:
        # sellip.geometry.hull.InitMeshOptions: the keys of config init that are set (mesh_path: user_mesh()).
        settings=section_settings("init", ("mesh_path", "threads")),
        mesh_path=" ".join(f"--mesh-path {shlex.quote(p)}" for p in user_mesh()),
        # init.mode mesh: the user's mesh by its content, so a changed scan re-runs what follows.
        content=content_of(user_mesh),
        silhouette_settings=settings_json(config["silhouette"]),
    shell:
        sellip_shell(
            "init-mesh --hdr {input.hdr:q} --cameras {input.cameras:q} --sfm {input.sfm:q}"
            " --output {output.mesh:q} --settings {params.settings} {params.mesh_path}"
            " --silhouette-settings {params.silhouette_settings} --threads {threads} > {log:q} 2>&1"
        )


rule refine_geometry:
    input:
        params=get_params,
        mesh=get_mesh,
        reference=f"{RESULTS}/mesh/init.ply",
        hdr=f"{RESULTS}/hdr.zarr",
        cameras=get_cameras,
        capture=capture_file("capture.yaml"),
        previous=lambda wildcards: [params_of(int(wildcards.it) - 1)] if int(wildcards.it) > 0 else [],
        poses=lambda wildcards: poses_summary_of(wildcards.it),
        passes=lambda wildcards: pass_through_inputs(wildcards.it),
    output:
        mesh=f"{RESULTS}/iter/{{it}}/mesh.ply",
        summary=f"{RESULTS}/iter/{{it}}/mesh.ply.json",
    log:
        f"{RESULTS}/logs/refine_geometry/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/refine_geometry/{{it}}.tsv"
    conda:
        "../../envs/geometry.yaml"
    params:
        # sellip.fit.geometry_jobs.GeometryUpdateSettings: the keys of config refine_geometry that are set, this
        # iteration's values.
        settings=lambda wildcards: section_settings("refine_geometry", it=wildcards.it),
        capture=lambda wildcards, input: Path(input.capture).parent,
        held_out=config["evaluate"]["held_out_views"],
        silhouette_settings=settings_json(config["silhouette"]),
        # sellip.fit.convergence.ConvergenceSettings: the keys of config converge that are set.
        convergence=section_settings("converge"),
        previous=lambda wildcards, input: (
            f"--previous-params {shlex.quote(input.previous[0])}" if input.previous else ""
        ),
        poses=lambda wildcards, input: f"--poses-summary {shlex.quote(input.poses[0])}" if input.poses else "",
        # Once the loop has converged: the previous iteration's mesh and summary, linked.
        pass_through=lambda wildcards, input, output: pass_through(
            wildcards.it, links=[(input.mesh, output.mesh), (summary_of(int(wildcards.it) - 1), output.summary)]
        ),
    shell:
        sellip_shell(
            "{params.pass_through} refine-geometry --params {input.params:q} --mesh {input.mesh:q} --output {output.mesh:q}"
            " --reference-mesh {input.reference:q} --settings {params.settings} --cameras {input.cameras:q}"
            " --hdr {input.hdr:q} --capture {params.capture:q} --exclude-views {params.held_out:q}"
            " --silhouette-settings {params.silhouette_settings} --iteration {wildcards.it} {params.previous}"
            " {params.poses} --convergence {params.convergence} > {log:q} 2>&1"
        )


rule refine_poses:
    # The cameras of iteration {it} (docs/geometry.md, "Poses refined against the object"): every view's pose
    # aligned to iteration it-1's model. Only in the DAG when refines_poses() (common.smk, cameras_of).
    input:
        params=lambda wildcards: params_of(int(wildcards.it) - 1),
        mesh=lambda wildcards: mesh_of(int(wildcards.it) - 1),
        cameras=lambda wildcards: cameras_of(int(wildcards.it) - 1),
        hdr=f"{RESULTS}/hdr.zarr",
        capture=capture_file("capture.yaml"),
        # Iteration it-1 passed through (the loop converged before it): its cameras, linked.
        passes=lambda wildcards: pass_through_inputs(int(wildcards.it) - 1),
    output:
        cameras=f"{RESULTS}/iter/{{it}}/cameras.csv",
        summary=f"{RESULTS}/iter/{{it}}/cameras.csv.json",
    log:
        f"{RESULTS}/logs/refine_poses/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/refine_poses/{{it}}.tsv"
    wildcard_constraints:
        it=r"[1-9]\d*",
    conda:
        "../../envs/geometry.yaml"
    params:
        capture=lambda wildcards, input: Path(input.capture).parent,
        # The PoseRefinementSettings fields of config refine_poses (enabled, after_iteration: cameras_of).
        settings=settings_json(
            {key: value for key, value in config["refine_poses"].items() if key not in ("enabled", "after_iteration")}
        ),
        pass_through=lambda wildcards, input, output: pass_through(
            int(wildcards.it) - 1,
            links=[(input.cameras, output.cameras)]
            + ([(f"{input.cameras}.json", output.summary)] if poses_summary_of(int(wildcards.it) - 1) else []),
            markers=[] if poses_summary_of(int(wildcards.it) - 1) else [output.summary],
        ),
    shell:
        sellip_shell(
            "{params.pass_through} refine-poses --params {input.params:q} --mesh {input.mesh:q} --cameras {input.cameras:q}"
            " --hdr {input.hdr:q} --capture {params.capture:q} --output {output.cameras:q} --settings {params.settings}"
            " > {log:q} 2>&1"
        )
