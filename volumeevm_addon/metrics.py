"""How far a rendered image is from the reference: one frame, or a sweep of frames.

Images are premultiplied RGBA arrays ``(H, W, 4)``, as :func:`volumeevm_addon.render` returns
them. Premultiplied values do not depend on the background and add linearly in compositing, so
their RMSE is the primary measure (``../shared/design/notes/dvr_evaluation.md`` §3). The sweep
measures follow the same notes: a popping index and a bias jump for an orbit through the
principal-axis switch, the temporal error frame to frame, and the spectral peak of an error image
that shows banding (wood grain) of ray sampling.

>>> import numpy as np
>>> from volumeevm_addon import metrics
>>> image, reference = np.zeros((2, 2, 4)), np.full((2, 2, 4), 0.5)
>>> float(metrics.rmse(image, reference))
0.5
"""

import numpy as np

__all__ = ["image_errors", "rmse", "luminance", "popping_index", "temporal_errors", "bias_jump",
           "spectral_peak"]

FOREGROUND_ALPHA = 1e-3
"""Pixels where either image's opacity exceeds this count as foreground in the masked RMSE."""


def _pair(image, reference):
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise ValueError(f"image shape {a.shape} differs from reference shape {b.shape}")
    return a, b


def rmse(image, reference):
    """Root mean square difference over every pixel and channel."""
    a, b = _pair(image, reference)
    return float(np.sqrt(np.mean((a - b) ** 2))) if a.size else 0.0


def image_errors(image, reference):
    """The per-image measures of one render against its reference.

    Returns
    -------
    dict
        ``rmse`` and ``psnr`` (dB, 1 = full range) over premultiplied RGBA, ``rmse_alpha``
        (opacity only: coverage and opacity-correction errors), ``max_abs`` (the worst pixel
        channel: local failures), ``mae``, and ``rmse_foreground`` over the pixels where
        either image is not transparent (so empty background does not dilute the error).
    """
    a, b = _pair(image, reference)
    d = a - b
    err = float(np.sqrt(np.mean(d * d))) if d.size else 0.0
    fg = (a[..., 3] > FOREGROUND_ALPHA) | (b[..., 3] > FOREGROUND_ALPHA)
    return {
        "rmse": err,
        "psnr": float("inf") if err == 0.0 else float(-20.0 * np.log10(err)),
        "rmse_alpha": float(np.sqrt(np.mean(d[..., 3] ** 2))) if d.size else 0.0,
        "max_abs": float(np.abs(d).max()) if d.size else 0.0,
        "mae": float(np.abs(d).mean()) if d.size else 0.0,
        "rmse_foreground": float(np.sqrt(np.mean(d[fg] ** 2))) if fg.any() else 0.0,
    }


def luminance(image):
    """Mean premultiplied luminance (Rec. 709 weights) of each image: the global scalar ``m``
    whose jumps between frames show popping. Accepts one image or a stack ``(N, H, W, 4)``."""
    rgb = np.asarray(image, dtype=np.float64)[..., :3]
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    return lum.mean(axis=(-2, -1))


def popping_index(images, references):
    """Largest frame-to-frame change of the mean luminance, relative to the reference's typical
    (median) change over the same sweep: about 1 for a method that changes as smoothly as the
    truth, much more than 1 for a jump (principal-axis switch)."""
    m_img = np.diff(luminance(images))
    m_ref = np.diff(luminance(references))
    typical = np.median(np.abs(m_ref))
    return float(np.abs(m_img).max() / max(typical, 1e-12))


def temporal_errors(images, references):
    """``TE(t) = RMSE(I[t+1] - I[t], R[t+1] - R[t])`` for each consecutive pair of frames: zero
    when the method changes exactly as the reference does, whatever its static error."""
    a = np.diff(np.asarray(images, dtype=np.float64), axis=0)
    b = np.diff(np.asarray(references, dtype=np.float64), axis=0)
    return np.sqrt(np.mean((a - b) ** 2, axis=(1, 2, 3)))


def bias_jump(angles, images, references, at=45.0, width=5.0):
    """Change of the signed relative error of the mean luminance across ``at`` degrees: the
    mean over ``(at, at + width]`` minus the mean over ``[at - width, at)``."""
    angles = np.asarray(angles, dtype=np.float64)
    m_img, m_ref = luminance(images), luminance(references)
    signed = (m_img - m_ref) / np.maximum(np.abs(m_ref), 1e-12)
    before = (angles >= at - width) & (angles < at)
    after = (angles > at) & (angles <= at + width)
    if not before.any() or not after.any():
        raise ValueError(f"bias_jump needs angles on both sides of {at}")
    return float(signed[after].mean() - signed[before].mean())


def spectral_peak(error_image):
    """Strength of the most periodic pattern in a 2-D error image: the largest magnitude of its
    Fourier spectrum (mean removed, DC excluded) over the spectrum's mean magnitude. Regular
    banding gives a sharp peak; noise of the same energy spreads out (about 3–4)."""
    e = np.asarray(error_image, dtype=np.float64)
    spectrum = np.abs(np.fft.rfft2(e - e.mean()))
    spectrum[0, 0] = 0.0
    mean = spectrum.mean()
    return float(spectrum.max() / mean) if mean > 0 else 0.0
