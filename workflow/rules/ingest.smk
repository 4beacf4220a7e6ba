# Ingest (docs/design.md §2): raw frames -> linear analyzer images -> one HDR image per view, plus previews.
# The numerics live in sellip.capture.ingest; each rule calls one `sellip` command (sellip.stages.*).


rule linearize_frames:
    input:
        capture=capture_file("capture.yaml"),
        frames=capture_file("frames.csv"),
    output:
        temp(directory(f"{RESULTS}/ingest/linear.zarr")),
    log:
        f"{RESULTS}/logs/linearize_frames.log",
    benchmark:
        f"{RESULTS}/benchmarks/linearize_frames.tsv"
    conda:
        "../../envs/ingest.yaml"
    threads: config["ingest"]["threads"]
    params:
        capture=lambda wildcards, input: Path(input.capture).parent,
        # The content of every file ingest reads: a replaced, added or removed frame re-runs ingest and what follows.
        content=content_of(lambda: [capture_file("capture.yaml"), capture_file("frames.csv")], raw_frames),
        saturation=config["ingest"]["saturation"],
        # A function: its value `capture` would read to `snakemake --lint` as a hard-coded prefix of captures/.
        black_level_from=lambda wildcards: config["ingest"]["black_level_from"],
        bad_frames=config["ingest"].get("bad_frames", "error"),
    shell:
        sellip_shell(
            "linearize --capture {params.capture:q} --output {output:q} --threads {threads}"
            " --saturation {params.saturation} --black-level-from {params.black_level_from}"
            " --bad-frames {params.bad_frames} > {log:q} 2>&1"
        )


rule merge_hdr:
    input:
        f"{RESULTS}/ingest/linear.zarr",
    output:
        directory(f"{RESULTS}/hdr.zarr"),
    log:
        f"{RESULTS}/logs/merge_hdr.log",
    benchmark:
        f"{RESULTS}/benchmarks/merge_hdr.tsv"
    conda:
        "../../envs/ingest.yaml"
    threads: config["ingest"]["threads"]
    params:
        flash_ratio_tolerance=config["ingest"]["flash_ratio_tolerance"],
    shell:
        sellip_shell(
            "merge-hdr --linear {input:q} --output {output:q} --threads {threads}"
            " --flash-ratio-tolerance {params.flash_ratio_tolerance} > {log:q} 2>&1"
        )


rule plot_hdr_previews:
    input:
        f"{RESULTS}/hdr.zarr",
    output:
        report(
            directory(f"{RESULTS}/previews"),
            patterns=["{view}_{kind}.png"],
            caption="../report/hdr_previews.rst",
            category="Ingest",
            subcategory="{kind}",
            labels={"view": "{view}", "image": "{kind}"},
        ),
    log:
        f"{RESULTS}/logs/plot_hdr_previews.log",
    benchmark:
        f"{RESULTS}/benchmarks/plot_hdr_previews.tsv"
    conda:
        "../../envs/ingest.yaml"
    shell:
        sellip_shell("hdr-previews --hdr {input:q} --output {output:q} > {log:q} 2>&1")
