"""Small public ``__init__`` files that import nothing until a name is used.

A subpackage's ``__init__`` names its public functions and the module each
lives in; ``attach`` turns that table into a module ``__getattr__`` (PEP 562),
so ``from FluoTomoLib.fem import forward_fields`` works while ``import
FluoTomoLib.fem`` stays cheap and free of import cycles (the FEM, the meshers
and numba kernels load only when used).
"""

from __future__ import annotations

import importlib


def attach(package, exports):
    """Lazy attribute access for ``package``.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    exports : dict of str to list of str
        Submodule name (relative to the package) -> public names it defines.

    Returns
    -------
    (__getattr__, __dir__, __all__)
        To assign in the package's ``__init__``.
    """
    where = {name: sub for sub, names in exports.items() for name in names}
    public = sorted(set(where) | set(exports))

    def __getattr__(name):
        if name in where:
            module = importlib.import_module(f"{package}.{where[name]}")
            return getattr(module, name)
        if name in exports:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return public

    return __getattr__, __dir__, public
