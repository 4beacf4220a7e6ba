"""Exported kernels (sellip.fit.kernels): same results as jax.jit, traced once, loaded by later processes."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sellip.fit import kernels


class Pair(NamedTuple):
    a: jnp.ndarray
    b: jnp.ndarray


TRACES = []


def _model(pair: Pair, x, scale: float):
    TRACES.append(scale)  # runs only while JAX traces the function
    return Pair(jnp.sin(pair.a * x) * scale, pair.b @ pair.b.T), jnp.sum(x)


@pytest.fixture
def exported(tmp_path):
    kernels.enable(tmp_path)
    yield tmp_path
    kernels.enable(None)


def test_exported_kernel_matches_jit_and_is_traced_once_per_shape(exported):
    fn = kernels.kernel(_model, static_argnames=("scale",), name="tests.model")
    rng = np.random.default_rng(0)
    pair = Pair(jnp.asarray(rng.normal(size=5), jnp.float32), jnp.asarray(rng.normal(size=(3, 4)), jnp.float32))
    x = jnp.asarray(rng.normal(size=5), jnp.float32)
    TRACES.clear()
    out = fn(pair, x, scale=2.0)
    reference = jax.jit(_model, static_argnames=("scale",))(pair, x, scale=2.0)
    for got, want in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(reference)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    assert isinstance(out[0], Pair)
    files = sorted(exported.glob("*.jaxexport"))
    assert len(files) == 1 and files[0].name.startswith("model-")
    fn(pair, x + 1, scale=2.0)  # same shapes and static arguments: neither traced nor exported again
    fn(pair, x, 2.0)  # positional static argument: the same kernel
    assert len(list(exported.glob("*.jaxexport"))) == 1
    fn(pair, x, scale=3.0)  # another static value: another kernel
    fn(Pair(pair.a[:4], pair.b), x[:4], scale=2.0)  # another shape: another kernel
    assert len(list(exported.glob("*.jaxexport"))) == 3
    traced = len(TRACES)
    # A new Kernel (as in a new process) loads the exported forms: the Python function is not traced.
    again = kernels.kernel(_model, static_argnames=("scale",), name="tests.model")
    np.testing.assert_array_equal(np.asarray(again(pair, x, scale=2.0)[0].a), np.asarray(out[0].a))
    assert len(TRACES) == traced


def test_a_transformed_kernel_exports_under_its_own_name(exported):
    def loss(z, data):
        return jnp.sum((data - z[0] * jnp.exp(-z[1] * data)) ** 2, keepdims=True)

    jacobian = kernels.kernel(jax.jacfwd(loss), name="tests.loss_jacobian")
    value = kernels.kernel(loss, name="tests.loss")
    z, data = jnp.array([1.0, 0.5]), jnp.linspace(0.0, 1.0, 7)
    np.testing.assert_allclose(np.asarray(jacobian(z, data)), np.asarray(jax.jacfwd(loss)(z, data)), rtol=1e-6)
    assert np.asarray(value(z, data)).shape == (1,)
    assert {p.name.split("-")[0] for p in exported.glob("*.jaxexport")} == {"loss_jacobian", "loss"}


def test_changed_code_exports_anew_instead_of_loading_a_stale_kernel(exported, monkeypatch):
    """The key holds the package's source hash: after an upgrade (any sellip file changed), a kernel of the
    same name and shapes is traced and exported again, not loaded from the old export."""
    assert kernels.code_version() == kernels.code_version() and len(kernels.code_version()) == 64
    pair, x = Pair(jnp.ones(3), jnp.ones((2, 2))), jnp.ones(3)
    kernels.kernel(_model, static_argnames=("scale",), name="tests.model_versioned")(pair, x, scale=1.0)
    assert len(list(exported.glob("*.jaxexport"))) == 1
    monkeypatch.setattr(kernels, "code_version", lambda: "another version")
    TRACES.clear()
    kernels.kernel(_model, static_argnames=("scale",), name="tests.model_versioned")(pair, x, scale=1.0)
    assert TRACES == [1.0] and len(list(exported.glob("*.jaxexport"))) == 2


def test_without_a_folder_it_is_plain_jit(tmp_path):
    fn = kernels.kernel(_model, static_argnames=("scale",), name="tests.model_plain")
    out = fn(Pair(jnp.ones(2), jnp.ones((2, 2))), jnp.ones(2), scale=1.0)
    assert float(out[1]) == 2.0 and not list(tmp_path.iterdir())


def _fit_script(tmp_path) -> str:
    """A process that fits 40 vertices with the compilation cache under tmp_path/cache, saves eta to argv[1] and
    prints its timing phases (JSON)."""
    return textwrap.dedent(f"""
        import json, sys
        import numpy as np
        from sellip import timing
        from sellip.fit.shard import enable_compilation_cache
        enable_compilation_cache({str(tmp_path / 'cache')!r})
        from sellip.fit import FitSettings, default_prior, fit_vertices
        sys.path[:0] = [{str(Path(__file__).parent)!r}, {str(Path(__file__).parents[1])!r}]
        from test_fit import _scene
        params, normals, obs, start = _scene(40, seed=3, n_views=12)
        clock = timing.start()
        with timing.phase("fit"):
            result = fit_vertices(obs, start, default_prior(40), FitSettings(max_iterations=8))
        np.save(sys.argv[1], np.asarray(result.params.eta))
        print(json.dumps(clock.report()))
    """)


@pytest.mark.slow
def test_a_second_process_loads_the_fit_kernels_instead_of_tracing(tmp_path):
    """The fit's kernels through two processes: the second traces (almost) nothing and fits the same."""
    script = _fit_script(tmp_path)
    reports = []
    for run in range(2):
        done = subprocess.run([sys.executable, "-c", script, str(tmp_path / f"eta{run}.npy")], capture_output=True,
                              text=True, check=True)
        reports.append(json.loads(done.stdout.strip().splitlines()[-1]))
    np.testing.assert_array_equal(np.load(tmp_path / "eta0.npy"), np.load(tmp_path / "eta1.npy"))
    assert list((tmp_path / "cache" / "exported").glob("lm_rounds-*.jaxexport"))
    assert reports[1].get("trace", 0.0) < 0.25 * reports[0]["trace"]


@pytest.mark.slow
def test_processes_that_start_together_compile_once(tmp_path):
    """Two fits started together on an empty cache (the shards of a pass): one compiles each kernel while the
    other waits for it and loads the compilation from the cache; both fit the same."""
    script = _fit_script(tmp_path)
    runs = [subprocess.Popen([sys.executable, "-c", script, str(tmp_path / f"eta{run}.npy")], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True) for run in range(2)]
    reports = []
    for run in runs:
        out, err = run.communicate(timeout=600)
        assert run.returncode == 0, err
        reports.append(json.loads(out.strip().splitlines()[-1]))
    np.testing.assert_array_equal(np.load(tmp_path / "eta0.npy"), np.load(tmp_path / "eta1.npy"))
    assert list((tmp_path / "cache" / "exported").glob("lm_rounds-*.lock"))
    compiled = sorted(report.get("compile", 0.0) for report in reports)
    assert compiled[0] < 0.25 * compiled[1], reports
