"""The examples in the core's docstrings run as tests (those marked ``# doctest: +SKIP`` stay
skipped), so the documentation cannot drift from the code.

Each core module is imported as ``volumeevm_addon.<module>`` (the package as users import it)
and its docstrings run through :mod:`doctest`.
"""

import doctest
import importlib
import pkgutil

import pytest

import volumeevm_addon

MODULES = sorted(
    info.name for info in pkgutil.walk_packages(volumeevm_addon.__path__, "volumeevm_addon.")
)


def test_every_core_module_is_collected():
    assert {"volumeevm_addon.model._evm", "volumeevm_addon.rendering._render",
            "volumeevm_addon.readers"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
