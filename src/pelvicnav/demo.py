"""``pelvicnav demo``: a short tour of what the toolkit does, writing figures to a folder."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.io.atomic import save_figure

BONE_COLOURS = {"sacrum": "#4c72b0", "left_hip": "#dd8452", "right_hip": "#55a868"}


def _views() -> dict[str, pj.CArm]:
    return {
        "AP": pj.CArm(),
        "oblique 30 / tilt -20": pj.CArm(orbit_deg=30.0, tilt_deg=-20.0),
        "lateral": pj.CArm(orbit_deg=90.0),
    }


def run_demo(out: Path, *, atlas: str | os.PathLike | None = None) -> None:
    """Print the C-arm geometry, project a pelvis into views and plan a reduction.

    Uses the atlas when one is configured, else a patient sampled from the packaged pelvis model
    (planned with the model's own planner; the model never saw a sampled patient).
    """
    from rich.console import Console
    from rich.table import Table

    from pelvicnav.phantom.population import MODEL, load_population

    console = Console()
    views = _views()
    table = Table(title="C-arm views (SID 600 mm, SDD 1100 mm, 512 x 512 px, 0.586 mm)")
    for col in ("view", "source (mm, LPS)", "isocentre -> pixel", "magnification", "9-DoF s (mm)"):
        table.add_column(col)
    for name, carm in views.items():
        P = carm.projection_matrix
        uv = pj.project(P, np.asarray(carm.isocenter))
        table.add_row(
            name,
            np.array2string(carm.source, precision=1, suppress_small=True),
            f"({uv[0]:.1f}, {uv[1]:.1f})",
            f"{carm.magnification(np.asarray(carm.isocenter)):.3f}",
            np.array2string(np.asarray(carm.nine_dof().source_in_detector), precision=1),
        )
    console.print(table)

    rng = np.random.default_rng(0)
    b = np.concatenate([rng.normal(0, 5, 3), rng.normal(0, 0.05, 3), [0.02]])
    T = tf.sim3_exp(b)
    console.print(
        "Sim(3): b = "
        + np.array2string(b, precision=3)
        + f" -> exp -> log error {np.abs(tf.sim3_log(T) - b).max():.1e}; "
        + f"geodesic distance to identity {tf.distance(np.eye(4), T):.3f}"
    )

    a = load_population(atlas, n_subjects=1)
    console.print(f"population: {a.n_subjects} subject(s) from {a.source}")
    out.mkdir(parents=True, exist_ok=True)
    path = out / "atlas_projection.png"
    _projection_figure(a, views, path)
    console.print(f"wrote {path}")
    if a.n_subjects < 10 and a.source != MODEL:
        console.print(f"[yellow]planning demo skipped: {a.n_subjects} subjects is too few[/]")
        return
    _planning_demo(a, out, console)


def _planning_demo(a, out: Path, console) -> None:
    """Dislocate subject 1's left hip and estimate its target pose.

    With the atlas the models come from the other subjects; a sampled patient is planned with the
    packaged model (fitted on the atlas, so it never saw this patient).
    """
    from pelvicnav.phantom.population import MODEL
    from pelvicnav.pose.target import TargetPlanner
    from pelvicnav.studies.target_pose import pose_errors, random_dislocation

    V = a.vertices
    truth = V[0, 1]
    D, dmm, ddeg = random_dislocation(np.random.default_rng(1), truth.mean(axis=0), 20.0, 10.0)
    current = tf.apply(D, truth)
    observed = {"sacrum": V[0, 0], "right_hip": V[0, 2]}
    if a.source == MODEL:
        from pelvicnav.model import load_model

        planner = load_model().planner(observed)
        where = "the packaged pelvis model"
    else:
        planner = TargetPlanner.fit(V[1:], a.faces, observed=("sacrum", "right_hip"))
        where = f"models from the other {a.n_subjects - 1} subjects"
    console.print(
        f"plan: subject {a.subject_ids[0]}'s left hip dislocated by {dmm:.1f} mm / {ddeg:.1f} deg; "
        f"{where}"
    )
    estimates = {}
    for name, refine in (("SPM", "none"), ("SPM_CC", "joint")):
        est = planner.estimate(observed, {"left_hip": current}, refine=refine)["left_hip"]
        t, r, _ = pose_errors(truth, est.vertices)
        estimates[name] = est.vertices
        console.print(f"  {name:7s} target error {t:.2f} mm, {r:.2f} deg")
    _planning_figure(V[0], current, estimates["SPM_CC"], out / "target_pose.png")
    console.print(f"wrote {out / 'target_pose.png'}")


def _planning_figure(subject, current, target, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6))
    sub = slice(None, None, 4)
    for pts, colour, label in (
        (subject[0], "0.5", "sacrum"),
        (subject[2], "0.5", "right hip"),
        (current, "tab:red", "left hip, dislocated"),
        (subject[1], "k", "left hip, truth"),
        (target, "tab:green", "left hip, SPM_CC target"),
    ):
        ax.scatter(pts[sub, 0], pts[sub, 2], s=0.6, c=colour, label=label, alpha=0.5)
    ax.set_aspect("equal")
    # Radiological display: x (towards the patient's left) increases to the right of the page.
    ax.set_xlabel("x (mm, LPS; patient's right on the page's left)")
    ax.set_ylabel("z (mm, superior)")
    ax.legend(markerscale=8, fontsize=8, loc="lower right")
    ax.set_title("Target reduction pose (coronal projection)")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def _projection_figure(a, views: dict[str, pj.CArm], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    subject = a.subject_ids[0]
    verts = a.vertices[0]
    # Put the pelvis's centroid at the isocentre, as a surgeon centres the C-arm.
    world_from_ct = np.eye(4)
    world_from_ct[:3, 3] = -verts.reshape(-1, 3).mean(axis=0)
    fig, axes = plt.subplots(1, len(views), figsize=(5 * len(views), 5.3))
    for ax, (name, carm) in zip(axes, views.items(), strict=True):
        P = carm.projection_matrix
        for b, bone in enumerate(a.bones):
            uv = pj.project(P, tf.apply(world_from_ct, verts[b]))
            polys = uv[a.faces[b]]
            ax.add_collection(
                PolyCollection(polys, facecolor=BONE_COLOURS[bone], edgecolor="none", alpha=0.05)
            )
        # The detector outline: at magnification ~1.8 a 300 mm detector sees part of the pelvis.
        ax.add_patch(
            plt.Rectangle((-0.5, -0.5), carm.cols, carm.rows, fill=False, edgecolor="k", lw=1.5)
        )
        ax.autoscale_view()
        ax.invert_yaxis()  # row 0 at the top, as images are displayed
        ax.set_aspect("equal")
        ax.set_title(f"{name} (subject {subject})")
        ax.set_xlabel("column (px)")
        ax.set_ylabel("row (px)")
    fig.suptitle("Atlas pelvis projected through pelvicnav's C-arm model (radiological display)")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
