"""The core never imports bpy or mathutils: it runs in plain Python."""

import ast
import subprocess
import sys
from pathlib import Path

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
