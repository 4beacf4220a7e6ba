# sellip: sparse ellipsometry as a Snakemake workflow (see README.md and DESIGN).
# This file only wires things together: config, includes, the default target.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/synth.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/geometry.smk"
include: "workflow/rules/observe.smk"


rule all:
    input:
        get_final_outputs(),
    default_target: True
