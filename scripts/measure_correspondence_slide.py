"""How far the shape model's correspondence on a perfect surface moves a bone's pose, and whether
that slide can be predicted (docs/segmentation.md, "What we measured of that gap").

For each atlas subject: the left-hip SSM of the other 39 is fitted point-to-plane to the subject's
true surface (:func:`pelvicnav.shape.correspond.refine_correspondence`, as the ASM's last stage
does), and the rigid fit of the atlas mesh onto the model-corresponded one is the pose the slide
adds (translation at the bone's centroid, rotation). Then, leave-one-out over the subjects, two
corrections are tried: subtracting the other subjects' mean slide (a bias), and a ridge regression
of the slide on the fitted shape's weights (every subject's weights in one model of all 40: a
leak that can only flatter the regression). Run: ``PELVICNAV_ATLAS=... python
scripts/measure_correspondence_slide.py`` (about 1 minute on 2 cores).
"""

from __future__ import annotations

import os

import numpy as np
from threadpoolctl import threadpool_limits

from pelvicnav.geometry import transforms as tf
from pelvicnav.geometry.procrustes import fit_transform
from pelvicnav.io.atlas import load_atlas
from pelvicnav.shape.correspond import refine_correspondence
from pelvicnav.shape.ssm import ShapeModel

BONE = 1  # left hip


def slide(vertices, faces, i):
    """``(pose change [t at centroid mm, rotvec deg], model-corresponded mesh)`` of subject i."""
    ssm = ShapeModel.fit(np.delete(vertices[:, BONE], i, axis=0))
    true = vertices[i, BONE]
    fitted = refine_correspondence(ssm, true, faces[BONE])
    D = fit_transform(true, fitted)
    c = true.mean(axis=0)
    R = np.linalg.inv(fit_transform(ssm.mean, true, scale=True))  # into the model's frame
    t = R[:3, :3] @ (tf.apply(D, c[None])[0] - c) / tf.scale_of(R)
    r = R[:3, :3] @ tf.rotvec_from_matrix(D[:3, :3]) / tf.scale_of(R)
    return np.r_[t, np.rad2deg(r)], fitted


def medians(X):
    return (float(np.median(np.linalg.norm(X[:, :3], axis=1))),
            float(np.median(np.linalg.norm(X[:, 3:], axis=1))))  # fmt: skip


def main() -> None:
    atlas = load_atlas(os.environ.get("PELVICNAV_ATLAS"))
    V, F = np.asarray(atlas.vertices), atlas.faces
    with threadpool_limits(1):
        pairs = [slide(V, F, i) for i in range(len(V))]
    X = np.array([p[0] for p in pairs])
    n = len(X)
    t, r = medians(X)
    print(f"slide, median: {t:.2f} mm / {r:.2f} deg")
    print("mean slide (bias):", np.round(X.mean(axis=0), 2), "spread:", np.round(X.std(axis=0), 2))
    loo = np.array([X[i] - np.delete(X, i, axis=0).mean(axis=0) for i in range(n)])
    t, r = medians(loo)
    print(f"after subtracting the others' mean: {t:.2f} mm / {r:.2f} deg")
    model = ShapeModel.fit(V[:, BONE])
    W = np.array([model.project(tf.apply(fit_transform(p[1], model.mean, scale=True), p[1]))
                  for p in pairs]) / np.sqrt(model.variances)  # fmt: skip
    for k in (2, 4, 8, 16):
        for lam in (1.0, 10.0):
            res = []
            for i in range(n):
                A = np.c_[np.ones(n - 1), np.delete(W[:, :k], i, axis=0)]
                coef = np.linalg.solve(A.T @ A + lam * np.diag([0.0] + [1.0] * k),
                                       A.T @ np.delete(X, i, axis=0))  # fmt: skip
                res.append(X[i] - np.r_[1.0, W[i, :k]] @ coef)
            t, r = medians(np.array(res))
            print(f"ridge on {k:2d} weights, lambda {lam:4.1f}: {t:.2f} mm / {r:.2f} deg")


if __name__ == "__main__":
    main()
