# Observations (docs/design.md §2 observe, per iteration): for every vertex of iteration {it}'s mesh and
# every view, visibility, bilinear HDR samples (I_d, I_alpha, I_s) and the geometry the fit needs.
# The numerics live in sellip.fit.observe; the rule calls `sellip observe` (sellip.stages.observe).
# The store is bulky (65 B per vertex and view before compression) and cheap to rebuild: temp().


rule gather_observations:
    input:
        mesh=get_mesh,
        cameras=get_cameras,
        hdr=f"{RESULTS}/hdr.zarr",
        capture=capture_file("capture.yaml"),
    output:
        temp(directory(f"{RESULTS}/iter/{{it}}/observations.zarr")),
    log:
        f"{RESULTS}/logs/gather_observations/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/gather_observations/{{it}}.tsv"
    wildcard_constraints:
        it=r"\d+",
    conda:
        "../../envs/geometry.yaml"
    threads: config["observe"]["threads"]
    params:
        capture=lambda wildcards, input: Path(input.capture).parent,
        vertex_chunk=config["observe"]["vertex_chunk"],
        view_chunk=config["observe"]["view_chunk"],
        occlusion_tolerance=config["observe"]["occlusion_tolerance"],
        shadow_offset=config["observe"]["shadow_offset"],
        min_cos=config["observe"]["min_cos"],
        edge_margin=config["observe"]["edge_margin"],
        silhouette_settings=settings_json(config["silhouette"]),
        max_slope=config["observe"]["max_slope"],
        missing_poses=config["observe"]["missing_poses"],
        held_out=config["evaluate"]["held_out_views"],
        max_views=(
            f"--max-views {config['observe']['max_views']}" if config["observe"].get("max_views") is not None else ""
        ),
    shell:
        sellip_shell(
            "observe --mesh {input.mesh:q} --cameras {input.cameras:q} --hdr {input.hdr:q}"
            " --capture {params.capture:q} --output {output:q} --vertex-chunk {params.vertex_chunk}"
            " --view-chunk {params.view_chunk} --occlusion-tolerance {params.occlusion_tolerance}"
            " --shadow-offset {params.shadow_offset} --min-cos {params.min_cos}"
            " --edge-margin {params.edge_margin} --silhouette-settings {params.silhouette_settings}"
            " --max-slope {params.max_slope}"
            " --missing-poses {params.missing_poses} --exclude-views {params.held_out:q} {params.max_views}"
            " --threads {threads} > {log:q} 2>&1"
        )
