"""The ``pelvicnav`` command line.

A thin layer over the library: heavy imports (numpy, scipy, numba) happen inside the commands so
that ``pelvicnav --help`` answers at once. Errors in user input are printed as one message naming
the file and what is wrong, with exit status 2.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

# numba's worker threads busy-wait by default and stall small shared machines.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

app = typer.Typer(
    name="pelvicnav",
    help="Image-guided reduction of pelvic dislocation: plan from CT, guide from X-rays.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
atlas_app = typer.Typer(help="The Han pelvis atlas (40 subjects x 3 bones).", no_args_is_help=True)
app.add_typer(atlas_app, name="atlas")
study_app = typer.Typer(
    help="Reproduce the method's studies (tables, figures).", no_args_is_help=True
)
app.add_typer(study_app, name="study")
model_app = typer.Typer(
    help="The embedded pelvis model (shape, pose and planning models from the atlas).",
    no_args_is_help=True,
)
app.add_typer(model_app, name="model")
views_app = typer.Typer(
    help="View sets (views.json): radiographs with their projection geometry.",
    no_args_is_help=True,
)
app.add_typer(views_app, name="views")

AtlasOption = Annotated[
    Path | None,
    typer.Option(
        "--atlas",
        help="Atlas folder (default: $PELVICNAV_ATLAS, then the user cache).",
        file_okay=False,
    ),
]
PopulationOption = Annotated[
    str | None,
    typer.Option(
        "--atlas",
        help=(
            "Atlas folder, 'model' for patients sampled from the packaged pelvis model, or "
            "'procedural' for the template population (default: $PELVICNAV_ATLAS, then the user "
            "cache, then the model)."
        ),
    ),
]

WorkersOption = Annotated[
    int | None,
    typer.Option(help="LocalCluster worker processes (default one per core; 0: in this process)."),
]
SchedulerOption = Annotated[
    str | None, typer.Option(help="Address of a running dask scheduler, e.g. tcp://host:8786.")
]
ForceOption = Annotated[
    bool, typer.Option(help="Start afresh if OUT's store holds this study with other settings.")
]
ModelOption = Annotated[
    Path | None,
    typer.Option("--model", help="Model file (default: $PELVICNAV_MODEL, then packaged)."),
]
_CT_HELP = "CT in HU: a DICOM series folder, NIfTI, NRRD or MHA."
SeriesOption = Annotated[
    str | None,
    typer.Option(help="Series Instance UID, when the CT's DICOM folder holds several series."),
]
LabelSchemeOption = Annotated[
    str,
    typer.Option(
        help="Labels of the map: 'ours' (1 sacrum, 2 left, 3 right hip), 'totalsegmentator' "
        "(25/26, 77, 78) or 'sacrum=25,26;left_hip=77;right_hip=78'."
    ),
]


def _population(location: str | None, subject_ids: tuple[int, ...] | None = None):
    """The atlas, or a generated population (see ``phantom.population.load_population``)."""
    from rich.console import Console

    from pelvicnav.phantom.population import MODEL, PROCEDURAL, load_population

    a = load_population(location, subject_ids=subject_ids)
    if a.source in (MODEL, PROCEDURAL):
        what = "sampled from the pelvis model" if a.source == MODEL else "procedural templates"
        Console(stderr=True).print(
            f"[yellow]no atlas: using {a.n_subjects} patient(s) {what}[/]", highlight=False
        )
    return a


def _study_progress():
    """A progress bar for a study's cases: done/total and the time remaining."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("{task.description}"), BarColumn(),
                    TextColumn("{task.completed}/{task.total}"), TimeRemainingColumn())  # fmt: skip


def _fail(message: str) -> typer.Exit:
    from rich.console import Console

    Console(stderr=True, soft_wrap=True).print(f"[bold red]error:[/] {message}", highlight=False)
    return typer.Exit(code=2)


@app.callback()
def _main(
    version: Annotated[bool, typer.Option("--version", help="Print the version and exit.")] = False,
) -> None:
    if version:
        from pelvicnav import __version__

        typer.echo(__version__)
        raise typer.Exit()


@atlas_app.command("info")
def atlas_info(atlas: AtlasOption = None) -> None:
    """Print the atlas's subjects and per-bone mesh sizes."""
    from rich.console import Console
    from rich.table import Table

    from pelvicnav.io.atlas import AtlasNotFoundError, load_atlas

    try:
        a = load_atlas(atlas)
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    console.print(
        f"[bold]atlas[/] {a.source}: {a.n_subjects} subjects, {a.n_vertices} vertices/bone"
    )
    table = Table("bone", "vertices", "triangles", "mean extent x/y/z (mm)", "centroid (mm, LPS)")
    for row in a.bone_summary():
        table.add_row(row["bone"], str(row["vertices"]), str(row["triangles"]),
                      " / ".join(f"{x:.1f}" for x in row["mean_extent_mm"]),
                      " / ".join(f"{x:.1f}" for x in row["centroid_mm"]))  # fmt: skip
    console.print(table)
    console.print("subjects: " + ", ".join(str(s) for s in a.subject_ids))


@atlas_app.command("download")
def atlas_download(
    dest: Annotated[
        Path | None, typer.Option(help="Install folder (default: the user cache).")
    ] = None,
    url: Annotated[
        list[str] | None,
        typer.Option(help="Archive URL(s) to try instead of the public repository."),
    ] = None,
    force: Annotated[bool, typer.Option(help="Replace an installed atlas.")] = False,
) -> None:
    """Download the public atlas from its GitHub repository and validate it."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TransferSpeedColumn

    from pelvicnav.io.atlas import ATLAS_URLS, default_atlas_dir, download_atlas

    target = dest or default_atlas_dir()
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        DownloadColumn(),
        TransferSpeedColumn(),
    ) as bar:
        task = bar.add_task("atlas", total=None)

        def report(done: int, total: int | None) -> None:
            bar.update(task, completed=done, total=total)

        try:
            a = download_atlas(
                target, urls=tuple(url) if url else ATLAS_URLS, force=force, progress=report
            )
        except (ValueError, FileExistsError) as err:
            raise _fail(str(err)) from None
    typer.echo(f"atlas installed at {target}: {a.n_subjects} subjects x {len(a.bones)} bones")


@study_app.command("target-pose")
def study_target_pose(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    subjects: Annotated[
        int | None, typer.Option(help="Test only the first N subjects (models still use the rest).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the simulated dislocations.")] = 0,
    workers: Annotated[int, typer.Option(help="Worker processes.")] = 2,
    prior: Annotated[float, typer.Option(help="SPM prior weight (equation 8a).")] = 0.1,
    segmentation: Annotated[
        str,
        typer.Option(
            help="What the planner sees: 'truth' (the atlas meshes) or 'asm' (each tested "
            "subject segmented on a synthetic CT, prior from the others; OUT/segmentation)."
        ),
    ] = "truth",
    scheduler: SchedulerOption = None,
    force: ForceOption = False,
    quick: Annotated[
        bool, typer.Option(help="Two test subjects, the left hip, SPM and SPM_CC (for CI).")
    ] = False,
) -> None:
    """Leave-one-out target-pose study (SSM_single, CM, SPM, SPM_CC) on the atlas.

    Runs on dask.distributed (a LocalCluster unless --scheduler); every finished fold is stored in
    OUT/store.sqlite, so an interrupted run resumes where it stopped."""
    from rich.console import Console
    from rich.table import Table

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.target_pose import (
        PAPER_MEDIANS,
        TargetPoseSettings,
        run_target_pose_study,
    )

    try:
        if segmentation not in ("truth", "asm"):
            raise ValueError(f"--segmentation must be 'truth' or 'asm', got {segmentation!r}")
        a = _population(atlas)
        ids = None if subjects is None else tuple(a.subject_ids[:subjects])
        if subjects is not None and not 1 <= subjects <= a.n_subjects:
            raise ValueError(f"--subjects must be between 1 and {a.n_subjects}, got {subjects}")
        common = {"seed": seed, "workers": workers, "prior": prior, "segmentation": segmentation}
        settings = (TargetPoseSettings.quick(ids or a.subject_ids, **common) if quick
                    else TargetPoseSettings(subjects=ids, **common))  # fmt: skip
        ids = settings.subjects  # only the tested subjects are segmented
        segmented = None
        if segmentation == "asm":
            from pelvicnav.studies.segmentation import segmented_population

            with _study_progress() as bar:
                task = bar.add_task("segmenting (ASM)", total=None)
                segmented = segmented_population(
                    a, out / "segmentation", len(ids) if ids else a.n_subjects, seed=seed,
                    workers=workers, scheduler=scheduler, force=force,
                    progress=lambda d, t: bar.update(task, completed=d, total=t),
                )  # fmt: skip
        with _study_progress() as bar:
            task = bar.add_task("leave-one-out", total=len(ids or a.subject_ids))
            run_target_pose_study(
                a, out, settings, segmented=segmented, scheduler=scheduler, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    import csv

    with open(out / "summary.csv") as fh:
        summary = list(csv.DictReader(fh))
    table = Table(
        "method", "dislocated", "n", "translation mm (IQR)", "rotation deg (IQR)", "paper",
        title=f"target pose, leave-one-out ({out})",
    )  # fmt: skip
    for row in summary:
        paper = PAPER_MEDIANS.get(row["method"])
        if not row["translation_median_mm"]:
            cells = ("-", "-")
        else:
            t, ti = float(row["translation_median_mm"]), float(row["translation_iqr_mm"])
            r, ri = float(row["rotation_median_deg"]), float(row["rotation_iqr_deg"])
            cells = (f"{t:.2f} ({ti:.2f})", f"{r:.2f} ({ri:.2f})")
        table.add_row(
            row["method"],
            row["dislocated_bone"],
            row["n"],
            *cells,
            f"{paper[0]} / {paper[1]}" if paper else "",
        )
    Console().print(table)


@study_app.command("spm-modes")
def study_spm_modes(
    out: Annotated[Path, typer.Option(help="PNG to write.")] = Path("spm_modes.png"),
    atlas: PopulationOption = None,
) -> None:
    """Figure of the first four SPM modes at +-3 sd (cf. the paper's figure 2)."""
    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.figures import spm_modes_figure

    try:
        spm_modes_figure(_population(atlas), out)
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    typer.echo(f"wrote {out}")


@study_app.command("population")
def study_population(
    out: Annotated[Path, typer.Option(help="Output folder (created).")] = Path("population"),
    atlas: AtlasOption = None,
    subjects: Annotated[int, typer.Option(help="Subjects to draw.")] = 40,
    seed: Annotated[int, typer.Option(help="Seed of the drawn population.")] = 0,
    population: Annotated[
        str, typer.Option(help="'model' (sampled from the pelvis model) or 'procedural'.")
    ] = "model",
) -> None:
    """A generated population vs the atlas: size table (sizes.csv/.md) and population.png."""
    from rich.console import Console
    from rich.table import Table

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.population import population_study

    console = Console()
    try:
        rows, reference, note = population_study(out, population, atlas, subjects=subjects,
                                                 seed=seed)  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    if note:
        console.print(f"[yellow]{note}[/]")
    table = Table(
        "measure (mm)", "sampled mean ± sd", "range", title=f"{population} population, seed {seed}"
    )
    if reference is not None:
        for col in ("atlas mean ± sd", "range", "inside"):
            table.add_column(col)
    for r in rows:
        cells = [
            str(r["measure"]),
            f"{r['sampled_mean']} ± {r['sampled_sd']}",
            f"{r['sampled_min']}-{r['sampled_max']}",
        ]
        if reference is not None:
            cells += [
                f"{r['atlas_mean']} ± {r['atlas_sd']}",
                f"{r['atlas_min']}-{r['atlas_max']}",
                "yes" if r["inside"] else "[red]NO[/]",
            ]
        table.add_row(*cells)
    console.print(table)
    console.print(f"wrote {out / 'sizes.csv'}, {out / 'sizes.md'}, {out / 'population.png'}")


@study_app.command("registration")
def study_registration(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    cases: Annotated[int, typer.Option(help="Number of simulated cases.")] = 20,
    dof: Annotated[int, typer.Option(help="6 (two views, P known) or 9 (one view).")] = 6,
    seed: Annotated[int, typer.Option(help="Seed of the study.")] = 0,
    segmentation: Annotated[
        str,
        typer.Option(
            help="Bone labels of the CT: 'truth' or 'asm' (segmented, prior from the "
            "other subjects)."
        ),
    ] = "truth",
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
    force: ForceOption = False,
    quick: Annotated[bool, typer.Option(help="One case, 1.5 mm CTs (for CI).")] = False,
    real_ct: Annotated[
        int,
        typer.Option(
            "--real-ct",
            help="Instead of atlas cases: N cases from each of the three real CTs "
            "($PELVICNAV_REAL_CT or shared/data/real-ct/fracsegnet), bones in a synthetic body.",
        ),
    ] = 0,
) -> None:
    """Registration accuracy on simulated cases (in-/out-of-plane error per bone, PDE for 9 DoF).

    Runs on dask.distributed (a LocalCluster unless --scheduler); every finished case is stored in
    OUT/store.sqlite at once, and a re-run skips what is stored."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.registration import (
        QUICK_CT_SPACING,
        RegistrationStudySettings,
        run_registration_study,
        summarise,
    )

    try:
        if dof not in (6, 9):
            raise ValueError(f"--dof must be 6 or 9, got {dof}")
        if cases < 1:
            raise ValueError(f"--cases must be >= 1, got {cases}")
        if real_ct < 0:
            raise ValueError(f"--real-ct must be >= 0, got {real_ct}")
        cases = 1 if quick else cases
        a = _population(atlas) if not real_ct else None
        coarse = {"ct_spacing": QUICK_CT_SPACING} if quick else {}
        settings = RegistrationStudySettings.for_dof(dof, n_cases=cases, seed=seed,
                                                     segmentation=segmentation,
                                                     real_ct=real_ct, **coarse)  # fmt: skip
        if real_ct:
            cases = real_ct * 3
        with _study_progress() as bar:
            task = bar.add_task("cases", total=cases)
            rows = run_registration_study(
                a, out, settings, workers=workers, scheduler=scheduler, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    for row in summarise(rows):
        console.print(row)
    console.print(f"wrote {out / 'results.csv'}, {out / 'summary.csv'} ({out / 'store.sqlite'})")


@study_app.command("capture-range")
def study_capture_range(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    quick: Annotated[
        bool, typer.Option(help="x at +-20 mm, one case each, 1.5 mm CTs (for CI).")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of the simulated patients.")] = 0,
    axes: Annotated[
        str | None, typer.Option(help="Comma-separated axes to test (default: x,y,z,rx,ry,rz).")
    ] = None,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
    force: ForceOption = False,
) -> None:
    """Capture range (figure 7): success against the initial offset along each C-arm axis."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.capture_range import CaptureRangeSettings, run_capture_range_study

    try:
        settings = CaptureRangeSettings.quick(seed) if quick else CaptureRangeSettings(seed=seed)
        if axes is not None:
            chosen = tuple(a.strip() for a in axes.split(",") if a.strip())
            settings = replace(settings, axes=chosen)
        population = _population(atlas)
        with _study_progress() as bar:
            task = bar.add_task("cases", total=None)
            summary = run_capture_range_study(
                population, out, settings, workers=workers, scheduler=scheduler, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    for axis, s in summary.items():
        unit = "deg" if axis.startswith("r") else "mm"
        console.print(f"{axis}: capture range ±{s['capture']:g} {unit}")
    console.print(f"wrote {out / 'results.csv'}, {out / 'summary.md'}, {out / 'capture_range.png'}")


@study_app.command("dose")
def study_dose(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    quick: Annotated[
        bool, typer.Option(help="50 and 10 uGy/frame, one patient, 1.5 mm CTs (for CI).")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of the simulated patients.")] = 0,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
    force: ForceOption = False,
) -> None:
    """Dose (figure 9d): TRE at fiducial beads from 50 down to 0.5 uGy/frame."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.dose import DoseSettings, run_dose_study

    settings = DoseSettings.quick(seed) if quick else DoseSettings(seed=seed)
    try:
        population = _population(atlas)
        with _study_progress() as bar:
            task = bar.add_task("cases", total=None)
            summary = run_dose_study(
                population, out, settings, workers=workers, scheduler=scheduler, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    for s in summary:
        console.print(f"{s['dose_ugy']:g} uGy/frame: TRE {s['tre_median_mm']:.2f} mm "
                      f"(worst {s['tre_worst_mm']:.2f} mm, n={s['n']})")  # fmt: skip
    console.print(f"wrote {out / 'results.csv'}, {out / 'summary.md'}, {out / 'dose.png'}")


@study_app.command("fov")
def study_fov(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    quick: Annotated[
        bool, typer.Option(help="340 and 200 mm, one crop each, 1.5 mm CTs (for CI).")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of the patients and crops.")] = 0,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
    force: ForceOption = False,
) -> None:
    """Field of view (figure 12b): single-view 9-DoF PDE on radiographs cropped 340 -> 150 mm."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.fov import FovSettings, run_fov_study

    settings = FovSettings.quick(seed) if quick else FovSettings(seed=seed)
    try:
        population = _population(atlas)
        with _study_progress() as bar:
            task = bar.add_task("crops", total=None)
            summary = run_fov_study(
                population, out, settings, workers=workers, scheduler=scheduler, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    for s in summary:
        console.print(f"{s['size_mm']:g} mm: PDE {s['pde_median_mm']:.2f} mm "
                      f"(worst {s['pde_worst_mm']:.2f} mm, {s['n']} bones)")  # fmt: skip
    console.print(f"wrote {out / 'results.csv'}, {out / 'summary.md'}, {out / 'fov.png'}")


@study_app.command("runtime")
def study_runtime(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    cases: Annotated[int, typer.Option(help="Simulated patients to time.")] = 10,
    quick: Annotated[bool, typer.Option(help="One patient (for CI).")] = False,
    seed: Annotated[int, typer.Option(help="Seed of the simulated patients.")] = 0,
    force: ForceOption = False,
) -> None:
    """Runtime (table 2): segmentation, planning, stage 1, stage 2, augmentation, a subsequent
    frame; one case at a time in this process (timings are per machine, not per cluster)."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.runtime import RuntimeSettings, run_runtime_study

    settings = RuntimeSettings.quick(seed) if quick else RuntimeSettings(n_cases=cases, seed=seed)
    try:
        population = _population(atlas)
        with _study_progress() as bar:
            task = bar.add_task("cases", total=None)
            summary = run_runtime_study(
                population, out, settings, workers=0, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    for s in summary:
        console.print(
            f"{s['step']}: {s['median_s']:.2f} s (IQR {s['iqr_s']:.2f}; paper {s['paper_s']})"
        )
    console.print(f"wrote {out / 'results.csv'}, {out / 'summary.md'}")


@study_app.command("segmentation")
def study_segmentation(
    out: Annotated[Path, typer.Option(help="Output folder (created).")],
    atlas: PopulationOption = None,
    subjects: Annotated[
        int, typer.Option(help="Leave-one-out over the first N subjects (the prior from the rest).")
    ] = 20,
    dislocated: Annotated[
        bool, typer.Option(help="Also segment each subject with one innominate dislocated.")
    ] = False,
    real_ct: Annotated[
        bool, typer.Option(help="Also the real CTs (PELVICNAV_REAL_CT or shared/data/real-ct).")
    ] = True,
    quick: Annotated[
        bool, typer.Option(help="One subject, intact, 1.5 mm CT, no real CTs (CI).")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of the synthetic CTs.")] = 0,
    workers: WorkersOption = None,
    scheduler: SchedulerOption = None,
    force: ForceOption = False,
) -> None:
    """ASM segmentation accuracy: Dice and surface RMSD per bone, leave-one-out on CTs
    synthesised from atlas subjects (intact, dislocated) and on the real CTs."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.studies.segmentation import SegmentationStudySettings, run_segmentation_study

    if quick:
        settings = SegmentationStudySettings.quick(seed)
    else:
        settings = SegmentationStudySettings(n_subjects=subjects, dislocated=dislocated,
                                             real_ct=real_ct, seed=seed)  # fmt: skip
    try:
        population = _population(atlas)
        with _study_progress() as bar:
            task = bar.add_task("CTs", total=None)
            summary = run_segmentation_study(
                population, out, settings, workers=workers, scheduler=scheduler, force=force,
                progress=lambda done, total: bar.update(task, completed=done, total=total),
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    console = Console()
    for s in summary:
        console.print(
            f"{s['kind']} {s['condition']} {s['bone']}: Dice {s['dice_median']:.3f} "
            f"(min {s['dice_min']:.3f}), RMSD {s['rmsd_median_mm']:.2f} mm (n={s['n']})"
        )
    console.print(f"wrote {out / 'results.csv'}, {out / 'summary.md'}, {out / 'segmentation.png'}")


@study_app.command("ssm-reference")
def study_ssm_reference(atlas: AtlasOption = None) -> None:
    """Compare our per-bone SSMs with the statismo models shipped with the atlas."""
    from rich.console import Console
    from rich.table import Table

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.shape.reference import compare_atlas_models

    try:
        comparison = compare_atlas_models(atlas)
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    table = Table(
        "bone", "mean RMS (mm)", "relative", "spectrum corr.", "max |fraction diff|",
        title="our SSM vs the atlas's statismo model",
    )  # fmt: skip
    for bone, c in comparison.items():
        table.add_row(bone, f"{c['mean_rms_mm']:.2f}", f"{100 * c['mean_rms_relative']:.1f}%",
                      f"{c['spectrum_correlation']:.3f}",
                      f"{c['max_fraction_difference']:.3f}")  # fmt: skip
    Console().print(table)


@model_app.command("build")
def model_build(
    out: Annotated[Path, typer.Option(help="Model file to write (.npz).")],
    atlas: AtlasOption = None,
    variance: Annotated[
        float, typer.Option(help="Fraction of each shape model's variance its modes keep.")
    ] = 0.99,
) -> None:
    """Fit the pelvis model (SSMs, SPM, target planners) from the atlas and write it."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.model import build_model_file

    console = Console()
    try:
        with console.status("fitting") as status:
            model = build_model_file(atlas, out, variance_kept=variance, progress=status.update)
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    modes = model.provenance["shape_modes"]
    console.print(
        f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB) from "
        f"{len(model.subject_ids)} subjects; "
        f"shape modes {modes}"
    )


@model_app.command("info")
def model_info(
    model: ModelOption = None,
) -> None:
    """Print the pelvis model's provenance and sizes."""
    from rich.console import Console

    from pelvicnav.model import ModelFileError, load_model, resolve_model_path

    try:
        path = resolve_model_path(model)
        m = load_model(path)
    except (FileNotFoundError, ModelFileError) as err:
        raise _fail(str(err)) from None
    p = m.provenance
    console = Console()
    console.print(f"[bold]pelvis model[/] {path}", highlight=False)
    console.print(f"{p.get('atlas')} — {p.get('reference')}, doi:{p.get('doi')}")
    console.print(f"licence {p.get('licence')}; {p.get('note')}")
    console.print(
        f"{len(m.subject_ids)} subjects, {m.n_vertices} vertices per bone, shape modes "
        f"{ {b: s.n_modes for b, s in m.shapes.items()} }, pose modes {m.population.n_modes}"
    )
    console.print("planners for observed bones: " + "; ".join(" + ".join(k) for k in m.planners))
    console.print(f"built {p.get('created')} by pelvicnav {p.get('pelvicnav_version')}")


@app.command("segment")
def segment(
    ct: Annotated[Path, typer.Argument(help=_CT_HELP)],
    out: Annotated[Path, typer.Option(help="Output folder.")],
    labels: Annotated[
        Path | None,
        typer.Option(
            help="Existing label map to fit the model to (same grid); default: the "
            "active shape model segments the CT."
        ),
    ] = None,
    label_scheme: LabelSchemeOption = "ours",
    model: ModelOption = None,
    atlas: Annotated[
        Path | None,
        typer.Option(help="Fit the shape models from this atlas folder instead of the model."),
    ] = None,
    series: SeriesOption = None,
) -> None:
    """Bones of a CT as corresponded meshes (VTK, STL) and a label map, with contours."""
    from rich.console import Console
    from rich.progress import Progress

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.model import load_model
    from pelvicnav.workflow.segment import segment as run_segment

    console = Console()
    steps = ["reading", "fitting the model to the labels"]
    if labels is None:
        steps = [
            "reading",
            "pyramid",
            "initialisation",
            "profile",
            "free-form",
            "correspondence",
            "label map",
        ]
    try:
        if model is not None and atlas is not None:
            raise ValueError("give --model or --atlas, not both")
        prior = _atlas_prior(atlas) if atlas is not None else None
        with Progress(console=console) as bar:
            task = bar.add_task("segmenting", total=len(steps) + 1)

            def step(name: str) -> None:
                done = next((k for k, s in enumerate(steps) if name.startswith(s)), 0)
                bar.update(task, completed=done, description=name)

            record = run_segment(
                ct, out, labels=labels, label_scheme=label_scheme,
                model=None if prior is not None else load_model(model), prior=prior,
                series=series, progress=step,
            )  # fmt: skip
            bar.update(task, completed=len(steps) + 1, description="written")
    except (FileNotFoundError, ValueError, AtlasNotFoundError) as err:
        raise _fail(str(err)) from None
    for bone, r in record["bones"].items():
        extra = (f"edge RMS {r['edge_rms_mm']:.2f} mm, edges found at {r['edge_fraction']:.0%}"
                 if "edge_rms_mm" in r else f"RMS {r['rms_mm']:.2f} mm")  # fmt: skip
        console.print(f"{bone}: {r['voxels']} voxels, {extra}")
    total = sum(record["seconds"].values()) - record["seconds"].get("total", 0.0)
    console.print(f"wrote {out} ({total:.1f} s)")


def _atlas_prior(atlas: Path):
    """A shape prior fitted from an atlas folder (all its subjects)."""
    from pelvicnav.io.atlas import load_atlas
    from pelvicnav.shape.asm import ShapePrior

    a = load_atlas(atlas)
    return ShapePrior.from_subjects(a.vertices, a.faces)


@app.command("plan")
def plan_command(
    ct: Annotated[Path, typer.Argument(help=_CT_HELP)],
    out: Annotated[Path, typer.Option(help="Plan folder to write.")],
    labels: Annotated[
        Path | None, typer.Option(help="Label map of the bones (any format the CT takes).")
    ] = None,
    label_scheme: LabelSchemeOption = "ours",
    dislocated: Annotated[
        str, typer.Option(help="auto, left_hip, right_hip, both or none.")
    ] = "auto",
    model: ModelOption = None,
    series: SeriesOption = None,
) -> None:
    """Plan the reduction: the bones of the CT, which one is dislocated, and its target."""
    from rich.console import Console

    from pelvicnav.model import load_model
    from pelvicnav.workflow.plan import make_plan

    console = Console()
    try:
        with console.status("planning") as status:
            plan = make_plan(
                ct, out, labels=labels, label_scheme=label_scheme, dislocated=dislocated,
                model=load_model(model), series=series,
                progress=lambda step: status.update(f"planning: {step}"),
            )  # fmt: skip
    except ValueError as err:
        raise _fail(str(err)) from None
    console.print(plan.decision["description"])
    for bone, r in plan.residual_in_ct.items():
        console.print(f"{bone}: to reach the target, {r['description']}")
    console.print(f"wrote {out} (plan {plan.identity})")


@app.command("guide")
def guide_command(
    plan: Annotated[Path, typer.Argument(help="Plan folder (from `pelvicnav plan`).")],
    views: Annotated[Path, typer.Option(help="views.json of this frame's radiographs.")],
    out: Annotated[Path, typer.Option(help="Session folder (frames are added to it).")],
    seed: Annotated[int, typer.Option(help="Seed of CMA-ES.")] = 0,
) -> None:
    """Register one intraoperative frame against the plan and report the residual."""
    from rich.console import Console

    from pelvicnav.workflow.guide import guide_frame

    console = Console()
    try:
        with console.status("registering"):
            frame = guide_frame(plan, views, out, seed=seed)
    except ValueError as err:
        raise _fail(str(err)) from None
    if not frame.converged:
        likely = (", likely wrong (its joints are implausible)"
                  if frame.record.get("verdict") == "implausible" else "")  # fmt: skip
        console.print(f"[bold red]frame {frame.index}: UNRELIABLE registration{likely}: "
                      "not guidance[/]")  # fmt: skip
    else:
        for bone, r in frame.residual.items():
            console.print(f"frame {frame.index} ({frame.mode}): {bone}: {r['description']}")
    console.print(f"wrote {frame.folder} ({frame.seconds:.1f} s) and {out / 'report.html'}")


@app.command("report")
def report_command(
    folder: Annotated[Path, typer.Argument(help="A plan, session or study folder.")],
) -> None:
    """Write FOLDER/report.html: one self-contained page (images inline, no network)."""
    from pelvicnav.guide.report import write_report

    try:
        path = write_report(folder)
    except ValueError as err:
        raise _fail(str(err)) from None
    typer.echo(f"wrote {path}")


@views_app.command("from-dicom")
def views_from_dicom(
    files: Annotated[
        list[Path], typer.Argument(help="X-ray DICOM files (XA, RF, DX, CR), or PNG/TIFF + JSON.")
    ],
    out: Annotated[Path, typer.Option(help="views.json to write (images beside it).")],
    profile: Annotated[
        Path | None, typer.Option(help="C-arm profile (JSON) for geometry the tags lack.")
    ] = None,
    isocenter: Annotated[
        str | None,
        typer.Option(help="The C-arm isocentre in the CT's world, 'x,y,z' mm (LPS)."),
    ] = None,
    ct: Annotated[
        Path | None,
        typer.Option(help="Place the isocentre at the centroid of this CT's bone instead."),
    ] = None,
    intensities: Annotated[
        str, typer.Option(help="'auto' (to line integrals) or 'keep' (display values as they are).")
    ] = "auto",
    dof: Annotated[int, typer.Option(help="Degrees of freedom the view set asks for: 6 or 9.")] = 6,
) -> None:
    """Turn C-arm images and their DICOM geometry into a view set for `pelvicnav register`."""
    from rich.console import Console

    from pelvicnav.io.xray_dicom import convert_views

    console = Console()
    try:
        if isocenter is not None:
            try:
                isocenter = [float(x) for x in isocenter.split(",")]
            except ValueError:
                raise ValueError(f"--isocenter must be 'x,y,z' in mm, got {isocenter!r}") from None
        views = convert_views(
            files, out, isocenter=isocenter, ct=ct, profile=profile, intensities=intensities,
            degrees_of_freedom=dof,
        )  # fmt: skip
    except ValueError as err:
        raise _fail(str(err)) from None
    for v in views:
        m = v.meta
        console.print(
            f"{v.name}: {v.image.shape[0]} x {v.image.shape[1]}, primary "
            f"{m['primary_angle_deg']:g} secondary {m['secondary_angle_deg']:g} deg, SDD "
            f"{m['source_to_detector_mm']:g} SID {m['source_to_isocenter_mm']:g} mm"
            + (f"; assumed: {', '.join(m['assumed'])}" if m["assumed"] else "")
        )
    console.print(f"wrote {out} ({len(views)} views, {dof} DoF)")


@app.command("simulate")
def simulate(
    subject: Annotated[
        int, typer.Option(help="Subject id (atlas id; any id >= 1 of a sampled population).")
    ],
    out: Annotated[Path, typer.Option(help="Output folder.")],
    atlas: PopulationOption = None,
    pattern: Annotated[str, typer.Option(help="si, ps or open-book.")] = "open-book",
    bone: Annotated[
        str, typer.Option(help="Dislocated innominate: left_hip or right_hip.")
    ] = "left_hip",
    dose: Annotated[
        float, typer.Option(help="uGy/frame at the isocentre (50 nominal, 0.5 lowest).")
    ] = 50.0,
    views: Annotated[
        str,
        typer.Option(
            help="Comma-separated: ap, lateral, inlet, outlet, iliac, obturator, oblique30."
        ),
    ] = "ap,oblique30",
    seed: Annotated[int, typer.Option(help="Seed of everything random in the case.")] = 0,
    beads: Annotated[int, typer.Option(help="Metal fiducial beads on the bones (for TRE).")] = 0,
    dicom: Annotated[
        bool,
        typer.Option(
            help="Also write dicom/ct/ (the CT as a DICOM series) and dicom/xray/ (XA images "
            "with their geometry tags)."
        ),
    ] = False,
) -> None:
    """Simulate a dislocated patient: CT, label map, radiographs and ground truth."""
    from rich.console import Console

    from pelvicnav.io.atlas import AtlasNotFoundError
    from pelvicnav.phantom.case import simulate_case
    from pelvicnav.phantom.ctsynth import CTOptions

    console = Console()
    try:
        a = _population(atlas, subject_ids=(subject,) if subject >= 1 else None)
        vertices = a.vertices[a.subject_index(subject)]
        with console.status(f"simulating subject {subject} ({pattern}, {dose} uGy/frame)"):
            truth = simulate_case(
                vertices, a.faces, out, subject_id=subject, pattern=pattern, bone=bone,
                dose_ugy=dose, views=tuple(v.strip() for v in views.split(",") if v.strip()),
                seed=seed, ct_options=CTOptions(beads=beads), dicom=dicom,
            )  # fmt: skip
    except (AtlasNotFoundError, ValueError) as err:
        raise _fail(str(err)) from None
    d = truth["dislocation"]
    console.print(
        f"wrote {out}: {d['pattern']} dislocation of {d['bone']} "
        f"({d['translation_mm']:.1f} mm, {d['rotation_deg']:.1f} deg), views {views}"
    )


@app.command("register")
def register(
    ct: Annotated[Path, typer.Option(help=_CT_HELP)],
    labels: Annotated[
        Path, typer.Option(help="Label map on the CT's grid (any format --ct takes).")
    ],
    views: Annotated[Path, typer.Option(help="views.json with the radiographs.")],
    out: Annotated[Path, typer.Option(help="result.json to write.")],
    plan: Annotated[
        Path | None,
        typer.Option(
            help="plan.json: dislocated_bone, target_from_current (4x4, CT frame), "
            "reference_bone (default sacrum)."
        ),
    ] = None,
    dof: Annotated[int, typer.Option(help="Stage-1 degrees of freedom: 6 (P known) or 9.")] = 6,
    seed: Annotated[int, typer.Option(help="Seed of CMA-ES.")] = 0,
    overlay: Annotated[
        Path | None, typer.Option(help="Folder for overlay PNGs (one per view).")
    ] = None,
    label_scheme: LabelSchemeOption = "ours",
    series: SeriesOption = None,
    overlay_dicom: Annotated[
        bool,
        typer.Option(
            help="With --overlay, also write each overlay as a DICOM Secondary Capture carrying "
            "the radiograph's patient and study identifiers."
        ),
    ] = False,
    init: Annotated[
        Path | None,
        typer.Option(
            help="A previous frame's result.json (same CT, bones and number of views): track "
            "from its poses and geometry, skipping stage 1 (a full registration if that fails)."
        ),
    ] = None,
) -> None:
    """Register the three bones of a CT to radiographs (two-stage multi-body 3D-2D).

    Writes OUT (result.json) and, beside it, transforms/{bone}.tfm (ITK, LPS; with --plan also
    transforms/residual.tfm) for 3D Slicer and ITK; see docs/slicer.md.
    """
    from rich.console import Console
    from rich.progress import Progress

    from pelvicnav.workflow.register import register_files

    console = Console()
    if plan is None:
        console.print(
            "[yellow]note:[/] no --plan: every bone gets the full search range and no "
            "residual is computed; with the plan naming the dislocated bone the "
            "registration is more reliable (docs/registration.md)"
        )
    try:
        with Progress(console=console) as bar:
            tasks = {}

            def report(stage: str, done: int, total: int) -> None:
                if stage not in tasks:
                    tasks[stage] = bar.add_task(stage, total=total)
                bar.update(tasks[stage], completed=done)

            record, result = register_files(
                ct, labels, views, out, plan=plan, dof=dof, seed=seed, overlay=overlay,
                overlay_dicom=overlay_dicom, label_scheme=label_scheme, series=series,
                progress=report, init=init,
            )  # fmt: skip
    except ValueError as err:
        raise _fail(str(err)) from None
    status = {
        "converged": "[green]converged[/]",
        "in question": "[red]NOT converged: in question, see the warnings[/]",
        "implausible": "[red]NOT converged: its joints are implausible, likely wrong[/]",
    }[result.verdict]
    if result.settled:
        status += " (its questions settled by a second opinion, see the warnings)"
    console.print(
        f"wrote {out} ({record['mode']}): {status}, GO {result.similarity:.3f}, "
        f"{result.seconds:.1f} s " + ", ".join(f"{s.name} {s.seconds:.1f} s" for s in result.stages)
    )
    for w in result.warnings:
        console.print(f"[yellow]warning:[/] {w}")
    if "residual" in record:
        console.print(record["residual"]["description"])


@app.command("demo")
def demo(
    out: Annotated[Path, typer.Option(help="Folder for the demo's figures.")] = Path("demo-output"),
    atlas: AtlasOption = None,
    tour: Annotated[
        bool, typer.Option(help="Instead: the short tour of C-arm geometry and planning figures.")
    ] = False,
) -> None:
    """The whole workflow offline: a simulated patient's CT -> plan -> two guided frames ->
    OUT/report.html (or, with --tour, the geometry and planning figures)."""
    from rich.console import Console

    console = Console()
    try:
        if tour:
            from pelvicnav.demo import run_demo as run_tour

            run_tour(out, atlas=atlas)
            return
        from pelvicnav.workflow.demo import run_demo

        summary = run_demo(out, atlas=atlas, say=console.print)
    except ValueError as err:
        raise _fail(str(err)) from None
    console.print(f"done in {summary['seconds']:.0f} s; open {summary['report']}")


def main() -> None:
    """Entry point of the ``pelvicnav`` script.

    The garbage collector's youngest generation collects every 10 000 allocations instead of
    700: numba's, scipy's and SimpleITK's imports create hundreds of thousands of objects that
    live as long as the process, and collecting them 400 times cost a ``pelvicnav register``
    0.1-0.2 s before it registered. Before the interpreter exits every object is frozen out of
    the collector: its teardown otherwise runs full collections over them, 0.35 s more (files
    are written and closed by then; the memory goes back with the process)."""
    import gc

    gc.set_threshold(10_000, 10, 10)
    try:
        app()
    finally:
        gc.freeze()


if __name__ == "__main__":
    main()
