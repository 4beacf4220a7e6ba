# Geometry bootstrap (DESIGN §2 sfm, mesh_init): camera poses, then the initial mesh.
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
        mode=config["sfm"]["mode"],
        matching=config["sfm"]["matching"],
        exhaustive_max_views=config["sfm"]["exhaustive_max_views"],
        retrieval_neighbors=config["sfm"]["retrieval_neighbors"],
        max_features=config["sfm"]["max_features"],
        feature_object_px=config["sfm"]["feature_object_px"],
        max_upscale=config["sfm"]["max_upscale"],
        refine_intrinsics="--refine-intrinsics" if config["sfm"]["refine_intrinsics"] else "",
        min_registered_fraction=config["sfm"]["min_registered_fraction"],
        mask_threshold=config["sfm"]["mask_threshold"],
        seed=config["seed"],
    shell:
        sellip_shell(
            "sfm --hdr {input.hdr:q} --capture {params.capture:q} --cameras {output.cameras:q}"
            " --output {output.sfm:q} --mode {params.mode} --matching {params.matching}"
            " --exhaustive-max-views {params.exhaustive_max_views} --retrieval-neighbors {params.retrieval_neighbors}"
            " --max-features {params.max_features} --feature-object-px {params.feature_object_px}"
            " --max-upscale {params.max_upscale} {params.refine_intrinsics}"
            " --min-registered-fraction {params.min_registered_fraction} --mask-threshold {params.mask_threshold}"
            " --seed {params.seed} --threads {threads} > {log:q} 2>&1"
        )


rule init_mesh:
    input:
        hdr=f"{RESULTS}/hdr.zarr",
        cameras=f"{RESULTS}/cameras.csv",
        sfm=f"{RESULTS}/sfm",
        # init.mode mesh: the user's mesh is an input, so a changed scan re-runs what follows.
        user_mesh=user_mesh(),
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
        mode=config["init"]["mode"],
        mesh_path=lambda wildcards, input: " ".join(f"--mesh-path {shlex.quote(p)}" for p in input.user_mesh),
        hull_resolution=config["init"]["hull_resolution"],
        min_inside_fraction=config["init"]["min_inside_fraction"],
        poisson_depth=config["init"]["poisson_depth"],
        target_depth=config["init"]["target_depth"],
        max_vertices=config["init"]["max_vertices"],
        mask_threshold=config["sfm"]["mask_threshold"],
    shell:
        sellip_shell(
            "init-mesh --hdr {input.hdr:q} --cameras {input.cameras:q} --sfm {input.sfm:q}"
            " --output {output.mesh:q} --mode {params.mode} {params.mesh_path} --hull-resolution {params.hull_resolution}"
            " --min-inside-fraction {params.min_inside_fraction} --poisson-depth {params.poisson_depth}"
            " --target-depth {params.target_depth} --max-vertices {params.max_vertices}"
            " --mask-threshold {params.mask_threshold} --threads {threads} > {log:q} 2>&1"
        )


rule refine_geometry:
    input:
        params=get_params,
        mesh=get_mesh,
        reference=f"{RESULTS}/mesh/init.ply",
        hdr=f"{RESULTS}/hdr.zarr",
        cameras=get_cameras,
        capture=capture_file("capture.yaml"),
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
        smoothness=lambda wildcards: at_iteration(config["refine_geometry"]["smoothness"], wildcards.it),
        smoothness_unconfident=lambda wildcards: at_iteration(
            config["refine_geometry"]["smoothness_unconfident"], wildcards.it
        ),
        anchor=lambda wildcards: at_iteration(config["refine_geometry"]["anchor"], wildcards.it),
        rounds=config["refine_geometry"]["rounds"],
        silhouette=lambda wildcards: at_iteration(config["refine_geometry"]["silhouette"], wildcards.it),
        capture=lambda wildcards, input: Path(input.capture).parent,
        held_out=config["evaluate"]["held_out_views"],
        mask_threshold=config["sfm"]["mask_threshold"],
    shell:
        sellip_shell(
            "refine-geometry --params {input.params:q} --mesh {input.mesh:q} --output {output.mesh:q}"
            " --reference-mesh {input.reference:q} --smoothness {params.smoothness}"
            " --smoothness-unconfident {params.smoothness_unconfident} --anchor {params.anchor} --rounds {params.rounds}"
            " --silhouette {params.silhouette} --cameras {input.cameras:q} --hdr {input.hdr:q} --capture {params.capture:q}"
            " --exclude-views {params.held_out:q} --mask-threshold {params.mask_threshold} > {log:q} 2>&1"
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
        blur_px=" ".join(str(float(b)) for b in config["refine_poses"]["blur_px"]),
        rounds=config["refine_poses"]["rounds"],
        max_rotation_deg=config["refine_poses"]["max_rotation_deg"],
        max_shift_fraction=config["refine_poses"]["max_shift_fraction"],
        min_motion_px=config["refine_poses"]["min_motion_px"],
    shell:
        sellip_shell(
            "refine-poses --params {input.params:q} --mesh {input.mesh:q} --cameras {input.cameras:q}"
            " --hdr {input.hdr:q} --capture {params.capture:q} --output {output.cameras:q} --blur-px {params.blur_px}"
            " --rounds {params.rounds} --max-rotation-deg {params.max_rotation_deg}"
            " --max-shift-fraction {params.max_shift_fraction} --min-motion-px {params.min_motion_px} > {log:q} 2>&1"
        )
