"""Bone label maps: label schemes, conversion to ours, and the check that the "bones" are bones.

Our scheme is 1 sacrum, 2 left innominate, 3 right innominate. TotalSegmentator's ``total`` task
labels the sacrum 25 (26 where it has a vertebra S1), ``hip_left`` 77 and ``hip_right`` 78; its
labels 1-3 are the spleen and the kidneys, so a TotalSegmentator map read as ours would put the
kidneys where the bones should be. :func:`check_bone_labels` catches that (and any map whose
bones are not bone, or sit on the wrong side) before anything is built from it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav import BONES, LABELS

__all__ = ["SCHEMES", "check_bone_labels", "parse_scheme", "to_bone_labels"]

SCHEMES: dict[str, dict[str, tuple[int, ...]]] = {
    "ours": {bone: (LABELS[bone],) for bone in BONES},
    "totalsegmentator": {"sacrum": (25, 26), "left_hip": (77,), "right_hip": (78,)},
}
# Median CT number a bone's voxels must exceed: soft tissue and organs sit at 0-80 HU, cancellous
# bone at 150-400 and the real CTs' bones at 181-403 (median over the mask).
MIN_BONE_MEDIAN_HU = 120.0
MIN_BONE_VOLUME_MM3 = 5000.0


def parse_scheme(text: str) -> dict[str, tuple[int, ...]]:
    """A label scheme: ``"ours"``, ``"totalsegmentator"`` or ``"sacrum=25,26;left_hip=77;..."``.

    Raises
    ------
    ValueError
        Unknown name, malformed mapping, an unknown or missing bone, or a label used twice.
    """
    key = text.strip().lower()
    if key in SCHEMES:
        return SCHEMES[key]
    scheme: dict[str, tuple[int, ...]] = {}
    for part in filter(None, (p.strip() for p in text.split(";"))):
        bone, sep, values = part.partition("=")
        bone = bone.strip()
        if not sep or bone not in BONES:
            raise ValueError(
                f"label scheme {text!r}: expected 'ours', 'totalsegmentator' or "
                f"'bone=label[,label];...' with bones {BONES}, got {part!r}"
            )
        try:
            scheme[bone] = tuple(int(v) for v in values.split(",") if v.strip())
        except ValueError:
            raise ValueError(f"label scheme {text!r}: labels of {bone} are not integers") from None
        if not scheme[bone] or min(scheme[bone]) < 1:
            raise ValueError(f"label scheme {text!r}: {bone} needs labels >= 1")
    missing = [b for b in BONES if b not in scheme]
    if missing:
        raise ValueError(f"label scheme {text!r}: no label for {', '.join(missing)}")
    used = [v for values in scheme.values() for v in values]
    if len(set(used)) != len(used):
        raise ValueError(f"label scheme {text!r}: a label is given to two bones")
    return scheme


def to_bone_labels(labels: ArrayLike, scheme: dict[str, tuple[int, ...]]) -> NDArray[np.uint8]:
    """Relabel a map into ours (0 background, 1, 2, 3); labels outside the scheme become 0."""
    lab = np.asarray(labels)
    if lab.size and lab.dtype.kind in "iub":  # one table lookup (np.isin per bone: 4 s each on
        lo, hi = int(lab.min()), int(lab.max())  # a 512 x 512 x 400 map)
        if lo >= 0 and hi < 2**16:
            lut = np.zeros(hi + 1, dtype=np.uint8)
            for bone, values in scheme.items():
                lut[[v for v in values if 0 <= v <= hi]] = LABELS[bone]
            if np.array_equal(lut, np.arange(hi + 1)):  # already ours: no 105 M-voxel copy
                return lab.astype(np.uint8, copy=False)
            return lut[lab]
    out = np.zeros(lab.shape, dtype=np.uint8)
    for bone, values in scheme.items():
        out[np.isin(lab, values)] = LABELS[bone]
    return out


def _likely_scheme(raw: NDArray) -> str:
    present = set(np.unique(raw).tolist())
    if {77, 78} <= present:
        return (
            " The map holds labels 77 and 78 (TotalSegmentator's hip_left and hip_right; its 1-3 "
            "are the spleen and kidneys): pass --label-scheme totalsegmentator."
        )
    return ""


def check_bone_labels(
    hu: ArrayLike,
    labels: ArrayLike,
    world_from_ijk: ArrayLike,
    *,
    source: str,
    raw_labels: ArrayLike | None = None,
) -> dict[str, NDArray[np.float64]]:
    """Refuse a label map (ours) whose bones are missing, are not bone, or are misplaced; returns
    each bone's label centroid (world mm), which the check computes.

    Parameters
    ----------
    hu : (ni, nj, nk) float
        The CT in Hounsfield units.
    labels : (ni, nj, nk) int
        Our scheme (after :func:`to_bone_labels`).
    world_from_ijk : (4, 4) float
        The grid's affine (LPS mm): +x is the patient's left.
    source : str
        The label map's file name, for the messages.
    raw_labels : array, optional
        The map as read, to name the scheme it probably uses.

    Raises
    ------
    ValueError
        A bone with too few voxels, a median below :data:`MIN_BONE_MEDIAN_HU`, or the innominates
        not on their sides of the sacrum; naming the file and the likely scheme.
    """
    from pelvicnav.io.volume import label_stats

    ct = np.asarray(hu)
    lab = np.asarray(labels)
    A = np.asarray(world_from_ijk, dtype=np.float64)
    raw = np.asarray(raw_labels if raw_labels is not None else labels)
    voxel_mm3 = abs(np.linalg.det(A[:3, :3]))
    stats = label_stats(lab, ct, [LABELS[b] for b in BONES])  # one pass over both volumes
    centres = {}
    for bone in BONES:
        st = stats[LABELS[bone]]
        volume = st.count * voxel_mm3
        if volume < MIN_BONE_VOLUME_MM3:
            raise ValueError(
                f"{source}: {bone} (label {LABELS[bone]}) has {volume:.0f} mm^3 of voxels, "
                f"not a bone (at least {MIN_BONE_VOLUME_MM3:.0f} expected).{_likely_scheme(raw)}"
            )
        if st.median_hu < MIN_BONE_MEDIAN_HU:
            raise ValueError(
                f"{source}: {bone} (label {LABELS[bone]}) has median {st.median_hu:.0f} HU, which "
                f"is soft tissue, not bone (expected above {MIN_BONE_MEDIAN_HU:.0f} HU)."
                f"{_likely_scheme(raw)}"
            )
        centres[bone] = (A @ np.r_[st.centroid_ijk, 1.0])[:3]
    x = {bone: c[0] for bone, c in centres.items()}
    if not x["left_hip"] > x["sacrum"] > x["right_hip"]:
        raise ValueError(
            f"{source}: the left innominate (label 2) must lie on the patient's left of the "
            f"sacrum and the right one (label 3) on the right (LPS x {x['left_hip']:.0f}, "
            f"{x['sacrum']:.0f}, {x['right_hip']:.0f} mm): labels swapped, or not ours?"
            f"{_likely_scheme(raw)}"
        )
    return centres
