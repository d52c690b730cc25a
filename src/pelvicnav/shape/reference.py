"""Cross-check our shape models against the statismo models shipped with the Han atlas."""

from __future__ import annotations

import numpy as np

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.shape.ssm import ShapeModel

__all__ = ["compare_atlas_models", "compare_with_reference"]


def compare_with_reference(ours: ShapeModel, mean: np.ndarray, variances: np.ndarray) -> dict:
    """Agreement of a model with a reference (mean shape and variance spectrum).

    The reference may live at another scale (the atlas's statismo models are normalised to unit
    RMS radius), so the mean shapes are compared after a similarity fit and the spectra as
    fractions of the total variance.

    Returns
    -------
    dict with ``mean_rms_mm`` (RMS distance of the means after the similarity fit, in our mm),
    ``mean_rms_relative`` (that over our mean's RMS radius), ``reference_scale`` (our mm per
    reference unit), ``fraction_ours`` / ``fraction_reference`` (first 10 modes),
    ``max_fraction_difference`` and ``spectrum_correlation`` (first 10 modes), and
    ``relative_total_variance`` (total variance / squared RMS radius, ours and reference).
    """
    ref_mean = np.asarray(mean, dtype=np.float64).reshape(-1, 3)
    ref_var = np.asarray(variances, dtype=np.float64)
    if ref_mean.shape != ours.mean.shape:
        raise ValueError(f"reference mean {ref_mean.shape} does not match {ours.mean.shape}")
    T = fit_transform(ref_mean, ours.mean, scale=True)
    aligned = tf.apply(T, ref_mean)
    rms = float(np.sqrt(np.mean(np.sum((aligned - ours.mean) ** 2, axis=1))))
    radius = float(np.sqrt(np.mean(np.sum((ours.mean - ours.mean.mean(0)) ** 2, axis=1))))
    ref_radius = float(np.sqrt(np.mean(np.sum((ref_mean - ref_mean.mean(0)) ** 2, axis=1))))
    k = min(10, ours.n_modes, len(ref_var))
    f_ours = ours.variances / ours.variances.sum()
    f_ref = ref_var / ref_var.sum()
    return {
        "mean_rms_mm": rms,
        "mean_rms_relative": rms / radius,
        "reference_scale": float(tf.scale_of(T)),
        "fraction_ours": f_ours[:k].tolist(),
        "fraction_reference": f_ref[:k].tolist(),
        "max_fraction_difference": float(np.max(np.abs(f_ours[:k] - f_ref[:k]))),
        "spectrum_correlation": float(np.corrcoef(f_ours[:k], f_ref[:k])[0, 1]),
        "relative_total_variance": {
            "ours": float(ours.variances.sum() / (len(ours.mean) * radius**2)),
            "reference": float(ref_var.sum() / (len(ref_mean) * ref_radius**2)),
        },
    }


def compare_atlas_models(atlas=None) -> dict[str, dict]:
    """Per bone: our SSM fitted on an atlas against the statismo model shipped with it
    (:func:`compare_with_reference`). ``atlas``: a path, or None for the configured one."""
    from pelvicnav.io.atlas import BONE_FILES, load_atlas, resolve_atlas_path
    from pelvicnav.io.statismo import read_statismo

    a = load_atlas(atlas)
    root = resolve_atlas_path(atlas)
    out = {}
    for b, bone in enumerate(a.bones):
        ref = read_statismo(root / "SSM" / f"{BONE_FILES[bone][1]}.h5")
        out[bone] = compare_with_reference(
            ShapeModel.fit(a.vertices[:, b]), ref.mean, ref.variances
        )
    return out
