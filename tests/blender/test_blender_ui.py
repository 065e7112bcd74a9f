"""The UI side in the real bpy: DICOM import through the operator, the File > Import entry and
the drag-and-drop handler, the sidebar panels' draw code, and the modal job driver (timer steps,
Esc) that the UI uses. The bpy module has no window, so panels draw into a recorder whose calls
are checked against the real ``UILayout`` functions, parameters and icons, and the modal driver
runs with a minimal window manager that hands out timer events.
"""

import tempfile
import threading
import time

import bpy
import numpy as np
import pytest

SKULL = "ct_skull_cgal.npy"


# ---------------------------------------------------------------------------- DICOM, menu, drop
@pytest.fixture
def dicom_series(tmp_path, data_dir):
    from test_readers import write_series  # the readers' own series writer (clones CT_small)

    stored = np.load(data_dir / "ct_head_invesalius.npy")[96:160, 80:150, 40:52] + 1024
    folder = tmp_path / "series"
    folder.mkdir()
    _, files = write_series(folder, stored.astype(np.int16), pixel_spacing=(0.9, 0.8), dz=1.5,
                            origin=np.array([-30.0, -20.0, 50.0]), row=(1.0, 0.0, 0.0),
                            col=(0.0, 1.0, 0.0), slope=1, intercept=-1024, seed=3)
    return folder, files, stored - 1024


@pytest.mark.parametrize("how", ["folder", "one_file", "file_list"])
def test_import_dicom_series(ext, dicom_series, how):
    folder, files, hu = dicom_series
    if how == "folder":
        kwargs = dict(directory=str(folder) + "/")
    elif how == "one_file":
        kwargs = dict(filepath=str(files[3]))
    else:
        kwargs = dict(directory=str(folder), files=[{"name": f.name} for f in files])
    assert bpy.ops.volumeevm.import_volume(**kwargs) == {"FINISHED"}
    obj = bpy.context.active_object
    s = obj.volumeevm
    assert tuple(s.shape) == hu.shape
    np.testing.assert_allclose(tuple(s.spacing), (0.9, 0.8, 1.5), rtol=1e-6)
    np.testing.assert_allclose(tuple(s.origin), (-30.0, -20.0, 50.0), atol=1e-6)
    assert (s.value_min, s.value_max) == (hu.min(), hu.max())
    assert s.units == "HU"
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=300.0) == {"FINISHED"}
    assert s.voxel_count == int(np.count_nonzero(hu >= 300))


def test_invoke_in_background_imports_directly(ext, data_dir):
    path = str(data_dir / SKULL)
    assert bpy.ops.volumeevm.import_volume("INVOKE_DEFAULT", filepath=path) == {"FINISHED"}
    assert bpy.context.active_object.volumeevm.role == "VOLUME"
    assert bpy.ops.volumeevm.build_vevm("INVOKE_DEFAULT") == {"FINISHED"}
    assert bpy.ops.volumeevm.make_mesh("INVOKE_DEFAULT") == {"FINISHED"}


def test_file_menu_and_drop_handler(ext):
    draw_funcs = bpy.types.TOPBAR_MT_file_import.draw._draw_funcs
    assert ext.operators.import_volume.menu_import in draw_funcs
    handler = bpy.types.FileHandler.bl_rna_get_subclass_py("VOLUMEEVM_FH_import_volume")
    assert handler.bl_import_operator == "volumeevm.import_volume"
    extensions = handler.bl_file_extensions.split(";")
    assert {".npy", ".nrrd", ".nii", ".nii.gz", ".dcm", ".tif", ".den"} <= set(extensions)


def test_raw_import_uses_the_operator_options(ext, tmp_path, data_dir):
    array = np.load(data_dir / SKULL)
    raw = tmp_path / "skull.raw"
    raw.write_bytes(b"HDR!" + array.astype(">f4").ravel(order="F").tobytes())
    assert bpy.ops.volumeevm.import_volume(
        filepath=str(raw), raw_shape=array.shape, raw_dtype="float32", raw_byte_order="big",
        raw_header_bytes=4, raw_spacing=(2.0, 2.0, 3.0)) == {"FINISHED"}
    s = bpy.context.active_object.volumeevm
    assert tuple(s.shape) == array.shape and tuple(s.spacing) == (2.0, 2.0, 3.0)
    assert s.value_max == pytest.approx(float(array.max()))
    with pytest.raises(RuntimeError, match="skull.raw"):
        bpy.ops.volumeevm.import_volume(filepath=str(raw), raw_shape=(64, 64, 65),
                                        raw_dtype="float32", raw_header_bytes=4)


# ---------------------------------------------------------------------------- panels
class Recorder:
    """Stands in for a UILayout: records every call, checks it against the real RNA function."""

    _functions = bpy.types.UILayout.bl_rna.functions
    _icons = set(_functions["label"].parameters["icon"].enum_items.keys())

    def __init__(self, calls):
        object.__setattr__(self, "calls", calls)

    def __setattr__(self, name, value):
        assert name in bpy.types.UILayout.bl_rna.properties, f"UILayout has no {name!r}"

    def __getattr__(self, name):
        assert name in self._functions, f"UILayout has no function {name!r}"
        params = self._functions[name].parameters

        def call(*args, **kwargs):
            for key, value in kwargs.items():
                assert key in params, f"UILayout.{name}() has no parameter {key!r}"
                if key == "icon":
                    assert value in self._icons, f"unknown icon {value!r}"
            if name == "prop":
                data, prop = args[:2]
                assert prop in data.bl_rna.properties, f"{data} has no property {prop!r}"
            if name == "operator":
                category, op = args[0].split(".")
                assert hasattr(getattr(bpy.ops, category), op), args[0]
            self.calls.append((name, args, kwargs))
            if name == "operator":
                return OperatorProperties(args[0], self.calls)
            if name == "panel":
                return Recorder(self.calls), Recorder(self.calls)
            return Recorder(self.calls)

        return call


class OperatorProperties:
    """What ``layout.operator()`` returns: settable operator properties, checked and recorded."""

    def __init__(self, idname, calls):
        category, op = idname.split(".")
        rna = getattr(getattr(bpy.ops, category), op).get_rna_type()
        object.__setattr__(self, "_rna", rna)
        object.__setattr__(self, "_calls", calls)
        object.__setattr__(self, "_idname", idname)

    def __setattr__(self, name, value):
        assert name in self._rna.properties, f"{self._idname} has no property {name!r}"
        self._calls.append(("operator_property", (self._idname, name, value), {}))


class _PanelSelf:
    def __init__(self):
        self.calls = []
        self.layout = Recorder(self.calls)


def draw_all(ext, context):
    """Draw every sidebar panel whose poll passes; returns the recorded calls."""
    calls = []
    for cls in ext.ui.panels.CLASSES:
        if hasattr(cls, "poll") and not cls.poll(context):
            continue
        panel = _PanelSelf()
        if hasattr(cls, "draw_header"):
            cls.draw_header(panel, context)
        cls.draw(panel, context)
        calls += panel.calls
    return calls


def texts(calls):
    return [kw.get("text", "") for name, _, kw in calls if name in {"label", "progress"}]


def test_panels_draw_every_state(ext, data_dir, tmp_path):
    api = ext.blender.api
    context = bpy.context
    assert "Select or import a volume" in texts(draw_all(ext, context))

    obj = api.import_volume(data_dir / SKULL)
    shown = texts(draw_all(ext, context))
    assert "Size: 64 × 64 × 64 voxels" in shown
    assert "Spacing: 3.943 × 3.943 × 3.651 mm" in shown
    assert "Values: 2.171e-13 .. 5.429" in shown
    assert "Not built yet" in shown
    bars = [kw for name, _, kw in draw_all(ext, context) if name == "progress"]
    assert len(bars) == ext.ui.panels.HISTOGRAM_ROWS
    assert max(b["factor"] for b in bars) == 1.0
    # The Viewport DVR's drawing of a volume not built yet: its problem goes to the sidebar,
    # nothing is raised from the draw (and nothing is drawn: no GPU is needed here).
    settings = context.scene.volumeevm_render
    settings.viewport, settings.mode = True, "xray"  # X-ray: no transfer function needed
    viewport = ext.blender.gpu_viewport
    viewport.draw_view(context.scene, [obj], "test", (8, 8), np.eye(4), np.eye(4))
    assert "no VolumeEVM" in viewport.problem(obj)
    settings.viewport, settings.mode = False, "over"
    viewport.on_load_pre()  # forget the problem, as a file load does

    api.build(obj, 2.9)
    vevm = api.get_vevm(obj)
    shown = texts(draw_all(ext, context))
    assert f"Voxels: {vevm.voxel_count:,}" in shown
    assert f"Extreme vertices: {len(vevm.evm):,}" in shown
    assert "Kept in a temporary folder until the .blend is saved" in shown
    obj.volumeevm.threshold = 3.0
    calls = draw_all(ext, context)
    assert "Built at 2.9: build again" in texts(calls)
    # The Build button carries the object's settings, so the redo panel can change them; the
    # Make Manifold Mesh and Make Smooth Mesh buttons are Make Mesh with its manifold and smooth
    # options.
    passed = {args[1]: args[2] for name, args, _ in calls if name == "operator_property"}
    assert passed == {"use_settings": False, "threshold": 3.0, "use_upper": False,
                      "upper": obj.volumeevm.upper, "manifold": True, "smooth": True}
    # The Viewport DVR: its Fast While Moving toggle, and the level its last draw showed (set
    # here: draw handlers never run without a window).
    settings = context.scene.volumeevm_render
    settings.viewport = True
    viewport = ext.blender.gpu_viewport
    viewport._levels[obj.name] = 2
    panel = _PanelSelf()
    ext.ui.render_panel.VOLUMEEVM_PT_render.draw(panel, context)
    assert any(name == "prop" and args[1] == "viewport_fast" for name, args, _ in panel.calls)
    assert "Showing level 2 (2\u00d7 coarser voxels)" in texts(panel.calls)
    viewport._levels[obj.name] = 1
    panel = _PanelSelf()
    ext.ui.render_panel.VOLUMEEVM_PT_render.draw(panel, context)
    assert not [t for t in texts(panel.calls) if t.startswith("Showing level")]
    # A view transform that cannot be baked into the viewport's colour table (no writable
    # temporary folder): the sidebar says the viewport shows "Standard" and why, until the
    # settings change and a bake works.
    lut, view_settings = ext.blender.display_lut, context.scene.view_settings
    writable = tempfile.tempdir
    tempfile.tempdir = str(tmp_path / "no such folder")
    try:
        assert lut.refresh(context.scene) is False
    finally:
        tempfile.tempdir = writable
    panel = _PanelSelf()
    ext.ui.render_panel.VOLUMEEVM_PT_render.draw(panel, context)
    said = [t for t in texts(panel.calls) if t.startswith("Viewport colours as 'Standard':")]
    assert said and "could not be baked" in " ".join(texts(panel.calls))
    view_settings.exposure = 0.5
    assert lut.refresh(context.scene) is True and lut.table(context.scene)[1]
    panel = _PanelSelf()
    ext.ui.render_panel.VOLUMEEVM_PT_render.draw(panel, context)
    assert not [t for t in texts(panel.calls) if t.startswith("Viewport colours")]
    view_settings.exposure = 0.0
    lut.free()
    settings.viewport = False

    surface = api.make_mesh(obj)  # the surface is active now: panels show its volume
    shown = texts(draw_all(ext, context))
    assert f"{surface.name}: {len(surface.data.vertices):,} vertices, " \
           f"{len(surface.data.polygons):,} faces" in shown

    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    assert "Kept beside the .blend" in texts(draw_all(ext, context))
    (tmp_path / "scene_volumeevm" / "ct_skull_cgal.vevm").unlink()
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "scene.blend"))
    bpy.context.view_layer.objects.active = bpy.data.objects["ct_skull_cgal"]
    shown = texts(draw_all(ext, bpy.context))
    assert "VolumeEVM problem:" in shown
    assert "Not in memory: Build re-reads the source" in shown


# ---------------------------------------------------------------------------- modal driver
class _WindowManager:
    def __init__(self):
        self.timers = []
        self.handlers = []

    def event_timer_add(self, step, window=None):
        self.timers.append(step)
        return step

    def event_timer_remove(self, timer):
        self.timers.remove(timer)

    def modal_handler_add(self, operator):
        self.handlers.append(operator)


class _Context:
    def __init__(self):
        self.window_manager = _WindowManager()
        self.window = object()
        self.screen = None


class _Event:
    def __init__(self, kind):
        self.type = kind


def _driver(ext, make_job):
    class Driver(ext.blender.jobs.JobOperator):
        reports = []

        def job(self, context):
            return make_job()

        def report(self, kind, message):
            self.reports.append((kind, message))

    return Driver()


def _ticks(op, context, limit=200):
    """Send timer events until the modal operator finishes; returns its last result."""
    for _ in range(limit):
        result = op.modal(context, _Event("TIMER"))
        if result != {"RUNNING_MODAL"}:
            return result
        time.sleep(0.01)
    raise AssertionError("the job did not finish")


def test_modal_driver_runs_steps_in_a_thread_and_commits(ext, data_dir):
    api, jobs = ext.blender.api, ext.blender.jobs
    obj = api.import_volume(data_dir / SKULL)
    threads = []

    def make_job():
        job = ext.blender.volumes.build_job(obj, 2.9)

        def steps():
            threads.append(threading.current_thread().name)
            result = yield from job.steps
            threads.append(threading.current_thread().name)
            return result

        return jobs.Job(job.label, steps(), job.commit)

    context = _Context()
    op = _driver(ext, make_job)
    assert op.start(context) == {"RUNNING_MODAL"}
    assert context.window_manager.handlers == [op] and jobs.CURRENT.label.startswith("Build")
    assert op.modal(context, _Event("LEFTMOUSE")) == {"RUNNING_MODAL"}  # held while running
    assert op.modal(context, _Event("WHEELUPMOUSE")) == {"PASS_THROUGH"}  # navigation passes
    assert _ticks(op, context) == {"FINISHED"}
    assert jobs.CURRENT is None and context.window_manager.timers == []
    assert threads and all(name.startswith("volumeevm") for name in threads)
    assert obj.volumeevm.voxel_count == api.get_vevm(obj).voxel_count > 0
    assert op.reports == []


def test_modal_driver_escape_leaves_scene_unchanged(ext, data_dir):
    api, jobs = ext.blender.api, ext.blender.jobs
    obj = api.import_volume(data_dir / SKULL)
    release = threading.Event()

    def slow_steps():
        yield 0.0, "waiting"
        release.wait(5)
        yield 0.5, "still waiting"
        return "never committed"

    committed = []
    op = _driver(ext, lambda: jobs.Job("Slow", slow_steps(), committed.append))
    context = _Context()
    before = (len(bpy.data.objects), obj.volumeevm.vevm_path)
    assert op.start(context) == {"RUNNING_MODAL"}
    assert op.start(_Context()) == {"CANCELLED"}  # one job at a time
    assert op.modal(context, _Event("ESC")) == {"CANCELLED"}
    release.set()
    op._executor.shutdown(wait=True)
    assert committed == [] and jobs.CURRENT is None
    assert (len(bpy.data.objects), obj.volumeevm.vevm_path) == before
    assert ({"WARNING"}, "Slow: cancelled, nothing changed") in op.reports


def test_modal_driver_reports_errors(ext, data_dir):
    api, jobs = ext.blender.api, ext.blender.jobs
    obj = api.import_volume(data_dir / SKULL)
    op = _driver(ext, lambda: ext.blender.volumes.build_job(obj, 1000.0))
    context = _Context()
    assert op.start(context) == {"RUNNING_MODAL"}
    assert _ticks(op, context) == {"CANCELLED"}
    assert jobs.CURRENT is None
    assert op.reports and "the region is empty" in op.reports[-1][1]
    assert obj.volumeevm.vevm_path == ""
