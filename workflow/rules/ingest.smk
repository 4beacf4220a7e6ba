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
        # sellip.capture.ingest.IngestSettings: the keys of config ingest that are set. A function: a value
        # `capture` would read to `snakemake --lint` as a hard-coded prefix of captures/.
        settings=lambda wildcards: section_settings("ingest", ("threads",)),
    shell:
        sellip_shell(
            "linearize --capture {params.capture:q} --output {output:q} --threads {threads}"
            " --settings {params.settings} > {log:q} 2>&1"
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
        # sellip.capture.ingest.IngestSettings (merge-hdr reads flash_ratio_tolerance).
        settings=section_settings("ingest", ("threads",)),
    shell:
        sellip_shell(
            "merge-hdr --linear {input:q} --output {output:q} --threads {threads}"
            " --settings {params.settings} > {log:q} 2>&1"
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
