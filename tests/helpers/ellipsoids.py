"""Uniform ellipsoids: partial-volume voxelisation and exact chord lengths (DRR ground truth)."""

from __future__ import annotations

import numpy as np

from pelvicnav.drr.volume import Volume

MU = 0.02  # 1/mm


def ellipsoid_volume(radii, centre, spacing=1.0, extent=70.0, supersample=3):
    """Partial-volume voxelisation of a uniform ellipsoid (fraction inside per voxel x MU)."""
    n = int(2 * extent / spacing) + 1
    origin = np.asarray(centre) - extent
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    ax = np.arange(n) * spacing
    frac = np.zeros((n, n, n))
    for a in sub:
        for b in sub:
            for c in sub:
                x = ax[:, None, None] + a * spacing + origin[0] - centre[0]
                y = ax[None, :, None] + b * spacing + origin[1] - centre[1]
                z = ax[None, None, :] + c * spacing + origin[2] - centre[2]
                frac += (x / radii[0]) ** 2 + (y / radii[1]) ** 2 + (z / radii[2]) ** 2 <= 1
    return Volume.from_spacing(MU * frac / supersample**3, [spacing] * 3, origin)


def chords(source, dirs, radii, centre):
    """Exact chord length of each ray through the ellipsoid (0 if it misses)."""
    r = np.asarray(radii)
    o = (source - centre) / r
    d = dirs / r
    a = np.sum(d * d, -1)
    b = 2 * np.sum(o * d, -1)
    c = np.sum(o * o) - 1
    disc = b * b - 4 * a * c
    return np.where(disc > 0, np.sqrt(np.maximum(disc, 0)) / a, 0.0)
