"""Names of a package that load their module on first use (PEP 562), so ``import fusion`` stays light."""

from __future__ import annotations

import importlib


def lazy_attributes(package: str, names: dict[str, str]):
    """A module ``__getattr__`` for ``package`` resolving ``names`` (name -> relative module) on first use."""

    def __getattr__(name: str):
        if name in names:
            return getattr(importlib.import_module(names[name], package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__
