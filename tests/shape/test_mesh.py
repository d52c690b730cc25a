"""Mesh utilities: closing holes, self-intersection tests, untangling, spike repair."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.synthetic import icosphere
from pelvicnav.shape.mesh import (
    close_mesh,
    inpaint_vertices,
    is_closed,
    self_intersections,
    signed_volume,
    spike_vertices,
    untangle,
    vertex_normals,
)


def test_close_mesh_fills_holes_and_orients_outwards():
    v, f = icosphere(2)
    v = 20.0 * v
    holed = np.delete(f, [3, 4, 50], axis=0)  # two holes: one of two triangles, one of one
    assert not is_closed(holed)
    closed = close_mesh(v, holed[:, ::-1])  # inward-facing input
    assert is_closed(closed)
    assert len(closed) == len(f)
    assert signed_volume(v, closed) == pytest.approx(signed_volume(v, f), rel=1e-3)
    assert signed_volume(v, closed) > 0
    radial = np.einsum("ij,ij->i", vertex_normals(v, closed), v / 20.0)
    assert radial.min() > 0.9


def test_close_mesh_removes_a_non_manifold_flap():
    v, f = icosphere(1)
    flap = np.vstack([f, [[f[0, 0], f[0, 1], f[7, 2]]]])  # a third triangle on edge (f00, f01)
    closed = close_mesh(v, flap)
    assert is_closed(closed)


def test_self_intersections_finds_crossing_triangles_only():
    v, f = icosphere(2)
    v = 20.0 * v
    assert len(self_intersections(v, f)) == 0
    crossed = v.copy()
    top = np.argmax(v[:, 2])
    crossed[top] = [0.0, 0.0, -25.0]  # pulled through the bottom of the sphere
    pairs = self_intersections(crossed, f)
    assert len(pairs) > 0
    # Every reported pair involves a triangle of the moved vertex.
    assert np.all(np.any(f[pairs[:, 0]] == top, axis=1) | np.any(f[pairs[:, 1]] == top, axis=1))


def test_untangle_separates_sheets_that_passed_through_each_other():
    v, f = icosphere(3)
    slab = v * [30.0, 30.0, 1.5]  # a thin plate, like an iliac wing
    assert len(self_intersections(slab, f)) == 0
    dented = slab.copy()
    centre = (np.hypot(slab[:, 0], slab[:, 1]) < 6.0) & (slab[:, 2] > 0)
    dented[centre, 2] -= 3.5  # the top sheet pushed through the bottom one
    assert len(self_intersections(dented, f)) > 0
    fixed, left = untangle(dented, f)
    assert left == 0
    assert len(self_intersections(fixed, f)) == 0
    far = np.hypot(slab[:, 0], slab[:, 1]) > 15.0
    np.testing.assert_array_equal(fixed[far], dented[far])  # only the crossing region moved


def test_spike_vertices_are_found_and_inpainted():
    v, f = icosphere(2)
    rng = np.random.default_rng(0)
    shapes = np.stack([40.0 * v * (1 + 0.05 * rng.standard_normal(3)) for _ in range(10)])
    spiked = shapes.copy()
    spiked[4, 17] += [60.0, 0.0, 0.0]
    flags = spike_vertices(spiked, f)
    assert flags[4, 17] and flags.sum(axis=1)[[0, 1, 2, 3, 5]].sum() == 0
    repaired = inpaint_vertices(spiked[4], f, flags[4], shapes[4])
    np.testing.assert_allclose(repaired, shapes[4], atol=1e-6)
