"""The Blender side's machinery: everything between the operators and panels and the core.

Operators (``operators/``) and panels (``ui/``) read Blender state and call functions here;
these convert between Blender data and the core's arrays and records (``volumeevm_addon``, which
never imports ``bpy``). Imports go one way: ``operators`` and ``ui`` import ``blender``, which
imports the core, never the reverse. One module per concept:

- ``api.py``: the script API, a thin facade over the modules below.
- ``volumes.py``: import a volume, build its VolumeEVM, make its surface mesh (jobs).
- ``objects.py``: volume and surface objects, and which one an operator or panel means.
- ``meshes.py``: meshes in and out of Blender in bulk (surface polygons, tool triangles).
- ``tool_stack.py``: the CAD tool stack runtime (entries, evaluation, live refresh handlers).
- ``dvr.py``: the DVR render job and its script calls (scene pass, volume render, composite).
- The GPU method through Blender's ``gpu`` module: ``gpu_context.py`` (whether this Blender can
  draw here: the GPU context, headless too), ``gpu_textures.py`` (the core's GPU inputs as
  textures, kept while used), ``gpu_draw.py`` (the shaders from the core's ``.glsl`` files, the
  one draw routine, the offscreen render read back); ``gpu_viewport.py``: the selected volumes'
  DVR in the 3D viewport (its draw handler).
- ``scene.py``: the scene pass (colour and depth read back through a temporary EXR).
- ``camera.py``: the core's camera record from a Blender camera.
- ``framing.py``: a camera that frames a volume; the objects that enclose (hide) it.
- ``images.py``: Image datablocks and image files written inside a job's transaction.
- ``exr.py``: OpenEXR through the core, or through Blender's OpenImageIO.
- ``transfer.py``: the transfer function as the Render settings' colour ramp.
- ``label_table.py``: a label map's label table on its volume object (colour, opacity, shown)
  and the categorical transfer function the renderers take from it.
- ``compositor.py``: the compositor set-up for F12 and its stale-image check.
- ``sidecar.py``: where VolumeEVM files live beside the .blend, and the save/load handlers.
- ``jobs.py``: long work as steps and an all-or-nothing commit; the operators' job mix-in.
- ``kernels.py``: the core's compiled kernels in Blender (cache folder, threads, first use).
- ``runtime.py``: runtime caches (dense volumes, loaded VolumeEVMs, tool stack states).
- ``handlers.py``: adding and removing the add-on's app handlers and viewport draw handlers.
"""
