"""What ``segment``, ``plan`` and ``register`` all read first: a CT and the label map of its bones.

The CT is read and checked for HU (:func:`pelvicnav.io.volume.read_ct`), the label map put on its
grid (:func:`pelvicnav.io.volume.read_labels`), mapped to our labels through its scheme and checked
to hold bone on the right sides (:func:`pelvicnav.shape.labels.check_bone_labels`).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["BoneInputs", "bones_of_ct", "fit_bones", "read_ct_and_bones", "start_reads"]


def read_ct_and_bones(
    ct: str | os.PathLike,
    labels: str | os.PathLike,
    label_scheme: str = "ours",
    series: str | None = None,
    *,
    meanwhile: Callable[[], object] | None = None,
    reads: tuple[Future, Future] | None = None,
) -> tuple[NDArray, NDArray[np.float64], NDArray, NDArray]:
    """``(hu, world_from_ijk, ours, centroids)`` (each bone's label centroid, world mm);
    ValueError naming the file on bad input (the CT's first).

    The two files are read in threads (decompression releases the GIL) while this thread loads
    the compiled kernels and runs ``meanwhile`` (say, imports the caller will need): on a
    512 x 512 x 400 NIfTI CT, ``pelvicnav register`` spent 0.8 s less than reading first.
    ``reads``: the two files' reads already started (futures of
    :func:`~pelvicnav.io.volume.read_ct` of ``ct`` and :func:`~pelvicnav.io.volume.read_volume`
    of ``labels``), else they are started here."""
    from concurrent.futures import ThreadPoolExecutor

    from pelvicnav.io.volume import labels_on_grid
    from pelvicnav.shape.labels import check_bone_labels, parse_scheme, to_bone_labels

    scheme = parse_scheme(label_scheme)
    with ThreadPoolExecutor(max_workers=2) as pool:
        ct_read, labels_read = reads or start_reads(pool, ct, labels, series)
        _load_kernels()
        if meanwhile is not None:
            meanwhile()
        hu, A = ct_read.result()
        raw = labels_on_grid(*labels_read.result(), hu.shape, A, source=str(labels))
    ours = to_bone_labels(raw, scheme)
    centroids = check_bone_labels(hu, ours, A, source=str(labels), raw_labels=raw)
    return hu, A, ours, centroids


def start_reads(pool, ct: str | os.PathLike, labels: str | os.PathLike,
                series: str | None = None) -> tuple[Future, Future]:  # fmt: skip
    """The CT (:func:`~pelvicnav.io.volume.read_ct`) and its label map
    (:func:`~pelvicnav.io.volume.read_volume`) being read in ``pool``, a thread pool
    (decompression releases the GIL): two futures, for :func:`read_ct_and_bones` ``reads``."""
    from pelvicnav.io.volume import read_ct, read_volume

    return pool.submit(read_ct, ct, series=series), pool.submit(read_volume, labels)


def _load_kernels() -> None:
    """numba's first kernel load (about 0.3 s, whichever kernel) on a 2 x 2 x 2 map."""
    from pelvicnav.io.volume import label_stats

    label_stats(np.zeros((2, 2, 2), np.uint8), np.zeros((2, 2, 2), np.int16), (1,))


def fit_bones(ours: NDArray, world_from_ijk: NDArray, model) -> dict:
    """The pelvis model fitted to a label map (:func:`pelvicnav.shape.fit.fit_labels`), started
    from the population's mean pelvis; bone -> LabelFit."""
    from pelvicnav.geometry import transforms as tf
    from pelvicnav.shape.fit import fit_labels

    pop = model.population
    reference = tf.apply(pop.poses_from_vector(pop.mean), pop.mean_shapes)
    return fit_labels(ours, world_from_ijk, model.shapes, model.faces, reference)


@dataclass(frozen=True, eq=False)
class BoneInputs:
    """A CT and its three bones, from a label map or segmented.

    Attributes
    ----------
    hu : (ni, nj, nk) array, HU
    world_from_ijk : (4, 4) float64
    labels : (ni, nj, nk) uint8
        Ours (1 sacrum, 2 left hip, 3 right hip): the given map relabelled, or the ASM's.
    meshes : dict bone -> (n_vertices, 3) float64
        In the model's correspondence (world mm).
    method : str
    quality : dict bone -> dict
    seconds : dict
    """

    hu: NDArray
    world_from_ijk: NDArray[np.float64]
    labels: NDArray[np.uint8]
    meshes: dict[str, NDArray[np.float64]]
    method: str
    quality: dict[str, dict] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def bones_of_ct(
    ct: str | os.PathLike,
    labels: str | os.PathLike | None,
    *,
    label_scheme: str = "ours",
    series: str | None = None,
    model=None,
    prior=None,
    progress=None,
) -> BoneInputs:
    """Read a CT and get its bones: the model fitted to ``labels`` when given, else segmented by
    the active shape model (:func:`pelvicnav.shape.asm.segment_ct`, ``prior`` or the model's).

    Raises
    ------
    ValueError
        Unreadable or implausible inputs (naming the file), a CT on which the ASM finds no bone.
    """
    import time

    from pelvicnav import BONES
    from pelvicnav.io.volume import read_ct
    from pelvicnav.model import load_model

    say = progress or (lambda _: None)
    started = time.perf_counter()
    if labels is not None:
        say("reading")
        hu, A, ours, _ = read_ct_and_bones(ct, labels, label_scheme, series)
        read_s = time.perf_counter() - started
        say("fitting the model to the labels")
        fits = fit_bones(ours, A, model or load_model())
        quality = {b: {"rms_mm": fits[b].rms_mm} for b in BONES}
        seconds = {"read": read_s, "fit": time.perf_counter() - started - read_s}
        return BoneInputs(hu, A, ours, {b: fits[b].vertices for b in BONES},
                          "pelvis model fitted to the label map (shape.fit.fit_labels)", quality,
                          seconds)  # fmt: skip
    from pelvicnav.shape.asm import ShapePrior, segment_ct

    say("reading")
    hu, A = read_ct(ct, series=series)
    read_s = time.perf_counter() - started
    prior = prior or ShapePrior.from_model(model or load_model())
    try:
        res = segment_ct(hu, A, prior, progress=say)
    except ValueError as err:
        raise ValueError(f"{ct}: {err}") from None
    meshes = {b: res.vertices[i] for i, b in enumerate(BONES)}
    return BoneInputs(hu, A, res.labels, meshes,
                      "multi-resolution active shape model on the CT (shape.asm.segment_ct)",
                      res.quality, {"read": read_s, **res.seconds})  # fmt: skip
