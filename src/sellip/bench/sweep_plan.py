"""What the speed-accuracy sweep varies (:class:`Factor`, the presets), the nested-config helpers
(get, set, merge, the defaults of config/config.yaml) and the plan of runs (:class:`Variant`, one per factor
value and scene), with the checkout (``REPO``) whose Snakefile runs them and the sweep's error."""
from __future__ import annotations

import copy
import logging
import re
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


REPO = Path(__file__).resolve().parents[3]
"""The checkout this module lives in (its Snakefile and config/config.yaml drive the runs)."""


class SweepError(RuntimeError):
    """A sweep run failed or its inputs are inconsistent (the message names the run and its log)."""


# --------------------------------------------------------------------------- what is swept


@dataclass(frozen=True)
class Factor:
    """One swept setting: the dotted config ``key`` and the ``values`` tried besides the base's own.

    values: a tuple for every preset, or {preset: tuple}. label: format of a value in the chart ("{}" gets
    on/off for booleans, "free" for None). upstream: the values change the capture, ingest, poses or
    initial mesh, so the variant runs everything itself instead of reusing the scene's upstream run.
    """

    name: str
    key: str
    values: tuple | dict
    label: str = "{}"
    upstream: bool = False

    def values_for(self, preset: str) -> tuple:
        values = self.values.get(preset, ()) if isinstance(self.values, dict) else self.values
        return tuple(values)


FACTORS: tuple[Factor, ...] = (
    Factor("iterations", "iterations", {"quick": (1, 3), "full": (2, 4)}, "{} it"),
    Factor("views", "observe.max_views", {"quick": (12,), "full": (24,)}, "{} views"),
    Factor("augment", "augment.enabled", (False,), "aug {}"),
    Factor("sigma_ss", "fit.settings.sigma_ss_fixed", {"quick": (0.9, 1.0), "full": (0.9,)}, "σss {}"),
    Factor("model_selection", "model_selection.enabled", (False,), "selection {}"),
    Factor("lm_cap", "fit.settings.max_iterations", (10,), "LM {}"),
    Factor("dtype", "fit.dtype", {"quick": ("float64",)}, "{}"),
)
"""The factors, in sweep order. Adding one is one line here. The quick preset tries every factor of issue #9
around its small base (iterations 1 and 3 of 2, 12 of 24 views, σ_ss fixed at 0.9 and 1, LM cap 10 of 30,
float64); the full one, at the demo's size, the values that the quick sweep found to matter or that change
the fit's cost (iterations 2 and 4 of 6, 24 of 36 views, augmentation and model selection off, σ_ss 0.9,
LM cap 10): 10 variants, about 50 minutes on 2 cores (docs/benchmarks.md)."""

SCENE_FACTORS: dict[str, dict[str, tuple[str, ...]]] = {"quick": {"sphere_ior": ("model_selection",)},
                                                        "full": {"sphere_ior": ("model_selection",)}}
"""Per preset and scene, the only factors swept there (a scene not named: every factor). sphere_ior runs its
base (the refractive-index table) and model selection off (a scene without single scattering)."""


_QUICK = {
    "iterations": 2,
    "demo": {"views": 24, "width": 320, "height": 256, "seed": 0},
    "init": {"hull_resolution": 64, "max_vertices": 1500},
    # Shards are whole observation chunks: 256-vertex chunks split ~1.5k vertices evenly over both shards.
    "observe": {"vertex_chunk": 256},
    "fit": {"shards": 2, "settings": {"min_views": 6}},
    "augment": {"max_samples": 4096, "settings": {"virtual_count": 45, "virtual_step_deg": 2.0}},
    "evaluate": {"held_out_views": ["v005", "v017"], "render_views": ["v000"], "supersample": 1},
}

_FULL = {
    "iterations": 6,
    "demo": {"views": 36, "width": 612, "height": 512, "seed": 0},
    "init": {"max_vertices": 6000},
    "observe": {"max_slope": 0.4},
    "fit": {"shards": 2},
    "augment": {"settings": {"virtual_count": 45, "virtual_step_deg": 2.0}},
    "evaluate": {"held_out_views": ["v004", "v013", "v022", "v031"], "render_views": ["v000"], "supersample": 1},
}

PRESETS: dict[str, dict] = {"quick": _QUICK, "full": _FULL}
"""Base configuration of each preset (over config/config.yaml; the same for every scene).

quick: 24 views at 320x256 (2 held out), ~1.5k vertices, 2 iterations, 6 usable views
per vertex suffice, cluster lobes from at most 4096 samples, 45 virtual samples 2 deg apart, observation chunks
that split the vertices over both fit shards. full: the built-in demo's own settings (config/config.yaml
``demo``: 36 views at 612x512, 4 held out, 6k vertices, and its ``overrides``: 6 iterations, the slope test,
45 virtual samples), with one rendered view instead of four."""


# --------------------------------------------------------------------------- config helpers


def get_key(config: dict, key: str):
    """The value at a dotted ``key`` of a nested dict (KeyError naming the key when absent)."""
    node = config
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise KeyError(key)
        node = node[part]
    return node


def set_key(config: dict, key: str, value) -> dict:
    """A deep copy of ``config`` with the dotted ``key`` set to ``value`` (intermediate dicts created)."""
    out = copy.deepcopy(config)
    node = out
    *parents, last = key.split(".")
    for part in parents:
        node = node.setdefault(part, {})
        if not isinstance(node, dict):
            raise ValueError(f"cannot set {key!r}: {part!r} is not a mapping")
    node[last] = copy.deepcopy(value)
    return out


def merge(base: dict, over: dict) -> dict:
    """``base`` updated by ``over`` recursively (nested dicts key by key), as Snakemake merges config files."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load_defaults(repo: Path = REPO) -> dict:
    """config/config.yaml of the checkout."""
    import yaml

    path = Path(repo) / "config" / "config.yaml"
    if not path.is_file():
        raise SweepError(f"{path} does not exist: run the sweep from a checkout of sellip")
    return yaml.safe_load(path.read_text())


def declared_default(key: str, repo: Path = REPO):
    """The default of a dotted config ``key`` that config/config.yaml leaves to its settings record: the section
    that holds it is marked ``x-record: module:Class`` in config/config.schema.yaml, and the record's field
    declares the default (``sellip.settings``). KeyError naming the key when no record declares it."""
    import dataclasses
    import importlib

    import yaml

    node = yaml.safe_load((Path(repo) / "config" / "config.schema.yaml").read_text())
    *section, name = key.split(".")
    for part in section:
        node = (node.get("properties") or {}).get(part)
        if not isinstance(node, dict):
            raise KeyError(key)
    if "x-record" not in node:
        raise KeyError(key)
    module, record = node["x-record"].split(":")
    fields = {f.name: f for f in dataclasses.fields(getattr(importlib.import_module(module), record))}
    if name not in fields:
        raise KeyError(key)
    return fields[name].default


def value_label(value) -> str:
    """A config value as text for names and labels: on/off, free (None), 0.9, float64, 12."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "free"
    return f"{value:g}" if isinstance(value, float) else str(value)


# --------------------------------------------------------------------------- the plan


@dataclass(frozen=True)
class Variant:
    """One run of the sweep: ``factor`` "base" is the scene's base configuration (value None)."""

    scene: str
    factor: str
    value: object = None
    label: str = "base"
    key: str | None = None
    upstream: bool = False

    @property
    def name(self) -> str:
        """Results folder name (config ``name``): scene__base, scene__factor-value."""
        if self.factor == "base":
            return f"{self.scene}__base"
        return f"{self.scene}__{self.factor}-{re.sub(r'[^A-Za-z0-9_.-]', '_', value_label(self.value))}"


def plan_variants(scenes: list[str], preset: str, only: list[str] | None = None,
                  factors: tuple[Factor, ...] = FACTORS, defaults: dict | None = None) -> list[Variant]:
    """Per scene: the base, then every value of every factor (``only``: these factors; :data:`SCENE_FACTORS`
    may narrow them per scene) that differs from the base's own value (base of ``preset`` over ``defaults``,
    config/config.yaml when None; a key it leaves out takes its settings record's declared default)."""
    if preset not in PRESETS:
        raise SweepError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
    known = {f.name for f in factors}
    unknown = sorted(set(only or ()) - known)
    if unknown:
        raise SweepError(f"unknown factor(s) {unknown}; expected some of {sorted(known)}")
    if not scenes:
        raise SweepError("no scene to sweep")
    base = merge(load_defaults() if defaults is None else defaults, PRESETS[preset])
    variants = []
    for scene in scenes:
        variants.append(Variant(scene, "base"))
        allowed = SCENE_FACTORS.get(preset, {}).get(scene)
        for factor in factors:
            if (only and factor.name not in only) or (allowed is not None and factor.name not in allowed):
                continue
            try:
                own = get_key(base, factor.key)
            except KeyError:  # config.yaml leaves it to the record's declaration
                try:
                    own = declared_default(factor.key)
                except KeyError:
                    own = None
            for value in factor.values_for(preset):
                if value == own and type(value) is type(own):
                    continue
                shown = value_label(value)
                variants.append(Variant(scene, factor.name, value, factor.label.format(shown), factor.key,
                                        factor.upstream))
    return variants


def variant_overrides(variant: Variant, preset: str, capture: str | Path, cache: str | Path,
                      name: str | None = None) -> dict:
    """The config file of ``variant``'s snakemake run (over config/config.yaml): the preset's base, the
    scene, the capture folder (absolute: the built-in demo overrides then do not apply), the shared XLA
    cache, the results name (default ``variant.name``) and the factor's value."""
    config = merge(PRESETS[preset], {"name": name or variant.name, "capture": str(Path(capture).resolve()),
                                     "demo": {"scene": variant.scene},
                                     "fit": {"compilation_cache": str(Path(cache).resolve())}})
    if variant.key is not None:
        config = set_key(config, variant.key, variant.value)
    return config


