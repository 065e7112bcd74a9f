"""The add-on's objects: volume objects and their surface objects, and which one is meant.

A *volume object* (``obj.volumeevm.role == "VOLUME"``) is the wire box of an imported grid; its
VolumeEVM lives in a sidecar file (:mod:`.sidecar`). Its *surface object* (``"SURFACE"``) is the
mesh of the VolumeEVM's boundary (or of its tool stack's result), a child of the volume object.
Operators, panels and the script API all find the volume they act on here.
"""

import functools

import bpy

from ..volumeevm_addon import VolumeEVMError
from . import jobs, sidecar


def require_enabled():
    """Raise a :class:`VolumeEVMError` saying how to enable the extension when it is not
    registered (its properties are missing: a script imported the API of a disabled one)."""
    if not hasattr(bpy.types.Object, "volumeevm"):
        package = __package__.rpartition(".")[0]
        raise VolumeEVMError(f"the VolumeEVM extension is not enabled: call "
                             f"bpy.ops.preferences.addon_enable(module={package!r})")


def volume_object(obj):
    """The volume object of ``obj`` (itself, or the volume a surface was made from).

    Raises
    ------
    VolumeEVMError
        If ``obj`` is not a VolumeEVM volume or surface object, or the extension is not enabled.
    """
    require_enabled()
    if obj is None:
        raise VolumeEVMError("no object given; select a volume made by Import Volume")
    settings = obj.volumeevm
    if settings.role == "VOLUME":
        return obj
    if settings.role == "SURFACE" and settings.volume is not None:
        return settings.volume
    raise VolumeEVMError(f"{obj.name}: not a VolumeEVM volume; import a volume first")


def active_volume(context):
    """The volume object of the active object (itself, the volume of a surface, or of a label
    object Make Label Meshes made), or None."""
    obj = context.active_object
    if obj is None:
        return None
    s = obj.volumeevm
    if s.role == "VOLUME":
        return obj
    if s.role == "SURFACE" and s.volume is not None:
        return s.volume
    owner = obj.parent.parent if "volumeevm_label" in obj and obj.parent is not None else None
    if owner is not None and owner.volumeevm.role == "VOLUME":
        return owner
    return None


def poll_volume(cls, context, *, built):
    """The volume an operator acts on (``built``: with its VolumeEVM), or None with the poll
    message saying why the button is disabled."""
    obj = active_volume(context)
    if obj is None:
        cls.poll_message_set("Select a volume object (File > Import > Volume (VolumeEVM))")
        return None
    if built and not obj.volumeevm.vevm_path:
        cls.poll_message_set("No VolumeEVM built yet: build one first")
        return None
    if jobs.CURRENT is not None:
        cls.poll_message_set(f"Busy: {jobs.CURRENT.label}")
        return None
    return obj


def render_volume(context, settings):
    """The volume the Render settings mean: their volume, else the active one, else the only one."""
    if settings.volume is not None:
        return settings.volume
    obj = active_volume(context)
    if obj is not None:
        return obj
    volumes = [o for o in context.scene.objects if o.volumeevm.role == "VOLUME"]
    return volumes[0] if len(volumes) == 1 else None


def get_vevm(obj):
    """The VolumeEVM of a volume (or surface) object, from the cache or its sidecar."""
    return sidecar.load_vevm(volume_object(obj))


def own_surface(vol_obj):
    """The surface object made from this volume (not one a duplicate still points at), or None."""
    surface = vol_obj.volumeevm.surface
    if surface is not None and surface.type == "MESH" and surface.volumeevm.volume == vol_obj:
        return surface
    return None


def link(context, obj):
    """Link ``obj`` into the active collection and make it the only selected, active object."""
    collection = context.collection or context.scene.collection
    collection.objects.link(obj)
    view_layer = context.view_layer
    if view_layer is None:
        return
    view_layer.update()  # sync the layer with the collection before selecting
    if view_layer.objects.get(obj.name) is None:
        return  # the active collection is excluded from the view layer
    for other in view_layer.objects:
        if other.select_get():
            other.select_set(False)
    obj.select_set(True)
    view_layer.objects.active = obj


def attach_surface(context, owner, mesh):
    """Give ``mesh`` to the owner's surface object (keeping its materials), or make one.

    In a job's commit the change is undone if the job fails (:func:`.jobs.transaction`), and
    the replaced mesh is removed only once it succeeded.
    """
    surface = own_surface(owner)
    if surface is not None:
        old = surface.data
        for material in old.materials:
            mesh.materials.append(material)
        jobs.assign(surface, data=mesh)
        jobs.on_success(functools.partial(_remove_unused_mesh, old))
        return surface
    surface = bpy.data.objects.new(f"{owner.name}_surface", mesh)
    surface.volumeevm.role = "SURFACE"
    surface.volumeevm.volume = owner
    surface.parent = owner
    jobs.assign(owner.volumeevm, surface=surface)
    link(context, surface)
    return surface


def _remove_unused_mesh(mesh):
    if mesh.users == 0:
        bpy.data.meshes.remove(mesh)
