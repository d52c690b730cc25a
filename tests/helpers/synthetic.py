"""A small synthetic pelvis-like population with known pose modes (no atlas needed)."""

from __future__ import annotations

import numpy as np

from pelvicnav.geometry import transforms as tf


def icosphere(level: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere by midpoint subdivision: (vertices, outward-oriented faces)."""
    t = (1 + 5**0.5) / 2
    v = [
        [-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0],
        [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
        [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1],
    ]  # fmt: skip
    f = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
        [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
        [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
        [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1],
    ]  # fmt: skip
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = f
    for _ in range(level):
        cache: dict[tuple[int, int], int] = {}

        def mid(i, j, verts=verts, cache=cache):
            key = (min(i, j), max(i, j))
            if key not in cache:
                p = verts[i] + verts[j]
                verts.append(p / np.linalg.norm(p))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    return np.array(verts), np.array(faces)


# Ellipsoid "bones": (radii, centre) in mm, LPS. The hips nearly touch the sacrum (SI joints) and
# each other (pubic symphysis), a few mm apart.
BODIES = {
    "sacrum": ((22.0, 14.0, 30.0), (0.0, 36.0, 10.0)),
    "left_hip": ((30.0, 28.0, 45.0), (32.5, 0.0, 0.0)),
    "right_hip": ((30.0, 28.0, 45.0), (-32.5, 0.0, 0.0)),
}


def make_population(
    n_subjects: int = 30,
    *,
    modes: np.ndarray | None = None,
    mode_sd: tuple[float, ...] = (3.0, 1.5),
    shape_sd: float = 0.0,
    seed: int = 0,
):
    """Subjects whose hip poses vary along known directions of the 21-dim tangent space.

    Returns vertices (n, 3, nv, 3), faces (3 arrays), the generating modes (21, k) and the
    per-subject tangent vectors (n, 21) (unscaled: t in mm, r in rad, log s).
    """
    rng = np.random.default_rng(seed)
    sphere, faces = icosphere(3)
    k = len(mode_sd)
    if modes is None:
        raw = rng.normal(size=(21, k))
        raw[:7] = 0.0  # the sacrum (the frame) does not move
        raw[[6 + 7, 6 + 14]] = 0.0  # no scale change of the hips
        for i in range(7, 21, 7):
            raw[i + 3 : i + 6] *= 0.02  # rotations in radians: ~1 degree per mm-scale unit
        modes, _ = np.linalg.qr(raw)
    weights = rng.normal(size=(n_subjects, k)) * np.asarray(mode_sd)
    weights -= weights.mean(axis=0)  # zero-mean tangent vectors: the generator's mean is exact
    b = weights @ modes.T
    V = np.empty((n_subjects, 3, len(sphere), 3))
    for l, (radii, centre) in enumerate(BODIES.values()):
        for n in range(n_subjects):
            r = np.asarray(radii) * (1 + shape_sd * rng.normal(size=3))
            shape = sphere * r
            T = tf.sim3_exp(b[n, 7 * l : 7 * l + 7])
            T[:3, 3] += centre
            V[n, l] = tf.apply(T, shape)
    return V, (faces, faces, faces), modes, b
