"""Compiled kernels that later processes load instead of tracing again (docs/speed.md).

Every workflow job is a new process. ``jax.jit`` traces and lowers each kernel again in every process
before the persistent compilation cache can even be asked (its key is the lowered module): on the demo
that was 6 s of a 12 s fit job. :func:`kernel` is ``jax.jit`` for the numerical kernels, with one
addition: when :func:`enable` names a folder, each (kernel, static arguments, argument shapes) is
exported once with ``jax.export`` and serialized there; a later process deserializes it (milliseconds)
and only compiles, which the persistent compilation cache then answers. Results are those of
``jax.jit`` (the same StableHLO). Without a folder, or where exporting fails, it is plain ``jax.jit``.

Jobs that start together (the shards of one pass) need the same compilations. The first call of each
exported kernel in a process (where XLA compiles it, or loads it from the persistent cache) holds an
exclusive lock on a file beside the export, so one job compiles while the others wait and then load the
result from the cache: two demo shards compiling side by side took 55-57 s each, one alone 39 s.

Public API::

    kernel(fn=None, *, static_argnames=(), name=None)   # decorator, as partial(jax.jit, static_argnames=...)
    enable(folder | None)                    # where exported kernels live (None: off)
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import inspect
import logging
import os
import sys
import tempfile
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

log = logging.getLogger(__name__)

_FOLDER: Path | None = None
_REGISTERED: set[type] = set()


@functools.cache
def code_version() -> str:
    """A hash of every source file of the sellip package: part of each exported kernel's key, so that a
    changed kernel (or a function it calls, in any module) is exported anew, never loaded stale."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]  # src/sellip: every subpackage
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def enable(folder: str | Path | None) -> None:
    """Export kernels to / load them from ``folder`` (created when needed); None turns it off."""
    global _FOLDER
    _FOLDER = None if folder is None else Path(folder)


def _node_types(treedef) -> set[type]:
    """The node types of a PyTreeDef (its root's and its children's)."""
    data = treedef.node_data()
    found = {data[0]} if data is not None else set()
    for child in treedef.children():
        found |= _node_types(child)
    return found


def _register_namedtuples(*treedefs) -> None:
    """jax.export serializes a pytree's node types by name: register the NamedTuples of the sellip modules
    (the kernels' outputs, known before a process deserializes them) and those of ``treedefs``."""
    from jax import export

    candidates = set()
    for name, module in list(sys.modules.items()):
        if name.startswith("sellip.") and module is not None:
            candidates |= {cls for cls in list(vars(module).values())
                           if inspect.isclass(cls) and cls.__module__ == name}
    for treedef in treedefs:
        candidates |= _node_types(treedef)
    for cls in candidates - _REGISTERED:
        if issubclass(cls, tuple) and hasattr(cls, "_fields"):
            export.register_namedtuple_serialization(cls, serialized_name=f"{cls.__module__}.{cls.__qualname__}")
            _REGISTERED.add(cls)


def _spec(leaf):
    return jax.ShapeDtypeStruct(np.shape(leaf), jnp.result_type(leaf))


class Kernel:
    """A jitted function whose compiled forms are exported per (static arguments, argument shapes)."""

    def __init__(self, fn, static_argnames=(), name: str | None = None):
        self.fn = fn
        self.static_argnames = tuple(static_argnames)
        self.signature = inspect.signature(fn)
        self.jitted = jax.jit(fn, static_argnames=self.static_argnames)
        self.calls: dict[tuple, object] = {}
        self.failed = False
        self.name = name or f"{fn.__module__}.{fn.__qualname__}"  # the key: unique per kernel, stable per run

    def __call__(self, *args, **kwargs):
        if _FOLDER is None or self.failed:
            return self.jitted(*args, **kwargs)
        bound = self.signature.bind(*args, **kwargs)
        bound.apply_defaults()
        static = {name: bound.arguments[name] for name in self.static_argnames if name in bound.arguments}
        dynamic_names = [name for name in bound.arguments if name not in static]
        dynamic = [bound.arguments[name] for name in dynamic_names]
        leaves, tree = jax.tree_util.tree_flatten(dynamic)
        leaves = [jnp.asarray(leaf) for leaf in leaves]
        # In-process key: cheap (static arguments are hashable, as jax.jit requires); the file name's hash
        # is computed only when this process has not met the signature yet.
        signature = (tuple(sorted(static.items())), tuple(dynamic_names), tree,
                     tuple((x.shape, x.dtype) for x in leaves), bool(jax.config.jax_enable_x64))
        call = self.calls.get(signature)
        if call is None:
            key = hashlib.sha256(repr((self.name, code_version(), sorted((k, repr(v)) for k, v in static.items()),
                                       dynamic_names,
                                       str(tree), [(np.shape(x), str(x.dtype)) for x in leaves], jax.__version__,
                                       bool(jax.config.jax_enable_x64), jax.default_backend())).encode()).hexdigest()
            # One process at a time exports and compiles this form; the others then load both (module docstring).
            with _exclusive(_FOLDER / f"{self.name.rsplit('.', 1)[-1]}-{key[:32]}.lock"):
                try:
                    call = self.calls[signature] = self._load_or_export(key, static, dynamic_names, tree, leaves)
                except Exception as exc:  # noqa: BLE001 - an unexportable kernel still runs, traced as usual
                    log.warning("%s: not exported (%s: %s); tracing it in every process", self.name,
                                type(exc).__name__, exc)
                    self.failed = True
                    return self.jitted(*args, **kwargs)
                return call(*jax.tree_util.tree_unflatten(tree, leaves))
        return call(*jax.tree_util.tree_unflatten(tree, leaves))

    def _cache_size(self) -> int:
        """Compiled forms held in this process (``jax.jit``'s own count, as the tests use it)."""
        return self.jitted._cache_size() + len(self.calls)

    def _load_or_export(self, key, static, dynamic_names, tree, leaves):
        from jax import export

        _register_namedtuples(tree)
        path = _FOLDER / f"{self.name.rsplit('.', 1)[-1]}-{key[:32]}.jaxexport"
        if path.is_file():
            exported = export.deserialize(bytearray(path.read_bytes()))
        else:
            names = list(self.signature.parameters)

            def bound_fn(*dynamic):  # positional, in the signature's order (jax.jacfwd differentiates arg 0)
                values = {**dict(zip(dynamic_names, dynamic)), **static}
                return self.fn(*[values[name] for name in names])

            specs = jax.tree_util.tree_unflatten(tree, [_spec(x) for x in leaves])
            exported = export.export(jax.jit(bound_fn))(*specs)
            _register_namedtuples(exported.out_tree)  # the outputs' node types
            _FOLDER.mkdir(parents=True, exist_ok=True)
            handle, tmp = tempfile.mkstemp(dir=_FOLDER, suffix=".tmp")
            with os.fdopen(handle, "wb") as out:
                out.write(exported.serialize())
            os.replace(tmp, path)  # atomic: parallel jobs may export the same kernel
        return jax.jit(exported.call)


@contextlib.contextmanager
def _exclusive(path: Path):
    """Hold an exclusive lock on ``path`` (created when needed) for the block; released when the process ends,
    however it ends."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def kernel(fn=None, *, static_argnames=(), name: str | None = None):
    """Decorator: ``@kernel(static_argnames=("settings",))`` on a numerical kernel (see the module docstring).
    ``name``: the kernel's name in the export key (default module.qualname; give one to a transformed
    function such as ``jax.jacfwd(f)``, which carries f's name)."""
    if fn is None:
        return partial(kernel, static_argnames=static_argnames, name=name)
    return Kernel(fn, static_argnames, name)
