"""A pytest plugin (``-p checkout_root`` in pytest.ini): the repository root collected as a plain
folder.

The root is the extension's package (it has ``__init__.py``), which the tests load by path, not
by import. pytest would import it under the folder's name to look for set-up functions, which
fails for a checkout whose folder name is no Python identifier (GitHub's ``volumeevm-main``).
A conftest cannot say this: its hooks apply below its own folder, not to the folder itself.
"""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def pytest_collect_directory(path, parent):
    if path == ROOT:
        return pytest.Dir.from_parent(parent, path=path)
    return None
