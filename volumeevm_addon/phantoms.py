"""Test volumes made in code, with closed-form images where they exist (like ``skimage.data``).

The public face of :mod:`._phantoms`, which documents each volume and its closed form. Every
function returns a :class:`~volumeevm_addon.Volume` (spacing 1 mm unless told otherwise), so
``VolumeEVM.from_volume(vol, threshold)`` builds its region:

>>> from volumeevm_addon import VolumeEVM, phantoms
>>> vol = phantoms.box((8, 8, 8), lo=(2, 2, 2), hi=(6, 6, 6))
>>> VolumeEVM.from_volume(vol, 0.5).voxel_count
64
"""

from ._phantoms import (
    blobs_optical_depth,
    box,
    box_chords_mm,
    checker,
    extinction_tf,
    gaussian_blobs,
    marschner_lobb,
    marschner_lobb_value,
    noise,
    ramp,
    shell,
    thin_plate,
    timing_volume,
)

__all__ = ["marschner_lobb", "marschner_lobb_value", "box", "box_chords_mm", "gaussian_blobs",
           "blobs_optical_depth", "extinction_tf", "ramp", "checker", "thin_plate", "shell",
           "noise", "timing_volume"]
