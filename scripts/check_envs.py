"""Check the conda environment files of the rule families (envs/<family>.yaml) without conda.

    python scripts/check_envs.py            # structure + what each family's stage modules import
    python scripts/check_envs.py --resolve  # also `pip install --dry-run` of each env's pip list

Conda cannot be installed everywhere (the CI machine has no conda), so this checks what can be
checked without it: each file is valid YAML with python/pip and a pip list that installs
`sellip[<family>]` from ${SELLIP_ROOT}; its pins agree with pyproject.toml's ranges; importing
each stage module of the family loads no heavy library outside the family's extra; and, with
--resolve, pip resolves the pip list (SELLIP_ROOT set to this checkout) for this Python.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]

# Rule family -> the `sellip.stages` modules its rules run (workflow/rules/*.smk, sellip.cli.COMMANDS).
FAMILIES: dict[str, dict[str, list[str]]] = {
    "ingest": {"rules": ["synth_capture", "linearize_frames", "merge_hdr", "plot_hdr_previews"],
               "modules": ["synth", "linearize", "merge_hdr", "hdr_previews"]},
    "geometry": {"rules": ["run_sfm", "init_mesh", "gather_observations", "refine_geometry", "refine_poses"],
                 "modules": ["sfm", "init_mesh", "observe", "refine_geometry", "refine_poses"]},
    "fit": {"rules": ["fit_pbrdf", "gather_fit", "cluster_lobes", "finalize_model"],
            "modules": ["fit", "gather_fit", "cluster_lobes", "finalize"]},
    "report": {"rules": ["render_outputs", "evaluate_model", "export_viewer"],
               "modules": ["render_outputs", "evaluate", "view"]},
}

# Import name -> distribution name, for the libraries that a family may or may not install.
HEAVY = {"jax": "jax", "jaxlib": "jaxlib", "scipy": "scipy", "zarr": "zarr", "pandas": "pandas",
         "pandera": "pandera", "open3d": "open3d", "pycolmap": "pycolmap", "pymeshlab": "pymeshlab",
         "rawpy": "rawpy", "tifffile": "tifffile", "imageio": "imageio", "matplotlib": "matplotlib",
         "sklearn": "scikit-learn", "tqdm": "tqdm", "snakemake": "snakemake", "mitsuba": "mitsuba",
         "cv2": "opencv-python-headless", "polanalyser": "polanalyser"}


def requirement_name(spec: str) -> str:
    return re.split(r"[\[<>=!~; ]", spec, maxsplit=1)[0].lower().replace("_", "-")


def pyproject_requirements() -> tuple[list[str], dict[str, list[str]]]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    return project["dependencies"], project["optional-dependencies"]


def allowed_distributions(family: str) -> set[str]:
    core, extras = pyproject_requirements()
    return {requirement_name(r) for r in core + extras[family]}


def check_env_file(family: str) -> list[str]:
    """Problems with envs/<family>.yaml (empty when fine)."""
    path = REPO / "envs" / f"{family}.yaml"
    if not path.exists():
        return [f"{path} is missing"]
    env = yaml.safe_load(path.read_text())
    problems = []
    deps = env.get("dependencies") or []
    conda = [d for d in deps if isinstance(d, str)]
    pip = next((d["pip"] for d in deps if isinstance(d, dict) and "pip" in d), None)
    if not any(d.split("=")[0] == "python" for d in conda):
        problems.append(f"{path.name}: no python in the conda dependencies")
    if "pip" not in conda:
        problems.append(f"{path.name}: pip must be a conda dependency when the file has a pip section")
    if not pip:
        return problems + [f"{path.name}: no pip section"]
    if f"-e ${{SELLIP_ROOT}}[{family}]" not in pip:
        problems.append(f"{path.name}: the pip list must install `-e ${{SELLIP_ROOT}}[{family}]`")
    core, extras = pyproject_requirements()
    ranges = {requirement_name(r): r for r in core + extras[family]}
    for spec in pip:
        if spec.startswith("-"):
            continue
        name = requirement_name(spec)
        if name not in ranges:
            problems.append(f"{path.name}: {spec} is not a dependency of sellip[{family}] in pyproject.toml")
            continue
        pinned = re.search(r"==\s*([^\s;]+)", spec)
        if not pinned:
            problems.append(f"{path.name}: {spec} is not pinned (==)")
            continue
        from packaging.requirements import Requirement
        if not Requirement(ranges[name]).specifier.contains(pinned.group(1), prereleases=True):
            problems.append(f"{path.name}: {spec} is outside pyproject.toml's {ranges[name]}")
    missing = set(ranges) - {requirement_name(s) for s in pip if not s.startswith("-")}
    if missing:
        problems.append(f"{path.name}: not pinned (pip resolves them from pyproject.toml): {sorted(missing)}")
    return problems


def imported_heavy(module: str) -> set[str] | None:
    """Heavy libraries (HEAVY's import names) loaded by `import sellip.stages.<module>`; None when
    the module does not exist (yet)."""
    code = ("import importlib.util, json, sys\n"
            f"if importlib.util.find_spec('sellip.stages.{module}') is None: print('null'); sys.exit()\n"
            f"import sellip.stages.{module}\n"
            "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                         env={**os.environ, "PYTHONPATH": str(REPO / "src")}, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"import sellip.stages.{module} failed:\n{out.stderr[-2000:]}")
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    return None if loaded is None else set(loaded) & set(HEAVY)


def check_imports(family: str) -> tuple[list[str], dict[str, list[str]]]:
    allowed = allowed_distributions(family)
    problems, seen = [], {}
    for module in FAMILIES[family]["modules"]:
        heavy = imported_heavy(module)
        if heavy is None:
            seen[module] = ["(not in this checkout yet)"]
            continue
        seen[module] = sorted(heavy)
        outside = sorted(name for name in heavy if HEAVY[name] not in allowed)
        if outside:
            problems.append(f"import sellip.stages.{module} loads {outside}, which envs/{family}.yaml does not install")
    return problems, seen


def resolve(family: str) -> list[str]:
    """`pip install --dry-run` of the env's pip list for this Python (SELLIP_ROOT = this checkout)."""
    env = yaml.safe_load((REPO / "envs" / f"{family}.yaml").read_text())
    pip = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict) and "pip" in d)
    with tempfile.TemporaryDirectory() as tmp:
        requirements = Path(tmp) / "requirements.txt"
        requirements.write_text("\n".join(pip) + "\n")
        report = Path(tmp) / "report.json"
        out = subprocess.run([sys.executable, "-m", "pip", "install", "--dry-run", "--ignore-installed", "--quiet",
                              "--report", str(report), "-r", str(requirements)],
                             capture_output=True, text=True, env={**os.environ, "SELLIP_ROOT": str(REPO)}, check=False)
        if out.returncode != 0:
            return [f"envs/{family}.yaml: pip cannot resolve its pip list:\n{out.stderr[-3000:]}"]
        installs = json.loads(report.read_text())["install"]
        print(f"  {family}: pip resolves {len(installs)} distributions")
    return []


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolve", action="store_true", help="also resolve each pip list with pip --dry-run")
    args = parser.parse_args(argv)
    problems = []
    if (REPO / "envs" / "sellip.yaml").exists():
        problems.append("envs/sellip.yaml is still there: the family environments replace it")
    for family in FAMILIES:
        problems += check_env_file(family)
        import_problems, seen = check_imports(family)
        problems += import_problems
        print(f"{family}: " + "; ".join(f"{m}: {', '.join(h) or '-'}" for m, h in seen.items()))
        if args.resolve:
            problems += resolve(family)
    for problem in problems:
        print("PROBLEM:", problem, file=sys.stderr)
    print("envs OK" if not problems else f"{len(problems)} problem(s)")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
