"""The core never imports bpy or mathutils (it runs in plain Python), and nothing outside it
imports its private modules (one public API)."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "volumeevm_addon"


def test_no_blender_imports_in_the_core_sources():
    for path in CORE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            assert not any(n.split(".")[0] in ("bpy", "mathutils", "bmesh") for n in names), path


def test_importing_the_core_loads_no_blender_module():
    code = ("import sys, volumeevm_addon; "
            "assert not {'bpy', 'mathutils'} & set(sys.modules), 'blender module loaded'")
    subprocess.run([sys.executable, "-c", code], cwd=CORE.parent, check=True)


# ------------------------------------------------------------------ one public API, enforced
REPO = CORE.parent
OUTSIDE_FOLDERS = ("blender", "operators", "ui", "bench", "sample_blends")
"""Code outside the core: it may import only the core's public names (``volumeevm_addon``,
``volumeevm_addon.readers``, ``.phantoms``, ``.metrics``), never a module named ``_...``."""


def is_private(module):
    """Whether the dotted ``module`` is a private module of ``volumeevm_addon`` or inside one
    (a part after ``volumeevm_addon`` starting with ``_``, dunders aside)."""
    parts = module.split(".")
    if "volumeevm_addon" not in parts:
        return False
    inner = parts[parts.index("volumeevm_addon") + 1:]
    return any(p.startswith("_") and not p.startswith("__") for p in inner)


def private_imports(source, filename):
    """``(line number, statement)`` of every import of a private module of ``volumeevm_addon`` in
    ``source``: absolute or relative, under any parent package (``bl_ext...volumeevm``), as
    ``import volumeevm_addon._x``, ``from volumeevm_addon._x import y`` or
    ``from volumeevm_addon import _x``."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            modules = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        else:
            continue
        if any(is_private(module) for module in modules):
            found.append((node.lineno, " ".join(ast.get_source_segment(source, node).split())))
    return found


def readme_python_blocks():
    """The README's ```python blocks: ``(first line number, code)``."""
    lines = (REPO / "README.md").read_text().splitlines()
    blocks, start = [], None
    for number, line in enumerate(lines, 1):
        if start is None and line.strip() == "```python":
            start = number + 1
        elif start is not None and line.strip() == "```":
            blocks.append((start, "\n".join(lines[start - 1:number - 1])))
            start = None
    return blocks


@pytest.mark.parametrize("source, private", [
    ("from ..volumeevm_addon.rendering._camera import Camera", True),
    ("from ..volumeevm_addon.rendering import _images", True),
    ("from ..volumeevm_addon import VolumeEVMError, _images", True),
    ("from volumeevm_addon.rendering._render import render", True),
    ("import volumeevm_addon._memory", True),
    ("from volumeevm.volumeevm_addon._files import write_atomically", True),
    ("from bl_ext.user_default.volumeevm.volumeevm_addon.rendering._transfer import PRESETS", True),
    ("from volumeevm_addon.readers._dicom import read_dicom", True),
    ("from ..volumeevm_addon import Camera, render", False),
    ("from volumeevm_addon.metrics import rmse", False),
    ("from volumeevm_addon import phantoms", False),
    ("import volumeevm_addon", False),
    ("from . import _jobs", False),
    ("from ._runtime import busy", False),
])
def test_private_import_scan_tells_private_from_public(source, private):
    assert bool(private_imports(source, "<example>")) == private


def test_nothing_outside_the_core_imports_a_private_module():
    files = [REPO / "__init__.py"]
    for folder in OUTSIDE_FOLDERS:
        files += sorted((REPO / folder).rglob("*.py"))
    assert len(files) > 20, files
    offending = [f"{path.relative_to(REPO)}:{number}: {line}"
                 for path in files
                 for number, line in private_imports(path.read_text(), str(path))]
    blocks = readme_python_blocks()
    assert len(blocks) >= 4
    for start, code in blocks:
        offending += [f"README.md:{start + number - 1}: {line}"
                      for number, line in private_imports(code, "README.md")]
    assert not offending, ("private core modules imported outside the core (use the names "
                           "exported by volumeevm_addon):\n" + "\n".join(offending))


def test_every_public_name_is_exported():
    import volumeevm_addon
    from volumeevm_addon import metrics, phantoms

    assert all(hasattr(volumeevm_addon, name) for name in volumeevm_addon.__all__)
    assert len(set(volumeevm_addon.__all__)) == len(volumeevm_addon.__all__)
    for public in (phantoms, metrics):  # the modules themselves: one way to import each name
        assert all(getattr(public, n).__module__ == public.__name__ for n in public.__all__)


def public_names_taken_privately(source, filename):
    """``(line number, name)`` of every name ``source`` imports from a private core module
    although ``volumeevm_addon`` or ``volumeevm_addon.readers`` exports it."""
    import volumeevm_addon
    from volumeevm_addon import readers

    public = set(volumeevm_addon.__all__) | set(readers.__all__)
    return [(node.lineno, alias.name)
            for node in ast.walk(ast.parse(source, filename))
            if isinstance(node, ast.ImportFrom) and node.module and is_private(node.module)
            for alias in node.names if alias.name in public]


def test_tests_take_public_names_from_the_public_api():
    """Tests may look inside a private module for what is not public (white-box tests of a
    renderer's internals), but a name the API exports comes from the API, as users get it."""
    files = sorted((REPO / "tests").glob("*.py"))
    assert len(files) > 30
    offending = [f"{path.relative_to(REPO)}:{number}: {name}"
                 for path in files
                 for number, name in public_names_taken_privately(path.read_text(), str(path))]
    assert not offending, "public names imported from private modules:\n" + "\n".join(offending)


# ------------------------------------------------------------------ imports go one way
def core_imports():
    """``{module: {core modules it imports}}`` for every module of the core, counting imports
    anywhere in a module (a function-level import that breaks a circle is still one)."""
    names = {}
    for path in CORE.rglob("*.py"):
        parts = path.relative_to(REPO).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {}
    for name, path in names.items():
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = ".".join(package[:len(package) - node.level + 1]
                                + ([node.module] if node.module else []))
                submodules = [f"{base}.{alias.name}" for alias in node.names]
                # ``from . import _sweep`` takes a sibling module, not the package's own names:
                # the package (whose ``__init__`` may import its modules) is no dependency then.
                wanted = submodules if all(m in names for m in submodules) else [base, *submodules]
                targets.update(m for m in wanted if m in names and m != name)
            elif isinstance(node, (ast.Import, ast.ImportFrom)):
                modules = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                           else [node.module])
                targets.update(m for m in modules if m in names and m != name)
        graph[name] = targets
    return graph


def import_circles(graph):
    """The circles of ``graph``: each strongly connected set of two or more modules, sorted."""
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in graph[node]:
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            members = []
            while not members or members[-1] != node:
                members.append(stack.pop())
                on_stack.discard(members[-1])
            if len(members) > 1:
                circles.append(sorted(members))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return circles


def test_the_circle_finder_finds_circles():
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles_in_the_core():
    """A module may use only what is below it: no two core modules import each other, directly
    or around a circle, even through an import inside a function."""
    graph = core_imports()
    assert {"volumeevm_addon.model._mesh", "volumeevm_addon.model._sweep"} <= graph[
        "volumeevm_addon.model._evm"]  # the scan sees relative imports, top-level and not
    assert import_circles(graph) == []
