"""The region as a native Blender Volume object (a sparse OpenVDB grid) for Cycles and EEVEE.

Grid
----
One ``FloatGrid`` named ``density``: exactly the region's voxels are active, with their
densities (the tool stack's result when the volume has tools) in float32. Grid coordinates
``(i, j, k)`` are the volume's own voxel indices; the grid's transform is the volume's
``index_to_physical`` times :data:`BLENDER_UNITS_PER_MM` (1 mm = 0.001 BU), so a voxel centre
lands where the surface mesh has the middle of that voxel's cell. The Volume object is a child
of the volume object with identity local matrix, like the surface. The background (inactive)
value is just below the region's smallest density (:func:`grid_background`): copying the
region's box with that background activates exactly the region's voxels, and the renderers'
trilinear lookups across the region's surface see a value that continues the data there rather
than a jump to 0.

Blender's Volume API only loads and saves files, so the grid goes through a ``.vdb`` file: in
the sidecar folder beside the saved .blend (``<blend>_volumeevm/<object>.vdb``), else in the
session's temporary folder; written atomically, a file of that name that is not this object's
is never replaced (another name is taken). ``File > External Data > Pack Resources`` packs it.

Material: the same optical model as our renderers
-------------------------------------------------
Our renderers (:mod:`volumeevm_addon` transfer functions) give each density an opacity ``a``
per ``Δ0 = unit_length_mm`` of path and a straight colour ``c``; a segment of ``Δ`` mm gets
``a' = 1 - (1 - a)^(Δ/Δ0)`` and adds ``c·a'`` (premultiplied) behind the transmittance so far.
That is exactly the emission–absorption integral with extinction per mm
``σ = -ln(1 - a) / Δ0`` and emission ``c·σ`` per mm, constant along the segment:
``∫0^Δ exp(-σt) c σ dt = c (1 - exp(-σΔ)) = c·a'``. Cycles and EEVEE integrate
``L = ∫ T(s) E(s) ds`` with ``T = exp(-∫ σ_a)``, both per Blender unit, so the material sets

- absorption density ``σ_a = 1000 · (-ln(1 - min(a, 1 - 1e-6))) / Δ0`` per BU (opacity 1 is
  capped: a transmittance of 1e-6 per unit length, as black as a render shows),
- emission colour ``c`` with strength ``σ_a`` (so emission ``c·σ_a`` per BU), no scattering,

where ``(c, a)`` come from a Color Ramp with the transfer function's points (positions
``(value - lo)/(hi - lo)`` after a clamped Map Range of the density, linear interpolation,
colour in the ramp's RGB and opacity in its alpha, as in the Render settings). Both are
multiplied by ``density > (background + smallest density)/2``: outside the region nothing
is emitted or absorbed whatever the transfer function says about the background value.
"""

import functools
import importlib
import shutil
import time
from pathlib import Path

import bpy
import numpy as np

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.model import BLENDER_UNITS_PER_MM
from ..volumeevm_addon.system import check_memory, write_atomically
from . import jobs, runtime, sidecar
from .objects import get_vevm, link, volume_object
from .transfer import ensure_ramp, transfer_function

GRID_NAME = "density"
#: Largest opacity per unit length the material uses (opacity 1 has no finite absorption).
ALPHA_CAP = 1.0 - 1e-6
#: OpenVDB leaf nodes are 8³ voxels; the grid's memory and file are estimated per leaf.
_LEAF = 8
_refresh_times = {}  # volume object name -> last refresh's timings (seconds)


def openvdb_module():
    """Blender's bundled ``openvdb`` module (the ``bpy`` module exposes it on request).

    Raises
    ------
    VolumeEVMError
        When this Blender has no ``openvdb`` module.
    """
    try:
        return importlib.import_module("openvdb")
    except ImportError:
        pass
    expose = getattr(bpy.utils, "expose_bundled_modules", None)
    if expose is not None:
        expose()
        try:
            return importlib.import_module("openvdb")
        except ImportError:
            pass
    raise VolumeEVMError("this Blender has no OpenVDB Python module (openvdb): native volumes "
                         "need a Blender build with it; the DVR and meshes work without it")


def grid_matrix(vevm):
    """4x4 matrix (column vectors) from voxel indices to the volume object's local space (BU)."""
    matrix = vevm.index_to_physical().copy()
    matrix[:3, :] *= BLENDER_UNITS_PER_MM
    return matrix


def grid_background(vevm):
    """The grid's background: float32 just below the region's smallest density (by 1e-3 of the
    density range, at least 1e-3 of its magnitude), so no region voxel has it."""
    table = vevm.table()
    lo, hi = float(table.min()), float(table.max())
    step = max(1e-3 * (hi - lo), 1e-3 * abs(lo), 1e-3)
    background = np.float32(lo - step)
    if not background < np.float32(lo):
        raise VolumeEVMError(f"densities: no float32 value below the smallest density {lo!r}")
    return float(background), lo


def _check_grid_memory(vevm):
    """Refuse a grid whose box copy and leaf nodes would not fit in memory."""
    lo, hi = vevm.evm.bounds()
    box = int(np.prod(np.subtract(hi, lo), dtype=np.float64))
    leaves = min(box, vevm.voxel_count * _LEAF ** 3) // _LEAF ** 3 + 1
    needed = box * 5 + leaves * (_LEAF ** 3 * 4 + 64)
    check_memory(needed, "making the OpenVDB grid", source=f"VolumeEVM region {vevm.shape}",
                 advice="clip the region to the part you need, or raise the threshold")


def region_grid(vevm):
    """The region as a sparse OpenVDB ``FloatGrid`` named ``density`` (see the module's notes).

    Raises
    ------
    VolumeEVMError
        No ``openvdb`` module, an empty region, or not enough memory for the grid.
    """
    openvdb = openvdb_module()
    if vevm.voxel_count == 0:
        raise VolumeEVMError("the region is empty: nothing to write as a volume")
    _check_grid_memory(vevm)
    background, _ = grid_background(vevm)
    lo, box = vevm.dense_box(background)
    grid = openvdb.FloatGrid(background)
    grid.name = GRID_NAME
    grid.copyFromArray(box, ijk=lo, tolerance=0.0)
    grid.transform = openvdb.createLinearTransform(grid_matrix(vevm).T)  # OpenVDB: row vectors
    return grid


def _vdb_path(vol_obj, native, blend_path=None):
    """Where the grid of ``vol_obj`` goes: its own file again, else a new free name (beside
    ``blend_path``, default the open .blend, else in the session's folder)."""
    name = f"{bpy.path.clean_name(vol_obj.name)}.vdb"
    blend_path = blend_path or bpy.data.filepath
    if blend_path:
        folder = sidecar.sidecar_dir(blend_path)
    else:
        folder = sidecar.session_dir()
    target = folder / name
    own = None
    if native is not None and native.data.filepath:
        own = Path(bpy.path.abspath(native.data.filepath))
    if target.exists() and (own is None or not _same(target, own)):
        target = folder / f"{target.stem}-{vol_obj.volumeevm.uid[:8]}.vdb"
        if target.exists() and (own is None or not _same(target, own)):
            raise VolumeEVMError(f"{target}: exists and is not this volume's grid; rename the "
                                 f"volume object or move the file")
    return target


def _same(a, b):
    try:
        return a.samefile(b)
    except OSError:
        return False


def write_grid(grid, path):
    """Write ``grid`` to ``path`` atomically (replacing the object's own earlier grid)."""
    write_atomically(path, lambda temporary: openvdb_module().write(str(temporary), grids=[grid]),
                     overwrite=True)


def live_vevm(vol_obj, depsgraph=None):
    """The VolumeEVM a volume shows: its tool stack's result (evaluated if needed), else its own."""
    if len(vol_obj.volumeevm.tools):
        state = runtime.stack_state(vol_obj.volumeevm.uid, vol_obj.name)
        if state is not None and state.result is not None:
            return state.result
        from .tool_stack import refresh
        depsgraph = depsgraph or bpy.context.evaluated_depsgraph_get()
        result = refresh(vol_obj, depsgraph, force=True)
        if result is not None:
            return result
    return get_vevm(vol_obj)


# ---------------------------------------------------------------------------- material
def _node(tree, kind, location, **inputs):
    node = tree.nodes.new(kind)
    node.location = location
    for name, value in inputs.items():
        node.inputs[name].default_value = value
    return node


def _math(tree, operation, location, a=None, b=None):
    node = tree.nodes.new("ShaderNodeMath")
    node.operation = operation
    node.location = location
    for socket, value in zip(node.inputs, (a, b)):
        if value is not None:
            socket.default_value = value
    return node


def fill_material(material, tf, threshold):
    """Build ``material``'s nodes from ``tf``: the emission–absorption of the module's notes,
    zero where the density is not above ``threshold`` (outside the region)."""
    if bpy.app.version < (5, 0, 0):
        material.use_nodes = True
    tree = material.node_tree
    tree.nodes.clear()
    links = tree.links
    points = np.asarray(tf.points, np.float64)
    lo, hi = tf.value_range
    if hi <= lo:
        hi = lo + 1.0
    attribute = tree.nodes.new("ShaderNodeAttribute")
    attribute.attribute_name = GRID_NAME
    attribute.location = (-1000, 0)
    density = attribute.outputs["Fac"]
    to_ramp = _node(tree, "ShaderNodeMapRange", (-800, 0), **{
        "From Min": lo, "From Max": hi, "To Min": 0.0, "To Max": 1.0})
    to_ramp.clamp = True
    links.new(density, to_ramp.inputs["Value"])
    ramp_node = tree.nodes.new("ShaderNodeValToRGB")
    ramp_node.location = (-600, 0)
    ramp = ramp_node.color_ramp
    ramp.interpolation, ramp.color_mode = "LINEAR", "RGB"
    while len(ramp.elements) > 1:
        ramp.elements.remove(ramp.elements[-1])
    for _ in range(len(points) - 1):
        ramp.elements.new(1.0)
    for element, row in zip(ramp.elements, points):
        element.position = float((row[0] - lo) / (hi - lo))
        element.color = tuple(float(v) for v in row[1:5])
    links.new(to_ramp.outputs["Result"], ramp_node.inputs["Fac"])
    capped = _math(tree, "MINIMUM", (-400, -200), b=ALPHA_CAP)
    links.new(ramp_node.outputs["Alpha"], capped.inputs[0])
    clear = _math(tree, "SUBTRACT", (-250, -200), a=1.0)
    links.new(capped.outputs[0], clear.inputs[1])
    log = _math(tree, "LOGARITHM", (-100, -200), b=float(np.e))
    links.new(clear.outputs[0], log.inputs[0])
    per_bu = _math(tree, "MULTIPLY", (50, -200), b=-1.0 / (tf.unit_length_mm *
                                                             BLENDER_UNITS_PER_MM))
    links.new(log.outputs[0], per_bu.inputs[0])
    inside = _math(tree, "GREATER_THAN", (50, -400), b=float(threshold))
    links.new(density, inside.inputs[0])
    sigma = _math(tree, "MULTIPLY", (200, -250))
    links.new(per_bu.outputs[0], sigma.inputs[0])
    links.new(inside.outputs[0], sigma.inputs[1])
    emission = _node(tree, "ShaderNodeEmission", (400, 100))
    links.new(ramp_node.outputs["Color"], emission.inputs["Color"])
    links.new(sigma.outputs[0], emission.inputs["Strength"])
    absorption = _node(tree, "ShaderNodeVolumeAbsorption", (400, -150),
                       Color=(0.0, 0.0, 0.0, 1.0))
    links.new(sigma.outputs[0], absorption.inputs["Density"])
    add = _node(tree, "ShaderNodeAddShader", (600, 0))
    links.new(emission.outputs[0], add.inputs[0])
    links.new(absorption.outputs[0], add.inputs[1])
    output = _node(tree, "ShaderNodeOutputMaterial", (800, 0))
    links.new(add.outputs[0], output.inputs["Volume"])


def transparent_note(tf, vevm):
    """A warning when ``tf`` makes every density of the region transparent, else ""."""
    table = vevm.table()
    lo, hi = float(table.min()), float(table.max())
    if bool(tf.transparent_between(lo, hi)):
        return (f"the transfer function is transparent over the region's densities "
                f"{lo:g} .. {hi:g}: the native volume renders empty; choose another preset or "
                f"raise the ramp's alpha")
    return ""


# ---------------------------------------------------------------------------- the object
def own_native(vol_obj):
    """The native Volume object made from this volume, or None."""
    native = vol_obj.volumeevm.native
    if native is not None and native.type == "VOLUME" and native.volumeevm.volume == vol_obj:
        return native
    return None


def _load(volume_data, path):
    volume_data.filepath = str(path)
    volume_data.grids.unload()
    volume_data.grids.load()
    if not volume_data.grids.is_loaded or volume_data.grids.get(GRID_NAME) is None:
        raise VolumeEVMError(f"{path}: Blender could not load the grid "
                             f"({volume_data.grids.error_message or 'no density grid'})")


def _write_and_load(vol_obj, native, vevm, timing):
    start = time.perf_counter()
    grid = region_grid(vevm)
    middle = time.perf_counter()
    path = _vdb_path(vol_obj, native)
    write_grid(grid, path)
    end = time.perf_counter()
    timing.update(grid_s=middle - start, write_s=end - middle)
    return grid, path


def _tf_of(scene):
    settings = scene.volumeevm_render
    ensure_ramp(settings)
    return transfer_function(settings)


def make_volume_object(obj, *, scene=None):
    """Make (or refresh) the native Blender Volume object of a volume's region.

    The region (its tool stack's result when it has tools) is written as a sparse OpenVDB
    grid to a ``.vdb`` file beside the .blend and loaded as a Volume object, child of the
    volume object, with a material from the scene's transfer function (Render settings) that
    Cycles and EEVEE integrate like our DVR (see the module's notes). The object, its grid and
    material then follow changes of the transfer function and of the tool stack.

    Parameters
    ----------
    obj : bpy.types.Object
        A volume object (or its surface) with a VolumeEVM built.
    scene : bpy.types.Scene, optional
        Whose Render settings hold the transfer function (default the context's).

    Returns
    -------
    bpy.types.Object
        The Volume object. When the transfer function is transparent over every density of the
        region, a warning is printed and kept as the volume's status (the sidebar shows it).

    Raises
    ------
    VolumeEVMError
        Not a volume, no VolumeEVM, no ``openvdb`` module, not enough memory, a file in the
        way; the scene is left as it was.
    """
    vol_obj = volume_object(obj)
    scene = scene or bpy.context.scene
    tf = _tf_of(scene)
    vevm = live_vevm(vol_obj)
    native = own_native(vol_obj)
    timing = {}
    grid, path = _write_and_load(vol_obj, native, vevm, timing)
    background, smallest = grid_background(vevm)
    with jobs.transaction():
        if native is None:
            data = bpy.data.volumes.new(f"{vol_obj.name}_native")
            native = bpy.data.objects.new(f"{vol_obj.name}_native", data)
            native.volumeevm.role = "NATIVE"
            native.volumeevm.volume = vol_obj
            native.parent = vol_obj
            jobs.assign(vol_obj.volumeevm, native=native)
            link(bpy.context, native)
        data = native.data
        data.render.precision = "FULL"  # HU need more than half floats near the background
        data.render.clipping = 0.0  # Cycles would drop voxels with |density| < clipping
        _load(data, bpy.path.relpath(str(path)) if bpy.data.filepath else path)
        material = data.materials[0] if len(data.materials) else None
        if material is None:
            material = bpy.data.materials.new(f"{vol_obj.name}_native")
            data.materials.append(material)
        fill_material(material, tf, (background + smallest) / 2)
    _remember(native, tf, vevm)
    timing["voxels"] = vevm.voxel_count
    timing["grid_bytes"] = int(grid.memUsage())
    timing["file_bytes"] = path.stat().st_size
    _refresh_times[vol_obj.name] = timing
    note = transparent_note(tf, vevm)
    runtime.set_status(vol_obj.volumeevm.uid, note)
    if note:
        print(f"[volumeevm] {vol_obj.name}: warning: {note}")
    return native


def last_timing(obj):
    """What the last write or refresh of a volume's native object took and made: seconds
    (``grid_s``, ``write_s``; ``material_s`` for a refresh) and sizes (``voxels``,
    ``grid_bytes``, ``file_bytes``), or {}."""
    return dict(_refresh_times.get(volume_object(obj).name, {}))


# ---------------------------------------------------------------------------- following changes
_shown = {}  # native object name -> (transfer function points, unit length, id of the VolumeEVM)


def _tf_key(tf):
    return (np.asarray(tf.points).tobytes(), tf.unit_length_mm)


def _remember(native, tf, vevm):
    _shown[native.name] = (_tf_key(tf), id(vevm))


def refresh(vol_obj, scene, depsgraph=None):
    """Bring a volume's native object up to date: a new grid when the region changed (tool
    stack), a new material when the transfer function changed. Returns what it redid
    (``"grid"``, ``"material"`` or ``""``)."""
    native = own_native(vol_obj)
    if native is None:
        return ""
    tf = _tf_of(scene)
    vevm = live_vevm(vol_obj, depsgraph)
    shown = _shown.get(native.name)
    if shown == (_tf_key(tf), id(vevm)):
        return ""
    if shown is not None and shown[1] == id(vevm):
        start = time.perf_counter()
        background, smallest = grid_background(vevm)
        fill_material(native.data.materials[0], tf, (background + smallest) / 2)
        _refresh_times[vol_obj.name] = {"material_s": time.perf_counter() - start}
        _remember(native, tf, vevm)
        runtime.set_status(vol_obj.volumeevm.uid, transparent_note(tf, vevm))
        return "material"
    make_volume_object(vol_obj, scene=scene)
    return "grid"


@bpy.app.handlers.persistent
def on_depsgraph_update_post(scene, depsgraph):
    """Follow the transfer function and tool stacks (after the stacks' own handler)."""
    volumes = [o for o in scene.objects if o.volumeevm.role == "VOLUME" and own_native(o)]
    for vol_obj in volumes:
        try:
            refresh(vol_obj, scene, depsgraph)
        except VolumeEVMError as error:
            runtime.set_status(vol_obj.volumeevm.uid, f"native volume not updated: {error}")
            print(f"[volumeevm] {vol_obj.name}: native volume not updated: {error}")


@bpy.app.handlers.persistent
def on_save_pre(filepath, *_args):
    """Copy each native volume's grid beside the .blend being written (atomically, never over
    a foreign file) and store its ``//``-relative path; packed grids stay packed."""
    filepath = filepath or bpy.data.filepath
    if not filepath:
        return
    for native in [o for o in bpy.data.objects if o.volumeevm.role == "NATIVE"]:
        vol_obj = native.volumeevm.volume
        data = native.data
        if vol_obj is None or data is None or data.packed_file is not None or not data.filepath:
            continue
        source = Path(bpy.path.abspath(data.filepath))
        folder = sidecar.sidecar_dir(filepath)
        if not source.is_file() or source.parent == folder:
            continue
        try:
            target = _vdb_path(vol_obj, None, filepath)
            write_atomically(target, functools.partial(shutil.copyfile, source),
                             overwrite=False)
        except (OSError, VolumeEVMError) as error:
            print(f"[volumeevm] {native.name}: could not copy its grid beside the .blend: {error}")
            continue
        data.filepath = bpy.path.relpath(str(target), start=str(Path(filepath).parent))


HANDLERS = (("depsgraph_update_post", on_depsgraph_update_post), ("save_pre", on_save_pre))
