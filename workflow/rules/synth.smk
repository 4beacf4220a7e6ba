# Synthetic captures with ground truth (sellip synth, docs/design.md §3). The built-in demo capture
# (config `demo`) is made here when `capture` is empty; any scene can be built by asking for
# captures/<scene>/capture.yaml. capture.yaml appears last: the folder is written whole or not at all.


rule synth_capture:
    output:
        capture="captures/{scene}/capture.yaml",
        frames="captures/{scene}/frames.csv",
        poses="captures/{scene}/poses.csv",
    log:
        "results/logs/synth_capture/{scene}.log",
    benchmark:
        "results/benchmarks/synth_capture/{scene}.tsv"
    conda:
        "../../envs/ingest.yaml"
    params:
        # sellip.capture.synthetic.DemoSettings: the keys of config demo that are set, as `sellip synth` options
        # (scene: the wildcard's; overrides: the workflow's).
        options=synth_options(),
    shell:
        sellip_shell(
            "synth --scene {wildcards.scene} --out captures/{wildcards.scene} {params.options}"
            " --no-progress > {log:q} 2>&1"
        )
