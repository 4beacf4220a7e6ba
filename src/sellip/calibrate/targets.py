"""What each ``sellip calibrate`` step must reach before it writes anything: its own uncertainty against a target.

Public API::

    Target(name, step, default, unit, help)       # one setting: the step's largest acceptable 1-sigma or residual
    TARGETS                                        # every target, declared once (the CLI options come from it)
    defaults(step) -> {name: value}                # the targets of one step at their defaults
    check(step, measured: {name: value}, targets: {name: value}) -> list[str]   # the targets missed, in words

A step measures its own uncertainty (OpenCV's 1-sigma of fx and cx, the flash position's 1-sigma from the
highlight lines' spread, the flash polarizer's spread over the highlights, the chart's ΔE2000) and compares it
with its targets; a step that misses one fails with the causes it can see in the frames and leaves device.yaml
as it was (docs/calibration.md, "What each step must reach"). The defaults are the accuracy a reconstruction at
the device's size needs (docs/calibration.md, "How careful to be"); a calibration at a smaller size or a quick
check can relax them on the command line (``--max-flash-std-mm 5``), and device.yaml records the values used.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class Target:
    """One target: ``name`` (also the command-line option ``--max-<name with dashes>`` and the key in the step's
    ``calibration.<step>.targets`` record), the ``step`` it gates, its ``default``, ``unit`` and what it bounds."""

    name: str
    step: str
    default: float
    unit: str
    help: str

    @property
    def option(self) -> str:
        return "--max-" + self.name.replace("_", "-")


TARGETS: tuple[Target, ...] = (
    Target("f_std_pct", "intrinsics", 0.1, "%", "1-sigma of fx and fy, relative to them"),
    Target("c_std_px", "intrinsics", 0.25, "raw px",
           "1-sigma of the principal point cx, cy (96 poses give 0.15-0.22 px at 2448x2048)"),
    Target("reprojection_rms_px", "intrinsics", 0.5, "raw px", "RMS reprojection error of the board corners"),
    Target("flash_std_mm", "flash", 2.0, "mm", "1-sigma of the flash position, largest of x, y, z"),
    Target("flash_rms_mm", "flash", 3.0, "mm", "RMS distance of the highlights' mirror rays from the flash"),
    Target("polarizer_std_deg", "polarization", 0.5, "deg", "1-sigma of the flash polarizer's angle"),
    Target("delta_e_mean", "color", 1.5, "ΔE2000", "mean CIEDE2000 of the chart's patches after the fit"),
)


def for_step(step: str) -> tuple[Target, ...]:
    return tuple(t for t in TARGETS if t.step == step)


def defaults(step: str) -> dict[str, float]:
    """{name: default} of the targets of ``step``."""
    return {t.name: t.default for t in for_step(step)}


def check(step: str, measured: Mapping[str, float], targets: Mapping[str, float] | None = None) -> list[str]:
    """The targets of ``step`` that ``measured`` ({name: value}) misses, one sentence each ("flash_std_mm: 1-sigma
    of the flash position ... is 53.1 mm, target <= 2 mm"); a NaN (not measured) misses. Empty when all are met."""
    targets = {**defaults(step), **(targets or {})}
    missed = []
    for target in for_step(step):
        value = float(measured[target.name])
        limit = float(targets[target.name])
        if not value <= limit or math.isnan(value):
            missed.append(f"{target.help} is {value:.3g} {target.unit}, target <= {limit:g} {target.unit} "
                          f"({target.option})")
    return missed
