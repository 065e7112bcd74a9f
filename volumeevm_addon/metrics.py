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

from ._errors import VolumeEVMError

__all__ = ["image_errors", "rmse", "luminance", "popping_index", "temporal_errors", "bias_jump",
           "spectral_peak"]

FOREGROUND_ALPHA = 1e-3
"""Pixels where either image's opacity exceeds this count as foreground in the masked RMSE."""


def _pair(image, reference):
    a = np.asarray(image, dtype=np.float64)
    b = np.asarray(reference, dtype=np.float64)
    if a.shape != b.shape:
        raise VolumeEVMError(f"image shape {a.shape} differs from reference shape {b.shape}")
    return a, b


def rmse(image, reference):
    """Root mean square difference over every pixel and channel.

    Parameters
    ----------
    image, reference : array_like
        Images of the same shape, e.g. premultiplied RGBA ``(H, W, 4)``.

    Returns
    -------
    float
        0 for empty images.

    Raises
    ------
    VolumeEVMError
        When ``image`` and ``reference`` differ in shape.

    Examples
    --------
    >>> rmse([0.0, 0.0], [0.0, 2.0]) == 2 ** 0.5
    True
    """
    a, b = _pair(image, reference)
    return float(np.sqrt(np.mean((a - b) ** 2))) if a.size else 0.0


def image_errors(image, reference):
    """The per-image measures of one render against its reference.

    Parameters
    ----------
    image, reference : (H, W, 4) array_like
        Premultiplied RGBA, the render and the reference (:func:`volumeevm_addon.render`).

    Returns
    -------
    dict
        ``rmse`` and ``psnr`` (dB, 1 = full range) over premultiplied RGBA, ``rmse_alpha``
        (opacity only: coverage and opacity-correction errors), ``max_abs`` (the worst pixel
        channel: local failures), ``mae``, and ``rmse_foreground`` over the pixels where
        either image is not transparent (so empty background does not dilute the error).

    Raises
    ------
    VolumeEVMError
        If the two arrays differ in shape.

    Examples
    --------
    >>> errors = image_errors(np.zeros((1, 2, 4)), np.full((1, 2, 4), 0.1))
    >>> round(errors["psnr"], 6), errors["rmse_foreground"] == errors["rmse"]
    (20.0, True)
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
    """Mean premultiplied luminance (Rec. 709 weights) of each image.

    The global scalar ``m`` whose jumps between frames show popping.

    Parameters
    ----------
    image : (..., H, W, 3 or 4) array_like
        One image or a stack ``(N, H, W, 4)``; alpha is ignored.

    Returns
    -------
    float or ndarray of np.float64
        One value per image (a 0-d array for one image).

    Examples
    --------
    >>> float(luminance(np.ones((2, 2, 4))))
    1.0
    """
    rgb = np.asarray(image, dtype=np.float64)[..., :3]
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    return lum.mean(axis=(-2, -1))


def popping_index(images, references):
    """Largest frame-to-frame change of the mean luminance, relative to the reference's typical
    (median) change over the same sweep.

    About 1 for a method that changes as smoothly as the truth, much more than 1 for a jump
    (principal-axis switch).

    Parameters
    ----------
    images, references : (N, H, W, 4) array_like
        The frames of a sweep (N >= 2) and the reference's frames of the same views.

    Returns
    -------
    float
    """
    m_img = np.diff(luminance(images))
    m_ref = np.diff(luminance(references))
    typical = np.median(np.abs(m_ref))
    return float(np.abs(m_img).max() / max(typical, 1e-12))


def temporal_errors(images, references):
    """The temporal error ``TE(t) = RMSE(I[t+1] - I[t], R[t+1] - R[t])`` of each pair of
    consecutive frames.

    Zero when the method changes exactly as the reference does, whatever its static error.

    Parameters
    ----------
    images, references : (N, H, W, C) array_like
        The frames of a sweep and the reference's frames of the same views.

    Returns
    -------
    (N - 1,) ndarray of np.float64

    Examples
    --------
    >>> frames = np.zeros((3, 1, 1, 4)); frames[2] = 1.0
    >>> temporal_errors(frames + 0.5, frames).tolist()
    [0.0, 0.0]
    """
    a = np.diff(np.asarray(images, dtype=np.float64), axis=0)
    b = np.diff(np.asarray(references, dtype=np.float64), axis=0)
    return np.sqrt(np.mean((a - b) ** 2, axis=(1, 2, 3)))


def bias_jump(angles, images, references, at=45.0, width=5.0):
    """Change of the signed relative error of the mean luminance across ``at`` degrees.

    The mean over ``(at, at + width]`` minus the mean over ``[at - width, at)``: a method
    whose error changes sign or size where its principal axis switches shows a jump.

    Parameters
    ----------
    angles : (N,) array_like
        The view angle of each frame, degrees.
    images, references : (N, H, W, 4) array_like
        The frames and the reference's frames.
    at : float, optional
        The angle of the switch (default 45).
    width : float, optional
        Degrees on each side averaged (default 5).

    Returns
    -------
    float

    Raises
    ------
    VolumeEVMError
        When no angle lies within ``width`` before or after ``at``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    m_img, m_ref = luminance(images), luminance(references)
    signed = (m_img - m_ref) / np.maximum(np.abs(m_ref), 1e-12)
    before = (angles >= at - width) & (angles < at)
    after = (angles > at) & (angles <= at + width)
    if not before.any() or not after.any():
        raise VolumeEVMError(f"bias_jump needs angles on both sides of {at}")
    return float(signed[after].mean() - signed[before].mean())


def spectral_peak(error_image):
    """Strength of the most periodic pattern in a 2-D error image.

    The largest magnitude of its Fourier spectrum (mean removed, DC excluded) over the
    spectrum's mean magnitude. Regular banding gives a sharp peak; noise of the same energy
    spreads out (about 3–4).

    Parameters
    ----------
    error_image : (H, W) array_like
        E.g. the luminance difference between a render and its reference.

    Returns
    -------
    float
        0 for a constant image.
    """
    e = np.asarray(error_image, dtype=np.float64)
    spectrum = np.abs(np.fft.rfft2(e - e.mean()))
    spectrum[0, 0] = 0.0
    mean = spectrum.mean()
    return float(spectrum.max() / mean) if mean > 0 else 0.0
