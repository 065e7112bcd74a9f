"""What a new user meets between installing the extension and a first picture (issue 21): a
script that ends without ``unregister()``, framing the volume, the data's units and the presets,
a stale DVR in F12, file paths in an unsaved .blend, the methods an error lists."""

import subprocess
import sys

from blender_helpers import REPO, ext, fresh  # noqa: F401 (fixtures)

# A user's script: register the extension, import a volume, show the viewport DVR, and end
# without unregister().
REGISTER_ONLY = r'''
import sys
sys.path.insert(0, sys.argv[1])
from sample_blends.make_demo import load_extension
extension = load_extension()
extension.register()
import bpy
from volumeevm.blender import api
vol = api.import_volume(sys.argv[2])
bpy.context.scene.volumeevm_render.viewport = True
print("REGISTERED", vol.name, flush=True)
'''


def test_a_script_that_only_registers_exits_cleanly(tmp_path, data_dir):
    script = tmp_path / "register_only.py"
    script.write_text(REGISTER_ONLY)
    run = subprocess.run([sys.executable, str(script), str(REPO),
                          str(data_dir / "ct_skull_cgal.npy")],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert "REGISTERED ct_skull_cgal" in run.stdout, run.stdout[-2000:] + run.stderr[-2000:]
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
