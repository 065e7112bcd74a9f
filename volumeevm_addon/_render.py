"""One entry point for direct volume rendering of a VolumeEVM, whatever the method.

Every method reads the VolumeEVM (its EVM for empty-space skipping, its densities tables) and
returns the same thing: a premultiplied RGBA image (row 0 at the top) and the axial depth of the
first visible sample in Blender units (1e10 where nothing is visible), for the scene camera.
The dense reference ray caster of :mod:`._reference` is the accuracy oracle of all of them.

Boundary policy ("clamp", :mod:`._reference`): voxels outside the region are transparent and
never read; interpolation at the region's surface uses only the region's voxels (weights
renormalised). Rendering a VolumeEVM therefore equals rendering the dense volume with
everything outside the region transparent, which is the exactness contract every method keeps.

Resolution levels (:mod:`._levels`): ``level="auto"`` renders a volume much finer than the
image's pixels from a coarser VolumeEVM (cached on the VolumeEVM); the exactness contract holds
for the level rendered, and the default ``level="full"`` renders the VolumeEVM itself.
"""


from ._levels import level_factor
from ._reference import MODES
from ._volume import grid_to_world

METHODS = ("shear_warp", "splat", "raycast", "raycast_navigate", "reference")


def render(vevm, camera, tf, *, method="shear_warp", mode="over", depth_in=None, matrix_world=None,
           level="full", **options):
    """Render ``vevm`` seen by ``camera`` with transfer function ``tf``.

    Parameters
    ----------
    vevm : VolumeEVM
    camera : Camera
        Blender's projection (see :mod:`._camera`).
    tf : TransferFunction
    method : {"shear_warp", "splat", "raycast", "raycast_navigate", "reference"}
    mode : {"over", "under", "xray", "mip"}
    depth_in : (H, W) ndarray, optional
        Axial depth (Blender units) of the scene's geometry; rays stop there.
    matrix_world : (4, 4) array_like, optional
        Placement of the volume object in the scene (identity by default).
    level : {"full", "auto"} or int
        Resolution level: ``"full"`` (default) renders ``vevm`` itself; an integer ``f >= 2``
        renders ``vevm.level(f)``, ``f`` times coarser voxels; ``"auto"`` picks the coarsest
        power of two whose voxels are still no wider than a pixel where the volume is nearest
        the camera (:func:`._levels.auto_factor`). A coarser level scales a given ``step_mm``
        by the factor (the ray casters keep their samples per voxel). The reference method
        ignores it: it is the full-resolution oracle.
    **options
        Method-specific quality settings.

    Returns
    -------
    rgba : (H, W, 4) float32
        Premultiplied colour and opacity, row 0 at the top of the image.
    depth : (H, W) float32
        Axial depth in Blender units of the first visible sample; 1e10 where none.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, matrix_world)
    factor = level_factor(level, vevm.shape, to_world, camera)
    if method == "reference":
        from ._reference import render_reference

        return render_reference(vevm.to_dense(), vevm.evm.to_mask(vevm.shape), to_world,
                                vevm.spacing, camera, tf, mode=mode, depth_in=depth_in, **options)
    if factor > 1:
        vevm = vevm.level(factor)
        to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, matrix_world)
        if options.get("step_mm") is not None:
            options["step_mm"] = options["step_mm"] * factor
    renderer = _renderers()[method]
    return renderer(vevm, camera, tf, to_world, mode=mode, depth_in=depth_in, **options)


def _renderers():
    """The method implementations, imported when first used."""
    from ._raycast import render_raycast, render_raycast_navigate
    from ._shear_warp import render_shear_warp
    from ._splat import render_splat

    return {"shear_warp": render_shear_warp, "splat": render_splat, "raycast": render_raycast,
            "raycast_navigate": render_raycast_navigate}
