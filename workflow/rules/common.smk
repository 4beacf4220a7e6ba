# Config validation, wildcard constraints and the input functions every rule family shares.
import json
import os
import shlex
import shutil
import sys
import time
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.settings.types import DeploymentMethod
from snakemake.utils import validate


def _unless_set(current, user, overrides):
    """``current`` with ``overrides`` applied wherever the user has not set the key (``user``: the settings the
    user gave, nested dicts key by key): the user's own settings always win, also where they equal a default."""
    merged = dict(current)
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(current.get(key), dict):
            merged[key] = _unless_set(current[key], (user or {}).get(key) or {}, value)
        elif key not in (user or {}):
            merged[key] = value
    return merged


def _user_settings():
    """What the user set: the config files given on the command line other than config/config.yaml itself, then
    ``--config`` (Snakemake's own merge)."""
    from snakemake.common.configfile import load_configfile
    from snakemake.utils import update_config

    defaults = (Path(workflow.basedir) / "config" / "config.yaml").resolve()
    user = {}
    for path in workflow.config_settings.configfiles:
        if Path(path).resolve() != defaults:
            update_config(user, load_configfile(path))
    update_config(user, dict(workflow.config_settings.config or {}))
    return user


try:
    from sellip import workflow_support
except ImportError:  # a Snakemake whose Python lacks sellip (e.g. --sdm conda): this checkout's own
    sys.path.append(str(Path(workflow.basedir) / "src"))
    from sellip import workflow_support

CONFIG_SCHEMA = workflow_support.load_yaml(Path(workflow.basedir) / "config" / "config.schema.yaml")

# Every key, at every level, must be a setting: a typo (`iteratons=2`, `fit={shard: 3}`) or a renamed key stops here,
# naming the key and the nearest valid one (docs/reliability.md), instead of running with the default.
try:
    workflow_support.check_config_keys(config, CONFIG_SCHEMA)
except ValueError as exc:
    raise WorkflowError(str(exc)) from None

# --config values nested in a mapping arrive as strings (`augment={min_coherence: 0}` gives '0'): read them as the
# numbers, booleans and nulls the schema expects there (docs/reliability.md).
config.update(workflow_support.coerce_to_schema(dict(config), CONFIG_SCHEMA))

# A key given twice in a config file: Snakemake's reader keeps the second value without a word.
try:
    workflow_support.check_config_files(
        dict.fromkeys([Path(workflow.basedir) / "config" / "config.yaml", *workflow.config_settings.configfiles])
    )
except ValueError as exc:
    raise WorkflowError(str(exc)) from None

# results/NAME/ must be one folder inside results/: name=.. or name=a/b would write elsewhere.
try:
    workflow_support.check_results_name(config.get("name"))
except ValueError as exc:
    raise WorkflowError(str(exc)) from None

# The built-in demo (no `capture` given) runs with config `demo.overrides` in place of the defaults:
# a laptop-sized model of a small, low-resolution capture; a user's capture gets the defaults.
if not config["capture"]:
    config.update(_unless_set(config, _user_settings(), config["demo"].get("overrides") or {}))

# init.mode mesh without a mesh: say so in words (the schema's own message would be "'' is too short").
if (config.get("init") or {}).get("mode") == "mesh" and not (config.get("init") or {}).get("mesh_path"):
    raise WorkflowError(
        "config: init.mode 'mesh' needs init.mesh_path, the mesh file to start from (PLY or OBJ, "
        "in the world of the poses, metres; relative to the capture folder unless absolute)"
    )

validate(config, "../../config/config.schema.yaml")

# Views named in the config must be the capture's: a wrong id would surface as a store problem in a later job.
if config["capture"]:
    try:
        workflow_support.check_config_views(
            config["evaluate"], workflow_support.capture_view_ids(config["capture"]), config["capture"]
        )
    except ValueError as exc:
        raise WorkflowError(str(exc)) from None


wildcard_constraints:
    name=r"[A-Za-z0-9_.-]+",
    scene=r"[A-Za-z0-9_]+",
    it=r"\d+",
    pass_="fit|refit",


ITERATIONS = int(config["iterations"])
"""Outer iterations (observe -> fit -> augment -> refine geometry); pass ITERATIONS is the final refit."""


DEMO_CAPTURE = f"captures/{config['demo']['scene']}"

# The fit's shard count (the `fit` scatter, Snakefile): config fit.shards, raised where the memory model says a job
# of that many would need more than fit.mem_mb (sellip.fit.shard_plan.planned_shards; docs/reliability.md).
from sellip.fit.shard_plan import fit_shard_plan

try:
    FIT_SHARDS, _shards_raised = fit_shard_plan(
        config,
        CONFIG_SCHEMA,
        (
            workflow_support.capture_view_ids(config["capture"])
            if config["capture"]
            else [
                f"v{index:03d}"
                for index in range(int(workflow_support.declared_setting(config, CONFIG_SCHEMA, "demo.views")))
            ]
        ),
    )
except MemoryError as exc:
    raise WorkflowError(str(exc)) from None
if _shards_raised:
    print(f"sellip: {_shards_raised}", file=sys.stderr)


def capture_dir():
    """The capture folder: config `capture`, or the built-in demo (made by rule synth_capture)."""
    return config["capture"] or DEMO_CAPTURE


def capture_file(name):
    """A file of the capture; for the built-in demo it is an output of synth_capture."""
    return str(Path(capture_dir()) / name)


def raw_frames():
    """The raw frames the capture's frames.csv names (those that exist: ingest reports the others). They are tracked
    by their content (content_of), not as inputs: a frame touched but unchanged re-runs nothing, whatever its size.
    The built-in demo's frames are made by synth_capture with its frames.csv, which is the input then."""
    return workflow_support.raw_frame_files(capture_dir()) if config["capture"] else []


def poses_file():
    """The capture's poses.csv as a list (empty when it has none): an input of run_sfm (and tracked by content), so
    that adding, removing or editing it re-runs the poses and what follows."""
    return (
        [capture_file("poses.csv")]
        if not config["capture"]
        else workflow_support.optional_file(capture_dir(), "poses.csv")
    )


def ground_truth_file():
    """The capture's ground-truth mesh as a list (empty when it has none): tracked by content for evaluate_model."""
    return workflow_support.optional_file(capture_dir(), "ground_truth/model.ply") if config["capture"] else []


def user_mesh():
    """The mesh file init.mode 'mesh' starts from (config init.mesh_path; a relative path lies in the capture
    folder, an absolute one is used as is), as a list: empty in the other modes. Tracked by content for init_mesh."""
    if config["init"]["mode"] != "mesh":
        return []
    path = capture_file(os.path.expanduser(config["init"]["mesh_path"]))  # Path(capture) / absolute = absolute
    if not Path(path).is_file():
        raise WorkflowError(
            f"config init.mesh_path: {path} does not exist (a relative path lies in the capture folder); "
            "give the scan's file, or init.mode hull"
        )
    return [path]


INPUT_DIGESTS = workflow_support.ContentDigests(workflow_support.DIGEST_CACHE)


def content_of(*files):
    """A `params:` value: the digest of the content of the capture's files that `files` (functions returning lists of
    paths) name, so that Snakemake's params trigger re-runs the rule when any of them changes, whatever its mtime
    (docs/reliability.md). Empty for the built-in demo, whose capture files are outputs of synth_capture."""

    def digest(wildcards):
        if not config["capture"]:
            return ""
        return INPUT_DIGESTS.digest([path for listed in files for path in listed()], capture_dir())

    return digest


RESULTS = f"results/{config['name']}"

# The command of each job: `sellip` from the rule's conda env with --sdm conda, or when it is
# on PATH (an activated venv); else the sellip of the Python that runs Snakemake (.venv/bin/snakemake).
_CONDA = DeploymentMethod.CONDA in workflow.deployment_settings.deployment_method
SELLIP = "sellip" if _CONDA or shutil.which("sellip") else f"{shlex.quote(sys.executable)} -m sellip.cli"


def sellip_shell(arguments):
    """A rule's shell command: SELLIP running the `sellip` subcommand and ``arguments`` (one command per rule)."""
    return f"{SELLIP} {arguments}"


# The env files (envs/*.yaml) install sellip from ${SELLIP_ROOT}: this checkout.
os.environ.setdefault("SELLIP_ROOT", str(Path(workflow.basedir).resolve()))


def settings_json(settings):
    """A config section (or the part of it a job takes) as one shell-quoted JSON argument: the job parses it into its
    settings record, whose declarations give every key left out its default (sellip.settings)."""
    return shlex.quote(json.dumps(dict(settings), sort_keys=True))


def section_settings(section, workflow_keys=(), it=None, keys=None):
    """`--settings` of a job: the keys of config `section` (a dotted path, e.g. "augment.settings") that the config
    sets, less the `workflow_keys` the workflow reads itself (threads, enabled, ...), with `keys` only those the job
    takes (so that another job's key re-runs nothing here), as one JSON argument; with `it`,
    a list of values is iteration it's (at_iteration: for sections whose only lists are values per iteration). The job's settings record gives every key left out its
    declared default (sellip.settings)."""
    values = config
    for key in section.split("."):
        values = values.get(key) or {}
    return settings_json(
        {
            key: value if it is None else at_iteration(value, it)
            for key, value in values.items()
            if key not in workflow_keys and (keys is None or key in keys)
        }
    )


def synth_options():
    """The `sellip synth` options of the keys of config demo that are set (`--noise-scale 0.5`); a key left out (or
    null) takes the declared default (sellip.capture.synthetic.DemoSettings)."""
    demo = config.get("demo") or {}
    return " ".join(
        f"--{key.replace('_', '-')} {shlex.quote(str(value))}"
        for key, value in demo.items()
        if key not in ("scene", "overrides") and value is not None
    )


def at_iteration(value, it):
    """A config value for iteration `it`: a list gives one value per iteration (its last value repeats)."""
    if isinstance(value, list):
        return value[min(int(it), len(value) - 1)]
    return value


def augmented(it):
    """Whether iteration `it` refits with specular augmentation (config `augment.enabled`)."""
    return bool(at_iteration(config["augment"]["enabled"], it))


def params_of(it):
    """The parameter store that iteration `it` ends with: the refit when augmented, else the first fit."""
    return f"{RESULTS}/iter/{it}/{'refit' if augmented(it) else 'fit'}.zarr"


def mesh_of(it):
    """The mesh of iteration `it`: the initial mesh at 0, else the mesh refined by iteration it-1."""
    return f"{RESULTS}/mesh/init.ply" if int(it) == 0 else f"{RESULTS}/iter/{int(it) - 1}/mesh.ply"


def refines_poses():
    """Whether the loop refines the poses against the model (config `refine_poses.enabled`; "auto": when the poses
    come from SfM, i.e. sfm.mode sfm or a capture without poses.csv)."""
    enabled = config["refine_poses"]["enabled"]
    if enabled == "auto":
        return config["sfm"]["mode"] == "sfm" or not poses_file()
    return bool(enabled)


def cameras_of(it):
    """The cameras of iteration `it`: the poses stage's, or with pose refinement from iteration
    after_iteration + 1 on, those aligned to iteration it-1's model."""
    it = int(it)
    if not refines_poses() or it <= int(config["refine_poses"]["after_iteration"]):
        return f"{RESULTS}/cameras.csv"
    return f"{RESULTS}/iter/{it}/cameras.csv"


def get_cameras(wildcards):
    return cameras_of(wildcards.it)


def may_pass_through(it):
    """Whether iteration `it`'s jobs pass their inputs through once the loop has converged (config converge,
    sellip.fit.convergence): from iteration converge.min_iterations to the last before the final pass."""
    it = int(it)
    setting = lambda key: workflow_support.declared_setting(config, CONFIG_SCHEMA, f"converge.{key}")
    return bool(setting("enabled")) and int(setting("min_iterations")) <= it <= ITERATIONS - 1


def summary_of(it):
    """The geometry update summary of iteration `it` (its convergence verdict)."""
    return f"{RESULTS}/iter/{int(it)}/mesh.ply.json"


def pass_through_inputs(it, sources=()):
    """The inputs a job of iteration `it` passes through (with the previous iteration's summary, which decides)."""
    return [summary_of(int(it) - 1), *sources] if may_pass_through(it) else []


def pass_through(it, links=(), markers=(), folders=()):
    """The `sellip pass-through ... --` prefix of a job of iteration `it` (nothing where it cannot pass through):
    `links` (source, output) pairs, `markers` output files and `folders` output folders that nothing reads."""
    if not may_pass_through(it):
        return ""
    words = ["pass-through", "--after", shlex.quote(summary_of(int(it) - 1))]
    for source, output in links:
        words += ["--link", shlex.quote(str(source)), shlex.quote(str(output))]
    words += [f"--marker {shlex.quote(str(path))}" for path in markers]
    words += [f"--marker-folder {shlex.quote(str(path))}" for path in folders]
    return " ".join(words + ["--"])


def previous_store(wildcards):
    """The store a gather of iteration it passes through once the loop has converged: iteration it-1's first-pass
    store for the first pass, the parameters it ended with for the refit."""
    it = int(wildcards.it)
    return f"{RESULTS}/iter/{it - 1}/fit.zarr" if wildcards.pass_ == "fit" else params_of(it - 1)


def poses_summary_of(it):
    """The pose refinement summary that made iteration `it`'s cameras; none where they are the poses stage's."""
    cameras = cameras_of(it)
    return [f"{cameras}.json"] if cameras != f"{RESULTS}/cameras.csv" else []


def get_mesh(wildcards):
    return mesh_of(wildcards.it)


def get_params(wildcards):
    """The parameters iteration `it` ends with (input of its geometry update)."""
    return params_of(int(wildcards.it))


def get_fit_prior(wildcards):
    """Warm start of a fit pass: the first pass starts from iteration it-1 (nothing at 0), the
    refit from this iteration's first pass."""
    it = int(wildcards.it)
    if wildcards.pass_ == "refit":
        return [f"{RESULTS}/iter/{it}/fit.zarr"]
    return [] if it == 0 else [params_of(it - 1)]


def get_lobes(wildcards):
    """The cluster lobes a pass adds virtual samples from: a refit its own iteration's; the final pass's first fit
    the previous iteration's (it then has the refit's settings and runs its compiled program instead of compiling
    one of its own); nothing for the other first passes."""
    it = int(wildcards.it)
    if wildcards.pass_ == "refit":
        return [f"{RESULTS}/iter/{it}/clusters"]
    if it == ITERATIONS and it > 0 and augmented(it - 1) and augmented(it):
        return [f"{RESULTS}/iter/{it - 1}/clusters"]
    return []


def get_final_outputs():
    """What the target `all` builds: the reconstructed model, its renders and its metrics."""
    return [
        f"{RESULTS}/previews",
        f"{RESULTS}/final/model.ply",
        f"{RESULTS}/final/params.zarr",
        f"{RESULTS}/final/renders",
        f"{RESULTS}/metrics.json",
        f"{RESULTS}/viewer",
    ]


# config fit/augment/final/model_selection settings as the arguments of rules fit_pbrdf and cluster_lobes.
def fit_settings(wildcards):
    """`--settings` (sellip.fit.records.FitSettings as JSON) of this iteration and pass: config `fit.settings`
    (lists are per iteration), then `augment.settings` for a pass with virtual samples (a refit, and the final
    pass's first fit: get_lobes), then `final.settings` for the final pass (iteration ITERATIONS: normals from the
    final geometry, pBRDF only)."""
    it = int(wildcards.it)
    settings = {key: at_iteration(value, it) for key, value in config["fit"]["settings"].items()}
    if get_lobes(wildcards):
        settings.update(config["augment"]["settings"])
    if it == ITERATIONS:
        settings.update(config["final"]["settings"])
    return settings_json(settings)


def cluster_settings(wildcards):
    """`--settings` of the cluster lobe fits of this iteration: config `fit.settings` (its loss weights, view
    selection, and the most complex model allowed: `lobes`, `sigma_ss_fixed`)."""
    it = int(wildcards.it)
    return settings_json({key: at_iteration(value, it) for key, value in config["fit"]["settings"].items()})


def fit_job_settings():
    """`--job-settings` of the fit, gather-fit and cluster-lobes jobs (sellip.fit.records.FitJobSettings): the keys
    of config `fit` that are set, less Snakemake's own (shards, threads, mem_mb) and the FitSettings (`settings`)."""
    return section_settings("fit", ("shards", "threads", "mem_mb", "settings"))


MODEL_SELECTION_WORKFLOW_KEYS = ("every",)
"""Keys of config `model_selection` that the workflow reads itself; the others are SelectionSettings fields."""


def model_selection_settings():
    """`--model-selection` (sellip.fit.selection.SelectionSettings as JSON): config `model_selection`."""
    return settings_json(
        {key: value for key, value in config["model_selection"].items() if key not in MODEL_SELECTION_WORKFLOW_KEYS}
    )


def previous_clusters(it):
    """cluster_lobes' `previous` input: the previous pass's clusters (none at iteration 0)."""
    return [f"{RESULTS}/iter/{int(it) - 1}/clusters"] if int(it) > 0 else []


def inherit_models(wildcards):
    """`--inherit-models` where cluster_lobes fits no candidate: candidates are fitted at iteration 0, every
    `model_selection.every`-th iteration and the final pass; the others inherit their vertices' models."""
    it = int(wildcards.it)
    return "--inherit-models" if it % int(config["model_selection"]["every"]) and it != ITERATIONS else ""


def model2_sigma_ss():
    """`--model2-sigma-ss` of the fit jobs where config `model_selection.model2_sigma_ss` is set (else the job takes
    its declared default)."""
    value = config["model_selection"].get("model2_sigma_ss")
    return "" if value is None else f"--model2-sigma-ss {float(value)}"
