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
        views=config["demo"]["views"],
        width=config["demo"]["width"],
        height=config["demo"]["height"],
        seed=config["demo"]["seed"],
        noise_scale=config["demo"].get("noise_scale", 1.0),
        renderer=config["demo"].get("renderer", "sellip"),
    shell:
        sellip_shell(
            "synth --scene {wildcards.scene} --out captures/{wildcards.scene}"
            " --views {params.views:q} --width {params.width} --height {params.height}"
            " --seed {params.seed} --noise-scale {params.noise_scale} --renderer {params.renderer:q}"
            " --no-progress > {log:q} 2>&1"
        )
