"""Overlays: Canny edges of a bone's DRR trace its outline; the PNG is written atomically."""

from __future__ import annotations

import numpy as np

from pelvicnav.drr.splat import point_model
from pelvicnav.drr.volume import Volume
from pelvicnav.geometry import projection as pj
from pelvicnav.guide.overlay import bone_edges, write_overlay


def test_edges_trace_the_outline_and_move_with_the_pose(tmp_path):
    n = 61
    ax = np.arange(n) - 30.0
    x, y, z = np.meshgrid(ax, ax, ax, indexing="ij")
    ball = ((x**2 + y**2 + z**2) <= 20.0**2).astype(np.float32) * 0.02
    A = np.eye(4)
    A[:3, 3] = -30.0
    model = point_model(Volume(ball, A))
    carm = pj.CArm(rows=96, cols=96, pixel_spacing=(1.0, 1.0))
    P = carm.projection_matrix
    edges = bone_edges(model, np.eye(4), P, (96, 96))
    rc = np.argwhere(edges)
    centre = pj.project(P, np.zeros((1, 3)))[0][::-1]
    radius_px = 20.0 * carm.source_to_detector / carm.source_to_isocenter
    r = np.linalg.norm(rc - centre, axis=1)
    assert len(rc) > 100
    # the strongest gradient sits just inside the silhouette (the chord falls to zero at the rim)
    assert np.median(np.abs(r - radius_px)) < 2.5 and np.percentile(np.abs(r - radius_px), 90) < 4
    shifted = np.eye(4)
    shifted[:3, 3] = [5.0, 0.0, 0.0]  # 5 mm along x moves the outline by 5 * magnification px
    rc2 = np.argwhere(bone_edges(model, shifted, P, (96, 96)))
    assert abs(abs(rc2[:, 1].mean() - rc[:, 1].mean()) - 5.0 * 1100 / 600) < 1.0
    target = bone_edges(model, shifted, P, (96, 96))
    png = write_overlay(tmp_path / "o.png", np.random.default_rng(0).random((96, 96)),
                        {"ball": edges}, target=target)  # fmt: skip
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert not list(tmp_path.glob("*.part"))
