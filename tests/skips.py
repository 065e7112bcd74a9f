"""Skips that CI reports: a test whose dependency is missing here skips, but where ``CI`` is set
(any non-empty value) the same missing dependency is a failure, as the GPU tests do with
``VOLUMEEVM_REQUIRE_GPU=1``. Every dependency named here is one CI provides: the pinned
packages of ``requirements/``, Debian's ``libvolpack1-dev`` examples, the real data."""

import importlib
import os

import pytest


def in_ci():
    """True where the environment variable ``CI`` is set (not empty)."""
    return bool(os.environ.get("CI"))


def skip_unless_ci(reason, *, module_level=False):
    """Skip the calling test (or, with ``module_level``, module) because of ``reason``; fail
    instead in CI."""
    if in_ci():
        pytest.fail(f"{reason} (CI is set: a required dependency may not be missing)",
                    pytrace=False)
    pytest.skip(reason, allow_module_level=module_level)


def required_module(name):
    """The module ``name``; when it cannot be imported, skip the calling test (or module), and
    in CI fail."""
    try:
        return importlib.import_module(name)
    except ImportError as error:
        skip_unless_ci(f"{name} is not installed ({error})", module_level=True)
