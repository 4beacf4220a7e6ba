# Config validation, wildcard constraints and the input functions every rule family shares.
import shlex
import shutil
import sys
from pathlib import Path

from snakemake.utils import validate


validate(config, "../../config/config.schema.yaml")


wildcard_constraints:
    name=r"[A-Za-z0-9_.-]+",
    scene=r"[A-Za-z0-9_]+",
    it=r"\d+",


DEMO_CAPTURE = f"captures/{config['demo']['scene']}"


def capture_dir():
    """The capture folder: config `capture`, or the built-in demo (made by rule synth_capture)."""
    return config["capture"] or DEMO_CAPTURE


def capture_file(name):
    """A file of the capture; for the built-in demo it is an output of synth_capture."""
    return str(Path(capture_dir()) / name)


RESULTS = f"results/{config['name']}"

# The command every rule runs: `sellip` when it is on PATH (an activated venv, or a conda env
# made with --sdm conda), else the sellip of the Python that runs Snakemake (.venv/bin/snakemake).
SELLIP = "sellip" if shutil.which("sellip") else f"{shlex.quote(sys.executable)} -m sellip.cli"


def get_mesh(wildcards):
    """The mesh of iteration `it`: the initial mesh at 0, else the Poisson mesh of iteration it-1."""
    it = int(wildcards.it)
    return f"{RESULTS}/mesh/init.ply" if it == 0 else f"{RESULTS}/iter/{it - 1}/mesh.ply"


def get_prior(wildcards):
    """The previous iteration's parameters (warm start), or nothing at iteration 0."""
    it = int(wildcards.it)
    return [] if it == 0 else [f"{RESULTS}/iter/{it - 1}/params.zarr"]


def get_final_outputs():
    """What `rule all` builds: every stage that exists so far, on the configured capture."""
    return [capture_file("capture.yaml"), f"{RESULTS}/hdr.zarr", f"{RESULTS}/previews",
            f"{RESULTS}/cameras.csv", f"{RESULTS}/mesh/init.ply", f"{RESULTS}/iter/0/params.zarr"]
