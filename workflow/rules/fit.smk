# Per-vertex fit (DESIGN §2 fit, per iteration and vertex shard) and its gather step.
# The numerics live in sellip.fit; each rule calls one `sellip` command.


def fit_settings_args(wildcards):
    """`--set KEY=VALUE` for every FitSettings value in config `fit.settings`."""
    return " ".join(f"--set {key}={'null' if value is None else value}"
                    for key, value in config["fit"]["settings"].items())


rule fit_pbrdf:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        prior=get_prior,
    output:
        temp(f"{RESULTS}/iter/{{it}}/fit/{{scatteritem}}.npz"),
    params:
        prior=lambda wildcards, input: f"--prior {input.prior}" if input.prior else "",
        settings=fit_settings_args,
        dtype=config["fit"]["dtype"],
        cache=config["fit"]["compilation_cache"],
    threads: config["fit"]["threads"]
    resources:
        mem_mb=config["fit"]["mem_mb"],
    conda:
        "../../envs/sellip.yaml"
    log:
        f"{RESULTS}/logs/fit_pbrdf/{{it}}/{{scatteritem}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/fit_pbrdf/{{it}}/{{scatteritem}}.tsv"
    shell:
        SELLIP + " fit --observations {input.observations} --shard {wildcards.scatteritem}"
        " --output {output} {params.prior} --dtype {params.dtype} {params.settings}"
        " --compilation-cache {params.cache} > {log} 2>&1"


rule gather_fit:
    input:
        observations=f"{RESULTS}/iter/{{it}}/observations.zarr",
        shards=gather.fit(f"{RESULTS}/iter/{{{{it}}}}/fit/{{scatteritem}}.npz"),
    output:
        directory(f"{RESULTS}/iter/{{it}}/params.zarr"),
    conda:
        "../../envs/sellip.yaml"
    log:
        f"{RESULTS}/logs/gather_fit/{{it}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/gather_fit/{{it}}.tsv"
    shell:
        SELLIP + " gather-fit --observations {input.observations} --shards {input.shards}"
        " --output {output} > {log} 2>&1"
