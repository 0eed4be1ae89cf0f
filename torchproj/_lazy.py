"""Names a package offers without importing the modules that hold them until first use.

``import torchproj`` and the ``torchproj`` command would otherwise import torch, scipy, scikit-image
and the whole library before the first line of ``main`` runs: seconds in which ``--help`` waits and
a Ctrl-C can only end in a traceback (the command's handlers are not yet installed). Each name is
imported on first access (PEP 562), and ``dir()`` lists them all, so ``help(torchproj)`` and
``from torchproj import X`` see the same face as an eager package.
"""

from __future__ import annotations

import importlib


def lazy_names(package: str, where: dict[str, str]):
    """``(__getattr__, __dir__)`` for ``package`` whose public names live in submodules.

    Args:
        package: the package's ``__name__``.
        where: public name -> submodule (relative, without the dot) that defines it; a name mapped
            to itself is a submodule offered as an attribute.
    """

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module = importlib.import_module(f"{package}.{where[name]}")
        value = module if where[name] == name else getattr(module, name)
        importlib.import_module(package).__dict__[name] = value  # the next access is a plain lookup
        return value

    def __dir__():
        return sorted(set(importlib.import_module(package).__dict__) | set(where))

    return __getattr__, __dir__
