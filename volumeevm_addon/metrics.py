"""How far a rendered image is from the reference: one frame, or a sweep of frames.

The public face of :mod:`._metrics`, which documents each measure. Images are premultiplied
RGBA arrays ``(H, W, 4)``, as :func:`volumeevm_addon.render` returns them:

>>> import numpy as np
>>> from volumeevm_addon import metrics
>>> image, reference = np.zeros((2, 2, 4)), np.full((2, 2, 4), 0.5)
>>> float(metrics.rmse(image, reference))
0.5
"""

from ._metrics import (
    bias_jump,
    image_errors,
    luminance,
    popping_index,
    rmse,
    spectral_peak,
    temporal_errors,
)

__all__ = ["image_errors", "rmse", "luminance", "popping_index", "temporal_errors", "bias_jump",
           "spectral_peak"]
