"""Lazy re-exports for the subpackages' ``__init__`` (PEP 562): a name is imported from its private module on
first use, so ``import sellip.fit`` stays cheap and a package's ``__init__`` cannot create an import cycle."""

from __future__ import annotations

import importlib


def lazy_exports(package: str, namespace: dict, modules: dict[str, tuple[str, ...]]):
    """(``__getattr__``, ``__dir__``, ``__all__``) of ``package`` re-exporting ``modules`` {module: names}; a
    name resolved once is kept in ``namespace`` (the package's globals)."""
    # A name that is also a module of the package (fit.observe_mesh the module and the function) stays the module:
    # otherwise `from sellip.fit import observe_mesh` would give the function before the module was imported and
    # the module after.
    home = {name: module for module, names in modules.items() for name in names if name not in modules}

    def __getattr__(name: str):
        if name not in home:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{home[name]}"), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(home))

    return __getattr__, __dir__, sorted(home)
