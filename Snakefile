# sellip: sparse ellipsometry as a Snakemake workflow (see README.md and docs/design.md).
# This file only wires things together: config, includes, the default target.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"


# Vertex shards of the per-vertex fit: config fit.shards, raised to what fit.mem_mb holds (FIT_SHARDS, common.smk;
# --set-scatter fit=N sets it outright); each shard job derives its vertex range at run time.
scattergather:
    fit=FIT_SHARDS,


include: "workflow/rules/synth.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/geometry.smk"
include: "workflow/rules/observe.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/final.smk"


rule all:
    default_target: True
    input:
        get_final_outputs(),
