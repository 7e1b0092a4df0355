"""Names of a package imported from their modules on first access (PEP 562).

A package's ``__init__`` declares which module defines each public name and calls :func:`lazy_exports` once::

    __getattr__, __dir__ = lazy_exports(__name__, {"correct_scan": "mpi_lidar.correction.correct"}, __all__)

``import package`` then imports none of those modules; ``package.correct_scan`` (or ``from package import
correct_scan``) imports its module the first time and keeps the value in the package, so later accesses do not
come back here.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Mapping
from importlib import import_module


def lazy_exports(package: str, exports: Mapping[str, str], names: Iterable[str] = ()
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """A package's module-level ``__getattr__`` and ``__dir__`` for names imported on first access.

    Parameters
    ----------
    package : The package's ``__name__``.
    exports : Each lazily imported name -> the module (absolute name) that defines it.
    names : The names ``dir(package)`` lists besides the package's own globals (its ``__all__``).

    Returns
    -------
    ``__getattr__``, which imports a name of ``exports`` from its module, stores it in the package and returns
    it (AttributeError for any other name), and ``__dir__``.
    """
    listed = frozenset(names)

    def __getattr__(name: str) -> object:  # noqa: N807 (the PEP 562 hook's name)
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(module), name)
        setattr(sys.modules[package], name, value)  # the next access does not come here
        return value

    def __dir__() -> list[str]:  # noqa: N807
        return sorted({*vars(sys.modules[package]), *listed})

    return __getattr__, __dir__
