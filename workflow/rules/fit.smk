# Per-vertex fit (docs/design.md §2 fit / augment / refit, per iteration and vertex shard) and its gather step.
# Two passes per iteration, one set of rules: `fit` (warm-started from iteration it-1) and, when
# augmentation is on, `refit` (virtual specular samples from the iteration's cluster lobes).
# cluster_lobes also chooses each cluster's model (config `model_selection`, docs/design.md §7); the refit
# and the next iteration's passes fit every vertex with its model.
# The numerics live in sellip.fit and sellip.fit; each rule calls one `sellip` command.


def fit_settings(wildcards):
    """`--settings` (sellip.fit.records.FitSettings as JSON) of this iteration and pass: config `fit.settings`
    (lists are per iteration), then `augment.settings` for a pass with virtual samples (a refit, and the final
    pass's first fit: get_lobes), then `final.settings` for the final pass (iteration ITERATIONS: normals from the
    final geometry, pBRDF only)."""
    it = int(wildcards.it)
    settings = {key: at_iteration(value, it) for key, value in config["fit"]["settings"].items()}
    if get_lobes(wildcards):
        settings.update(config["augment"]["settings"])
    if it == ITERATIONS:
        settings.update(config["final"]["settings"])
    return settings_json(settings)


def cluster_settings(wildcards):
    """`--settings` of the cluster lobe fits of this iteration: config `fit.settings` (its loss weights, view
    selection, and the most complex model allowed: `lobes`, `sigma_ss_fixed`)."""
    it = int(wildcards.it)
    return settings_json({key: at_iteration(value, it) for key, value in config["fit"]["settings"].items()})


MODEL_SELECTION_WORKFLOW_KEYS = ("every",)
"""Keys of config `model_selection` that the workflow reads itself; the others are SelectionSettings fields."""


def model_selection_settings():
    """`--model-selection` (sellip.fit.selection.SelectionSettings as JSON): config `model_selection`."""
    return settings_json({key: value for key, value in config["model_selection"].items()
                          if key not in MODEL_SELECTION_WORKFLOW_KEYS})


def inherit_models(wildcards):
    """`--inherit-models` where cluster_lobes fits no candidate: candidates are fitted at iteration 0, every
    `model_selection.every`-th iteration and the final pass; the others inherit their vertices' models."""
    it = int(wildcards.it)
    return "--inherit-models" if it % int(config["model_selection"]["every"]) and it != ITERATIONS else ""


def model2_sigma_ss():
    """`--model2-sigma-ss` of the fit jobs where config `model_selection.model2_sigma_ss` is set (else the job takes
    its declared default)."""
    value = config["model_selection"].get("model2_sigma_ss")
    return "" if value is None else f"--model2-sigma-ss {float(value)}"


rule fit_pbrdf:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        prior=get_fit_prior,
        lobes=get_lobes,
    output:
        temp(f"{RESULTS}/iter/{{it}}/{{pass_}}/{{scatteritem}}.npz"),
    params:
        prior=lambda wildcards, input: f"--prior {shlex.join(input.prior)}" if input.prior else "",
        lobes=lambda wildcards, input: f"--lobes {shlex.join(input.lobes)}" if input.lobes else "",
        settings=fit_settings,
        model2_sigma_ss=model2_sigma_ss(),
        dtype=config["fit"]["dtype"],
        cache=config["fit"]["compilation_cache"],
    threads: config["fit"]["threads"]
    resources:
        mem_mb=config["fit"]["mem_mb"],
    conda:
        "../../envs/fit.yaml"
    log:
        f"{RESULTS}/logs/fit_pbrdf/{{it}}/{{pass_}}/{{scatteritem}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/fit_pbrdf/{{it}}/{{pass_}}/{{scatteritem}}.tsv"
    shell:
        SELLIP + " fit --observations {input.observations:q} --shard {wildcards.scatteritem}"
        " --output {output:q} {params.prior} {params.lobes} --dtype {params.dtype} --settings {params.settings}"
        " {params.model2_sigma_ss} --compilation-cache {params.cache:q} --mem-mb {resources.mem_mb}"
        " > {log:q} 2>&1"


rule gather_fit:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        shards=gather.fit(f"{RESULTS}/iter/{{{{it}}}}/{{{{pass_}}}}/{{scatteritem}}.npz"),
    output:
        directory(f"{RESULTS}/iter/{{it}}/{{pass_}}.zarr"),
    params:
        min_fitted_share=config["fit"]["min_fitted_share"],
    conda:
        "../../envs/fit.yaml"
    log:
        f"{RESULTS}/logs/gather_fit/{{it}}/{{pass_}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/gather_fit/{{it}}/{{pass_}}.tsv"
    shell:
        SELLIP + " gather-fit --observations {input.observations:q} --shards {input.shards:q}"
        " --output {output:q} --min-fitted-share {params.min_fitted_share} > {log:q} 2>&1"


rule cluster_lobes:
    input:
        params=f"{RESULTS}/iter/{{it}}/fit.zarr",
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
    output:
        report(
            directory(f"{RESULTS}/iter/{{it}}/clusters"),
            patterns=["{name}.png"],
            caption="../report/lobes.rst",
            category="Augmentation",
            labels={"iteration": "{it}", "figure": "{name}"},
        ),
    params:
        seed=config["seed"],
        k_max=config["augment"]["k_max"],
        max_samples=config["augment"]["max_samples"],
        min_cluster_vertices=config["augment"]["min_cluster_vertices"],
        min_coherence=config["augment"]["min_coherence"],
        pool_min_coherence=config["augment"]["pool_min_coherence"],
        resamples=lambda wildcards: config["augment"]["stability_resamples"] if int(wildcards.it) == ITERATIONS else 0,
        settings=cluster_settings,
        selection=model_selection_settings(),
        inherit=inherit_models,
        cache=config["fit"]["compilation_cache"],
    threads: config["fit"]["threads"]
    conda:
        "../../envs/fit.yaml"
    log:
        f"{RESULTS}/logs/cluster_lobes/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/cluster_lobes/{{it}}.tsv"
    shell:
        SELLIP + " cluster-lobes --params {input.params:q} --observations {input.observations:q} --output {output:q}"
        " --seed {params.seed} --k-max {params.k_max} --max-samples {params.max_samples}"
        " --min-cluster-vertices {params.min_cluster_vertices} --min-coherence {params.min_coherence}"
        " --pool-min-coherence {params.pool_min_coherence} --stability-resamples {params.resamples}"
        " --settings {params.settings} --model-selection {params.selection} {params.inherit}"
        " --compilation-cache {params.cache:q} > {log:q} 2>&1"
