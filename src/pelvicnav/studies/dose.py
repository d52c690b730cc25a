"""Dose (Han et al. 2020, section 2.3.3, figure 9d): registration accuracy as the dose per frame
falls.

Each case is a simulated patient (the registration study's simulation: an innominate dislocated,
set-up error, two views) with metal fiducial beads glued to its bones, as in the paper's phantom
study, imaged at one dose per frame; the same patients (one per repeat) at every dose, so the
doses differ by their quantum noise alone. The registration runs with the shipped defaults. Target
registration error (TRE) at the beads: the distance between each bead carried by the registered
and by the true pose of its bone; also the error at the bone centroids.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pelvicnav import BONES
from pelvicnav.geometry import transforms as tf
from pelvicnav.studies.runner import Study, flatten, run_study

__all__ = ["DoseSettings", "dose_study", "run_dose_case", "run_dose_study", "summarise_dose"]

PAPER = "TRE < 4 mm down to 5 uGy/frame (Han et al. 2020, figure 9d)"


@dataclass(frozen=True)
class DoseSettings:
    """Doses (uGy/frame), patients per dose, beads per patient, seed; ``quick()`` for CI."""

    doses: tuple[float, ...] = (50.0, 20.0, 10.0, 5.0, 2.0, 1.0, 0.5)
    repeats: int = 5
    beads: int = 12
    seed: int = 0
    success_mm: float = 4.0
    ct_spacing: tuple[float, float, float] | None = None  # mm; None: the CT simulator's own

    @classmethod
    def quick(cls, seed: int = 0) -> DoseSettings:
        from pelvicnav.studies.registration import QUICK_CT_SPACING

        return cls(doses=(50.0, 10.0), repeats=1, seed=seed, ct_spacing=QUICK_CT_SPACING)


def dose_study(population, settings: DoseSettings | None = None) -> Study:
    """The runner's study: one case per dose and repeat (repeat r: patient r, its meshes with
    the case)."""
    cfg = settings or DoseSettings()
    cases = []
    for dose in cfg.doses:
        for r in range(cfg.repeats):
            s = r % population.n_subjects
            cases.append({
                "case_id": f"dose{dose:06.2f}-{r}", "dose_ugy": float(dose), "repeat": r,
                "subject": int(population.subject_ids[s]), "vertices": population.vertices[s],
                "faces": population.faces, "seed": cfg.seed * 1000 + r, "settings": cfg,
            })  # fmt: skip
    meta = {"study": asdict(cfg), "population": population.source,
            "subjects": [int(x) for x in population.subject_ids]}  # fmt: skip
    return Study("dose", meta, tuple(cases), run_dose_case)


def run_dose_case(case: dict) -> dict:
    """Simulate one patient at one dose and register it; TRE at its beads."""
    from pelvicnav.register.multibody import register_multibody
    from pelvicnav.studies.registration import (
        RegistrationStudySettings,
        simulate_registration_case,
    )

    cfg = case["settings"]
    sim_cfg = RegistrationStudySettings(dose_ugy=case["dose_ugy"], beads=cfg.beads,
                                        ct_spacing=cfg.ct_spacing)  # fmt: skip
    sim = simulate_registration_case(case["vertices"], case["faces"], seed=case["seed"],
                                     settings=sim_cfg)  # fmt: skip
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], seed=case["seed"],
                             dislocated=sim["bone"])  # fmt: skip
    tre = []
    for x, label in zip(sim["beads"], sim["bead_bones"], strict=True):
        bone = BONES[int(label) - 1]
        est, true = (tf.apply(T[bone], x[None])[0] for T in (res.poses, sim["truth"]))
        tre.append(float(np.linalg.norm(est - true)))
    centroid = {}
    for b in BONES:
        c = sim["centroids"][b][None]
        d = tf.apply(res.poses[b], c) - tf.apply(sim["truth"][b], c)
        centroid[b] = float(np.linalg.norm(d))
    tre_arr = np.asarray(tre) if tre else np.full(1, np.nan)
    return {"dose_ugy": case["dose_ugy"], "repeat": case["repeat"], "subject": case["subject"],
            "tre_median_mm": float(np.median(tre_arr)), "tre_max_mm": float(np.max(tre_arr)),
            "beads": len(tre), **{f"{b}_centroid_mm": e for b, e in centroid.items()},
            "success": bool(np.max(tre_arr) < cfg.success_mm), "converged": bool(res.converged),
            "seconds": res.seconds}  # fmt: skip


def summarise_dose(rows: list[dict], settings: DoseSettings) -> list[dict]:
    """Per dose: median and IQR of the per-case median TRE, worst bead, success rate."""
    out = []
    for dose in sorted({r["dose_ugy"] for r in rows}, reverse=True):
        sel = [r for r in rows if r["dose_ugy"] == dose]
        t = np.array([r["tre_median_mm"] for r in sel])
        q1, med, q3 = np.percentile(t, [25, 50, 75])
        out.append({"dose_ugy": dose, "n": len(sel), "tre_median_mm": float(med),
                    "tre_iqr_mm": float(q3 - q1), "tre_worst_mm": max(r["tre_max_mm"] for r in sel),
                    "success_rate": float(np.mean([r["success"] for r in sel]))})  # fmt: skip
    return out


def lowest_good_dose(summary: list[dict], settings: DoseSettings) -> float | None:
    """The lowest dose down to which every dose kept the median TRE under ``success_mm``."""
    good = None
    for s in summary:  # high to low
        if s["tre_median_mm"] < settings.success_mm:
            good = s["dose_ugy"]
        else:
            break
    return good


def run_dose_study(
    population, out: str | os.PathLike, settings: DoseSettings | None = None, **runner
) -> list[dict]:
    """Run the study (runner options: ``workers``, ``scheduler``, ``force``, ``progress``) and
    write ``results.csv``, ``summary.md`` (with the paper's number) and ``dose.png``."""
    from pelvicnav.io.atomic import write_text

    cfg = settings or DoseSettings()
    rows = flatten(run_study(dose_study(population, cfg), out, **runner))
    summary = summarise_dose(rows, cfg)
    good = lowest_good_dose(summary, cfg)
    lines = ["# Dose", "", "| uGy/frame | n | TRE median (IQR), mm | worst bead, mm | success |",
             "|---|---|---|---|---|"]  # fmt: skip
    for s in summary:
        lines.append(f"| {s['dose_ugy']:g} | {s['n']} | {s['tre_median_mm']:.2f} "
                     f"({s['tre_iqr_mm']:.2f}) | {s['tre_worst_mm']:.2f} | "
                     f"{s['success_rate']:.0%} |")  # fmt: skip
    reached = "none" if good is None else f"{good:g} uGy/frame"
    from pelvicnav.studies.flags import flag_counts, flag_line

    flags = flag_counts(rows, [f"{b}_centroid_mm" for b in BONES])
    lines += ["", f"Median TRE < {cfg.success_mm:g} mm down to {reached}.", f"Paper: {PAPER}.",
              "", flag_line(flags) + " (error: at each bone's centroid)", ""]  # fmt: skip
    out = Path(out)
    write_text(out / "summary.md", "\n".join(lines))
    _figure(rows, out / "dose.png")
    return summary


def _figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pelvicnav.io.atomic import save_figure

    doses = sorted({r["dose_ugy"] for r in rows}, reverse=True)
    data = [[r["tre_median_mm"] for r in rows if r["dose_ugy"] == d] for d in doses]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.boxplot(data)
    ax.set_xticks(range(1, len(doses) + 1), [f"{d:g}" for d in doses])
    ax.axhline(4.0, color="tab:red", lw=0.8, ls="--")
    ax.set_xlabel("dose per frame (uGy)")
    ax.set_ylabel("TRE at the beads (mm)")
    ax.set_title("registration error against dose (cf. Han et al. 2020, figure 9d)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
