"""The package layout of docs/architecture.md holds (scripts/check_layout.py), and the checker finds what breaks it."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _checker():
    spec = importlib.util.spec_from_file_location("check_layout", REPO / "scripts" / "check_layout.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["check_layout"] = module
    spec.loader.exec_module(module)
    return module


def test_the_package_has_no_cycle_no_import_above_its_floor_and_no_stage_importing_a_stage():
    assert _checker().problems(REPO / "src") == []


def test_the_checker_finds_a_cycle_a_floor_violation_a_stage_import_and_a_long_function(tmp_path):
    src = tmp_path / "src" / "sellip"
    for folder in ("model", "fit", "stages"):
        (src / folder).mkdir(parents=True)
        (src / folder / "__init__.py").write_text("")
    (src / "model" / "a.py").write_text("from sellip.fit.b import x\n")  # model importing fit: above its floor
    (src / "fit" / "b.py").write_text("from sellip.model.a import y\nx = 1\n")  # and a cycle
    (src / "stages" / "one.py").write_text("from sellip.stages.two import z\n")
    (src / "stages" / "two.py").write_text("z = 1\n")
    (src / "stages" / "_shared.py").write_text("w = 1\n")
    (src / "stages" / "three.py").write_text("from sellip.stages._shared import w\n")  # a shared helper: allowed
    (src / "fit" / "long.py").write_text("def f():\n    '''Short.'''\n" + "    x = 1\n" * 90
                                         + "def g():\n    '''Long: a reason.'''\n" + "    x = 1\n" * 90)
    found = _checker().problems(tmp_path / "src")
    assert any("sellip.model.a imports sellip.fit.b, above its floor" in p for p in found)
    assert any(p.startswith("import cycle:") and "sellip.model.a" in p and "sellip.fit.b" in p for p in found)
    assert any("sellip.stages.one imports the stage sellip.stages.two" in p for p in found)
    assert not any("_shared" in p for p in found)
    assert [p for p in found if "long.py" in p] == [f"{src / 'fit' / 'long.py'}:1: f is 92 lines (> 80) and its "
                                                    "docstring does not say why (Long: ...)"]


def test_a_package_name_that_is_also_a_module_is_always_the_module():
    """sellip.fit.observe_mesh is a module and a function in it: the package gives the module, whatever was
    imported before (a fresh interpreter, so nothing is)."""
    import subprocess

    code = ("import types\nfrom sellip.fit import observe_mesh\nassert isinstance(observe_mesh, types.ModuleType)\n"
            "from sellip.fit import fit_vertices\nassert callable(fit_vertices)\n")
    subprocess.run([sys.executable, "-c", code], check=True, env={**__import__("os").environ,
                                                                  "PYTHONPATH": str(REPO / "src")})


def test_no_file_takes_a_private_name_of_another_module_and_the_packages_list_what_others_take():
    assert _checker().surface_problems(REPO) == []


def test_the_checker_finds_a_private_name_taken_and_a_name_missing_from_the_package_list(tmp_path):
    src = tmp_path / "src" / "sellip"
    (src / "fit").mkdir(parents=True)
    (src / "report").mkdir()
    (src / "__init__.py").write_text("")
    (src / "report" / "__init__.py").write_text("")
    (src / "fit" / "__init__.py").write_text("from sellip._exports import lazy_exports\n"
                                             "__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), "
                                             "{'solver': ('listed',)})\n")
    (src / "fit" / "solver.py").write_text("def listed():\n    pass\n\ndef unlisted():\n    pass\n\n"
                                           "def _hidden():\n    pass\n")
    (src / "fit" / "vertex_fit.py").write_text("from sellip.fit.solver import _hidden, unlisted\n")  # same package
    (src / "report" / "use.py").write_text("from sellip.fit import listed\nfrom sellip.fit.solver import unlisted\n")
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_x.py").write_text("from sellip.fit import solver\nsolver._hidden()\n"
                                                  "setattr(solver, '_hidden', None)\n")
    found = _checker().surface_problems(tmp_path)
    assert found == [
        "src/sellip/fit/vertex_fit.py:1: takes sellip.fit.solver._hidden, a private name of another module "
        "(make it public)",
        "src/sellip/report/use.py:2: takes sellip.fit.solver.unlisted from outside sellip.fit, whose __init__ does "
        "not list it",
        "tests/test_x.py:2: takes sellip.fit.solver._hidden, a private name of another module (make it public)",
        "tests/test_x.py:3: takes sellip.fit.solver._hidden, a private name of another module (make it public)",
    ]


def test_every_commands_help_formats():
    """`sellip COMMAND [STEP] --help` prints for every command and sub-step: argparse expands %-formats in help
    texts, so a unit such as "%" in a generated help (the calibration targets' --max-f-std-pct) must be escaped."""
    import argparse

    from sellip.cli import build_parser

    def parsers(parser):
        yield parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child in action.choices.values():
                    yield from parsers(child)

    helps = [p.format_help() for p in parsers(build_parser())]
    assert len(helps) > 25 and any("--max-f-std-pct" in h and "(%;" in h for h in helps)
