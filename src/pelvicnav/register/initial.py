"""A global first guess of the translation, before stage 1: 2D correlation in every view.

Stage 1 searches a box around its start (+-40 mm); a patient placed further off leaves the truth
outside it. Here the stage-1 body's DRR at its start is correlated with each radiograph over
every 2D shift at once (FFT of the Sobel gradients: the edges, not the soft tissue's intensity),
and the best shift of each view is turned into the 3D translation that moves the body's centre by
those shifts (least squares over the views: two views fix all three components; one view only
the two in its plane). No rotation is searched.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pelvicnav.drr.renderer import Renderer
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.metrics.similarity import sobel_gradients
from pelvicnav.register.pyramid import Level

__all__ = ["about", "best_shift", "initial_pose", "initial_translation"]


def best_shift(moving: NDArray, fixed: NDArray, max_shift: float) -> tuple[NDArray, float]:
    """The 2D shift (columns, rows; px) that best lays ``moving``'s edges on ``fixed``'s.

    Gradient correlation ``sum_x g_m(x) . g_f(x + s)`` of the zero-mean Sobel gradients over
    every shift up to ``max_shift`` pixels (zero padding, no wrap), normalised by the
    gradient energy of both images; returns the shift and its correlation (about 1 for a
    perfect match).
    """
    H, W = fixed.shape
    shape = (2 * H, 2 * W)
    total = np.zeros(shape)
    norm = 1e-300
    for gm, gf in zip(sobel_gradients(moving), sobel_gradients(fixed), strict=True):
        gm, gf = gm - gm.mean(), gf - gf.mean()
        total += np.fft.irfft2(np.conj(np.fft.rfft2(gm, shape)) * np.fft.rfft2(gf, shape), shape)
        norm += np.sum(gm * gm) ** 0.5 * np.sum(gf * gf) ** 0.5
    dv = np.fft.fftfreq(shape[0], 1.0 / shape[0])[:, None]  # signed shift of each lag
    du = np.fft.fftfreq(shape[1], 1.0 / shape[1])[None, :]
    total[(np.abs(du) > max_shift) | (np.abs(dv) > max_shift)] = -np.inf
    r, c = np.unravel_index(int(np.argmax(total)), shape)
    return np.array([du[0, c], dv[r, 0]]), float(total[r, c] / norm)


def _jacobian(P: NDArray, X: NDArray) -> NDArray[np.float64]:
    """d(u, v)/dX (2, 3) of the projection ``P`` at world point ``X``."""
    x = P @ np.r_[X, 1.0]
    u, v, w = x
    return np.stack([P[0, :3] - (u / w) * P[2, :3], P[1, :3] - (v / w) * P[2, :3]]) / w


def initial_translation(
    level: Level,
    renderer: Renderer,
    bones,
    poses: NDArray,
    centre: NDArray,
    max_mm: float,
    rounds: int = 3,
) -> NDArray[np.float64]:
    """``world_from_world`` translation (4, 4) that best lays the bones' DRR on every view.

    Each round renders the body with its centre moved onto each view's central ray (so a start
    far off still renders inside the image), finds every view's best shift and solves for the
    translation; the next round starts there (its DRR at the new depth, so a start far along a
    beam is corrected in turn for its magnification).

    Parameters
    ----------
    level : Level
        Where to correlate (its blurred radiographs and binned ``P``).
    renderer : Renderer
    bones : names of the body's bones
    poses : (L, 4, 4) their starting ``world_from_ct``
    centre : (3,) world mm
        The body's centre at its start.
    max_mm : float
        Largest shift searched, in mm at the centre's depth.
    rounds : int
    """
    t = np.zeros(3)
    for _ in range(rounds):
        step, _ = _views_shift(level, renderer, bones, poses, centre, t, max_mm)
        t = t + step  # minimum norm: one view leaves depth alone
    return tf.from_params(t, np.zeros(3))


def initial_pose(
    level: Level,
    renderer: Renderer,
    bones,
    poses: NDArray,
    centre: NDArray,
    max_mm: float,
    angles_deg: tuple[NDArray, NDArray, NDArray],
) -> NDArray[np.float64]:
    """``world_from_world`` (4, 4): :func:`initial_translation`, then the body turned about its
    centre by the best of ``angles_deg`` about each axis of the first view in turn (in plane
    first; the summed best-shift correlation of the views decides), then translated again."""
    delta = initial_translation(level, renderer, bones, poses, centre, max_mm)
    R_view = pj.decompose_projection(level.projections[0]).carm_from_world
    axes = (R_view[2], R_view[0], R_view[1])  # about the beam (in plane), then the detector axes
    for axis, angles in zip(axes, angles_deg, strict=True):
        c = tf.apply(delta, centre[None])[0]
        best, best_score = np.eye(4), -np.inf
        for a in angles:
            turn = about(c, axis, a)
            moved = turn @ delta @ poses
            _, score = _views_shift(level, renderer, bones, moved, c, np.zeros(3), max_mm)
            if score > best_score:
                best, best_score = turn, score
        delta = best @ delta
        c = tf.apply(delta, centre[None])[0]
        delta = initial_translation(level, renderer, bones, delta @ poses, c, max_mm) @ delta
    return delta


def about(centre: NDArray, axis: NDArray, deg: float) -> NDArray[np.float64]:
    """Rotation by ``deg`` about ``axis`` through ``centre`` (4, 4)."""
    turn = tf.from_params(np.zeros(3), np.deg2rad(deg) * np.asarray(axis))
    return tf.from_params(centre, np.zeros(3)) @ turn @ tf.from_params(-centre, np.zeros(3))


def _views_shift(level, renderer, bones, poses, centre, t, max_mm):
    """The translation step that lays the body (moved by ``t``) on every view, and the summed
    correlation of the views' best shifts."""
    rows, cols, total = [], [], 0.0
    for img, P in zip(level.images, level.projections, strict=True):
        X = centre + t
        J = _jacobian(P, X)
        aim = _onto_central_ray(P, X, level.shape)  # world shift putting X on the ray
        moved = tf.from_params(t + aim, np.zeros(3))[None] @ poses
        drr = renderer.render(level.index, bones, moved[None], P[None], level.shape)[0, 0]
        px_per_mm = float(np.linalg.norm(J, axis=1).max())
        shift, score = best_shift(drr.astype(np.float64), img, max_mm * px_per_mm)
        rows.append(J)
        cols.append(shift + J @ aim)  # the shift from X's own projection
        total += score
    step, *_ = np.linalg.lstsq(np.concatenate(rows), np.concatenate(cols), rcond=None)
    return step, total


def _onto_central_ray(P: NDArray, X: NDArray, shape: tuple[int, int]) -> NDArray[np.float64]:
    """The world translation, at ``X``'s depth, that moves its projection to the image centre."""
    x = P @ np.r_[X, 1.0]
    target = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
    J = _jacobian(P, X)
    step, *_ = np.linalg.lstsq(J, target - x[:2] / x[2], rcond=None)
    return step
