# Per-vertex fit (docs/design.md §2 fit / augment / refit, per iteration and vertex shard) and its gather step.
# Two passes per iteration, one set of rules: `fit` (warm-started from iteration it-1) and, when
# augmentation is on, `refit` (virtual specular samples from the iteration's cluster lobes).
# cluster_lobes also chooses each cluster's model (config `model_selection`, docs/design.md §7); the refit
# and the next iteration's passes fit every vertex with its model.
# The numerics live in sellip.fit and sellip.fit; each rule calls one `sellip` command.


rule fit_pbrdf:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        prior=get_fit_prior,
        lobes=get_lobes,
        passes=lambda wildcards: pass_through_inputs(wildcards.it),
    output:
        temp(f"{RESULTS}/iter/{{it}}/{{pass_}}/{{scatteritem}}.npz"),
    log:
        f"{RESULTS}/logs/fit_pbrdf/{{it}}/{{pass_}}/{{scatteritem}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/fit_pbrdf/{{it}}/{{pass_}}/{{scatteritem}}.tsv"
    conda:
        "../../envs/fit.yaml"
    threads: config["fit"]["threads"]
    resources:
        mem_mb=config["fit"]["mem_mb"],
    params:
        prior=lambda wildcards, input: f"--prior {shlex.join(input.prior)}" if input.prior else "",
        lobes=lambda wildcards, input: f"--lobes {shlex.join(input.lobes)}" if input.lobes else "",
        settings=fit_settings,
        model2_sigma_ss=model2_sigma_ss(),
        job_settings=fit_job_settings(),
        # Once the loop has converged (sellip.fit.convergence): a marker, and no fit.
        pass_through=lambda wildcards, output: pass_through(wildcards.it, markers=[output[0]]),
    shell:
        sellip_shell(
            "{params.pass_through} fit --observations {input.observations:q} --shard {wildcards.scatteritem}"
            " --output {output:q} {params.prior} {params.lobes} --job-settings {params.job_settings}"
            " --settings {params.settings} {params.model2_sigma_ss} --mem-mb {resources.mem_mb} > {log:q} 2>&1"
        )


rule gather_fit:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        shards=gather.fit(f"{RESULTS}/iter/{{{{it}}}}/{{{{pass_}}}}/{{scatteritem}}.npz"),
        passes=lambda wildcards: pass_through_inputs(wildcards.it, [previous_store(wildcards)]),
    output:
        directory(f"{RESULTS}/iter/{{it}}/{{pass_}}.zarr"),
    log:
        f"{RESULTS}/logs/gather_fit/{{it}}/{{pass_}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/gather_fit/{{it}}/{{pass_}}.tsv"
    conda:
        "../../envs/fit.yaml"
    params:
        job_settings=fit_job_settings(),
        # Once the loop has converged (sellip.fit.convergence): the previous iteration's store, linked.
        pass_through=lambda wildcards, output: pass_through(
            wildcards.it, links=[(previous_store(wildcards), output[0])]
        ),
    shell:
        sellip_shell(
            "{params.pass_through} gather-fit --observations {input.observations:q} --shards {input.shards:q}"
            " --output {output:q} --job-settings {params.job_settings} > {log:q} 2>&1"
        )


rule cluster_lobes:
    input:
        params=f"{RESULTS}/iter/{{it}}/fit.zarr",
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        passes=lambda wildcards: pass_through_inputs(wildcards.it, [f"{RESULTS}/iter/{int(wildcards.it) - 1}/clusters"]),
        # The previous pass's clusters: a material found there is kept on less evidence (hysteresis).
        previous=lambda wildcards: previous_clusters(wildcards.it),
    output:
        report(
            directory(f"{RESULTS}/iter/{{it}}/clusters"),
            patterns=["{name}.png"],
            caption="../report/lobes.rst",
            category="Augmentation",
            labels={"iteration": "{it}", "figure": "{name}"},
        ),
    log:
        f"{RESULTS}/logs/cluster_lobes/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/cluster_lobes/{{it}}.tsv"
    conda:
        "../../envs/fit.yaml"
    threads: config["fit"]["threads"]
    params:
        seed=config["seed"],
        # sellip.fit.clusters.AugmentSettings: the keys of config augment that are set (enabled, settings and
        # stability_resamples, the final pass's, are the workflow's).
        augment_settings=section_settings("augment", ("enabled", "stability_resamples", "settings")),
        resamples=lambda wildcards: config["augment"]["stability_resamples"] if int(wildcards.it) == ITERATIONS else 0,
        settings=cluster_settings,
        selection=model_selection_settings(),
        inherit=inherit_models,
        previous=lambda wildcards, input: (
            f"--previous-clusters {shlex.quote(input.previous[0])}" if input.previous else ""
        ),
        job_settings=fit_job_settings(),
        # Once the loop has converged (sellip.fit.convergence): the previous iteration's clusters, linked.
        pass_through=lambda wildcards, output: pass_through(
            wildcards.it, links=[(f"{RESULTS}/iter/{int(wildcards.it) - 1}/clusters", output[0])]
        ),
    shell:
        sellip_shell(
            "{params.pass_through} cluster-lobes --params {input.params:q} --observations {input.observations:q} --output {output:q}"
            " --seed {params.seed} --augment-settings {params.augment_settings}"
            " --stability-resamples {params.resamples}"
            " --settings {params.settings} --model-selection {params.selection} {params.inherit}"
            " {params.previous}"
            " --job-settings {params.job_settings} > {log:q} 2>&1"
        )
