# Per-vertex fit (DESIGN §2 fit / augment / refit, per iteration and vertex shard) and its gather step.
# Two passes per iteration, one set of rules: `fit` (warm-started from iteration it-1) and, when
# augmentation is on, `refit` (virtual specular samples from the iteration's cluster lobes).
# The numerics live in sellip.fit and sellip.augment; each rule calls one `sellip` command.


def fit_settings_args(wildcards):
    """`--set KEY=VALUE` for the FitSettings of this iteration and pass: config `fit.settings`
    (lists are per iteration), then `augment.settings` for a refit, then `final.settings` for the
    final pass (iteration ITERATIONS: normals from the final geometry, pBRDF only)."""
    it = int(wildcards.it)
    settings = {key: at_iteration(value, it) for key, value in config["fit"]["settings"].items()}
    if wildcards.pass_ == "refit":
        settings.update(config["augment"]["settings"])
    if it == ITERATIONS:
        settings.update(config["final"]["settings"])
    return " ".join(f"--set {key}={'null' if value is None else value}" for key, value in settings.items())


rule fit_pbrdf:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        prior=get_fit_prior,
        lobes=get_lobes,
    output:
        temp(f"{RESULTS}/iter/{{it}}/{{pass_}}/{{scatteritem}}.npz"),
    params:
        prior=lambda wildcards, input: f"--prior {input.prior}" if input.prior else "",
        lobes=lambda wildcards, input: f"--lobes {input.lobes}" if input.lobes else "",
        settings=fit_settings_args,
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
        SELLIP + " fit --observations {input.observations} --shard {wildcards.scatteritem}"
        " --output {output} {params.prior} {params.lobes} --dtype {params.dtype} {params.settings}"
        " --compilation-cache {params.cache} > {log} 2>&1"


rule gather_fit:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        shards=gather.fit(f"{RESULTS}/iter/{{{{it}}}}/{{{{pass_}}}}/{{scatteritem}}.npz"),
    output:
        directory(f"{RESULTS}/iter/{{it}}/{{pass_}}.zarr"),
    conda:
        "../../envs/fit.yaml"
    log:
        f"{RESULTS}/logs/gather_fit/{{it}}/{{pass_}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/gather_fit/{{it}}/{{pass_}}.tsv"
    shell:
        SELLIP + " gather-fit --observations {input.observations} --shards {input.shards}"
        " --output {output} > {log} 2>&1"


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
        cache=config["fit"]["compilation_cache"],
    threads: config["fit"]["threads"]
    conda:
        "../../envs/fit.yaml"
    log:
        f"{RESULTS}/logs/cluster_lobes/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/cluster_lobes/{{it}}.tsv"
    shell:
        SELLIP + " cluster-lobes --params {input.params} --observations {input.observations} --output {output}"
        " --seed {params.seed} --k-max {params.k_max} --max-samples {params.max_samples}"
        " --min-cluster-vertices {params.min_cluster_vertices} --compilation-cache {params.cache} > {log} 2>&1"
