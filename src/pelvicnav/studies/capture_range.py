"""Capture range (Han et al. 2020, section 2.3.2, figure 7): how far off the registration may start.

Each case: a simulated patient (the registration study's simulation, without set-up error) and a
start (the CT's pose, the dislocated bone still to find) displaced along one axis of the first
view's C-arm frame: ``x`` and ``y`` in the detector plane, ``z`` along the beam (depth); ``rx``,
``ry``, ``rz`` rotations about the same axes through the isocentre. The registration (shipped
defaults, the plan's dislocated bone) must bring every bone within ``success_mm`` of the truth at
its centroid. The capture range of an
axis is the largest offset up to which every tested offset of either sign succeeded in at least
``success_rate`` of its cases.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pelvicnav import BONES
from pelvicnav.geometry import projection as pj
from pelvicnav.geometry import transforms as tf
from pelvicnav.studies.runner import Study, flatten, run_study

__all__ = ["AXES", "CaptureRangeSettings", "capture_range_study", "run_capture_case",
           "run_capture_range_study", "summarise_capture"]  # fmt: skip

AXES = ("x", "y", "z", "rx", "ry", "rz")
PAPER = {"in-plane translation": "±50 mm", "out-of-plane translation": "±120 mm",
         "in-plane rotation": "±50°", "out-of-plane rotation": "±30°"}  # fmt: skip


@dataclass(frozen=True)
class CaptureRangeSettings:
    """Offsets (mm and degrees), cases per offset, seed; ``quick()`` for CI."""

    translations: tuple[float, ...] = (-200, -150, -100, -75, -50, -25, 25, 50, 75, 100, 150, 200)
    rotations: tuple[float, ...] = (-60, -45, -30, -20, -10, 10, 20, 30, 45, 60)
    repeats: int = 3
    seed: int = 0
    success_mm: float = 4.0
    success_rate: float = 0.5
    views: tuple[str, ...] = ("ap", "oblique30")
    axes: tuple[str, ...] = AXES
    ct_spacing: tuple[float, float, float] | None = None  # mm; None: the CT simulator's own

    def __post_init__(self) -> None:
        unknown = set(self.axes) - set(AXES)
        if unknown or not self.axes:
            raise ValueError(f"capture-range axes must be some of {AXES}, got {self.axes}")

    @classmethod
    def quick(cls, seed: int = 0) -> CaptureRangeSettings:
        """One axis, one offset of each sign (2 cases, for CI): x +-20 mm, starts within stage
        1's own box, so each registration runs stage 1 once (a start far enough off for the
        first guess runs it from six starts: 45-70 s a case on one core)."""
        from pelvicnav.studies.registration import QUICK_CT_SPACING

        return cls(translations=(-20, 20), rotations=(), repeats=1, seed=seed, axes=("x",),
                   ct_spacing=QUICK_CT_SPACING)  # fmt: skip


def capture_range_study(population, settings: CaptureRangeSettings | None = None) -> Study:
    """The runner's study: one case per axis, offset and repeat (repeat r: patient r)."""
    cfg = settings or CaptureRangeSettings()
    cases = []
    for axis in cfg.axes:
        offsets = cfg.rotations if axis.startswith("r") else cfg.translations
        for offset in offsets:
            for r in range(cfg.repeats):
                s = r % population.n_subjects
                cases.append({
                    "case_id": f"{axis}{float(offset):+07.1f}-{r}", "axis": axis,
                    "offset": float(offset), "repeat": r,
                    "subject": int(population.subject_ids[s]), "vertices": population.vertices[s],
                    "faces": population.faces, "seed": cfg.seed * 1000 + r, "settings": cfg,
                })  # fmt: skip
    meta = {"study": asdict(cfg), "population": population.source,
            "subjects": [int(x) for x in population.subject_ids]}  # fmt: skip
    return Study("capture-range", meta, tuple(cases), run_capture_case)


def run_capture_case(case: dict) -> dict:
    """Register one displaced start; returns the worst bone error and success."""
    from pelvicnav.register.multibody import register_multibody

    cfg = case["settings"]
    sim = _simulated(case)
    iso = np.asarray(case["vertices"]).reshape(-1, 3).mean(axis=0)
    R = pj.decompose_projection(sim["views"].projections[0]).carm_from_world  # rows: C-arm axes
    k = AXES.index(case["axis"])
    direction = R[k % 3]
    if k < 3:
        offset = tf.from_params(direction * case["offset"], [0.0, 0.0, 0.0])
    else:
        rot = tf.from_params([0.0, 0.0, 0.0], direction * np.deg2rad(case["offset"]))
        offset = tf.from_params(iso, [0, 0, 0]) @ rot @ tf.from_params(-iso, [0, 0, 0])
    # every bone starts where the CT places it (the undislocated pelvis, no set-up error in these
    # cases), displaced by the offset: the dislocated bone still has its dislocation to find
    start = dict.fromkeys(BONES, offset @ sim["truth"]["sacrum"])
    res = register_multibody(sim["ct"], sim["labels"], sim["views"], init_poses=start,
                             seed=case["seed"], dislocated=sim["bone"])  # fmt: skip
    errors = {}
    for b in BONES:
        c = sim["centroids"][b]
        errors[b] = float(np.linalg.norm(tf.apply(res.poses[b], c[None])
                                         - tf.apply(sim["truth"][b], c[None])))  # fmt: skip
    worst = max(errors.values())
    return {"axis": case["axis"], "offset": case["offset"], "repeat": case["repeat"],
            "subject": case["subject"], "worst_error_mm": worst,
            "success": bool(worst < cfg.success_mm), "converged": bool(res.converged),
            "rescued": any(w.startswith("rescued") for w in res.warnings),
            **{f"{b}_error_mm": e for b, e in errors.items()},
            "seconds": res.seconds}  # fmt: skip


_SIMULATED: dict = {}
_KEEP = 3  # simulated patients a worker keeps (cases cycle through the repeats: 3 by default)


def _simulated(case: dict) -> dict:
    """The simulated patient of a case's repeat, kept for the worker's later cases of that
    repeat (the last ``_KEEP`` patients; each is ~10-20 s to simulate)."""
    from pelvicnav.studies.registration import (
        RegistrationStudySettings,
        simulate_registration_case,
    )

    V = np.ascontiguousarray(case["vertices"], dtype=np.float64)
    views = tuple(case["settings"].views)
    spacing = case["settings"].ct_spacing
    key = (case["seed"], case["subject"], views, spacing, hashlib.sha1(V.tobytes()).hexdigest())
    if key not in _SIMULATED:
        while len(_SIMULATED) >= _KEEP:
            _SIMULATED.pop(next(iter(_SIMULATED)))
        sim_cfg = RegistrationStudySettings(views=views, setup_mm=0.0, setup_deg=0.0,
                                            ct_spacing=spacing)  # fmt: skip
        _SIMULATED[key] = simulate_registration_case(V, case["faces"], seed=case["seed"],
                                                     settings=sim_cfg)  # fmt: skip
    return _SIMULATED[key]


def summarise_capture(rows: list[dict], settings: CaptureRangeSettings) -> dict:
    """Per axis: success rate per offset and the capture range (largest offset, both signs)."""
    out = {}
    for axis in settings.axes:
        sel = [r for r in rows if r["axis"] == axis]
        rates = {}
        for off in sorted({r["offset"] for r in sel}):
            hits = [r["success"] for r in sel if r["offset"] == off]
            rates[off] = float(np.mean(hits))
        capture = 0.0
        for mag in sorted({abs(o) for o in rates}):
            if all(rates.get(s * mag, 0.0) >= settings.success_rate for s in (-1, 1)):
                capture = mag
            else:
                break
        out[axis] = {"rates": rates, "capture": capture}
    return out


def run_capture_range_study(
    population, out: str | os.PathLike, settings: CaptureRangeSettings | None = None, **runner
) -> dict:
    """Run the study (runner options: ``workers``, ``scheduler``, ``force``, ``progress``) and
    write ``results.csv``, ``summary.md`` (with the paper's numbers) and ``capture_range.png``."""
    from pelvicnav.io.atomic import write_text
    from pelvicnav.studies.flags import flag_counts, flag_line

    cfg = settings or CaptureRangeSettings()
    rows = flatten(run_study(capture_range_study(population, cfg), out, **runner))
    summary = summarise_capture(rows, cfg)
    out = Path(out)
    lines = ["# Capture range", "", "| axis | capture range | success rate per offset |",
             "|---|---|---|"]  # fmt: skip
    for axis, s in summary.items():
        unit = "deg" if axis.startswith("r") else "mm"
        rates = ", ".join(f"{o:+g}: {r:.0%}" for o, r in s["rates"].items())
        lines.append(f"| {axis} | ±{s['capture']:g} {unit} | {rates} |")
    lines += [
        "",
        "x, y: in the detector plane of the first view; z: along its beam.",
        "Paper (Han et al. 2020): " + "; ".join(f"{k} {v}" for k, v in PAPER.items()),
        "",
        flag_line(flag_counts(rows, "worst_error_mm")) + " (error: the worst bone's centroid)",
        "",
    ]
    write_text(out / "summary.md", "\n".join(lines))
    _figure(summary, out / "capture_range.png")
    return summary


def _figure(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pelvicnav.io.atomic import save_figure

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for axis, s in summary.items():
        ax = axes[1 if axis.startswith("r") else 0]
        offs = list(s["rates"])
        ax.plot(offs, [100 * s["rates"][o] for o in offs], marker="o", label=axis)
    for ax, unit in zip(axes, ("translation offset (mm)", "rotation offset (deg)"), strict=True):
        ax.set_xlabel(unit)
        ax.set_ylabel("success (%)")
        ax.set_ylim(-5, 105)
        ax.legend()
        ax.grid(alpha=0.3)
    fig.suptitle("capture range: success (every bone < 4 mm) against the initial offset")
    fig.tight_layout()
    save_figure(fig, path)
