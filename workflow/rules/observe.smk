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
        passes=lambda wildcards: pass_through_inputs(wildcards.it),
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
        # sellip.fit.observe.ObserveSettings: the keys of config observe that are set (threads: the job's).
        settings=section_settings("observe", ("threads",)),
        silhouette_settings=settings_json(config["silhouette"]),
        held_out=config["evaluate"]["held_out_views"],
        # Once the loop has converged (sellip.fit.convergence): a marker folder, and no observations.
        pass_through=lambda wildcards, output: pass_through(wildcards.it, folders=[output[0]]),
    shell:
        sellip_shell(
            "{params.pass_through} observe --mesh {input.mesh:q} --cameras {input.cameras:q} --hdr {input.hdr:q}"
            " --capture {params.capture:q} --output {output:q} --settings {params.settings}"
            " --silhouette-settings {params.silhouette_settings} --exclude-views {params.held_out:q}"
            " --threads {threads} > {log:q} 2>&1"
        )
