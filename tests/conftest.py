"""Test-wide settings: float64 available in JAX (kernels take their dtype from the inputs); under pytest-xdist, the
order in which whole test files go to the workers."""

import collections

import jax

jax.config.update("jax_enable_x64", True)


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist (`make test`: ``-n 2 --dist loadfile --no-loadscope-reorder``, whole files per worker, a
    worker takes the next file when it has at most two tests left), the files with the most tests marked slow go first
    and the fast files last: the long files (whole Snakemake runs) start early and the fast files fill the end, so
    that both workers finish together. Without xdist the order stays pytest's own."""
    if not hasattr(config, "workerinput"):
        return
    slow = collections.Counter(item.path for item in items if item.get_closest_marker("slow"))
    first_seen = {path: k for k, path in enumerate(dict.fromkeys(item.path for item in items))}
    items.sort(key=lambda item: (-slow[item.path], first_seen[item.path]))  # stable: a file keeps its own order
