"""The ``pelvicnav`` command line.

A thin layer over the library: heavy imports (numpy, scipy, numba) happen inside the commands so
that ``pelvicnav --help`` answers at once. Errors in user input are printed as one message naming
the file and what is wrong, with exit status 2.
"""

from __future__ import annotations

import os
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

AtlasOption = Annotated[
    Path | None,
    typer.Option(
        "--atlas",
        help="Atlas folder (default: $PELVICNAV_ATLAS, then the user cache).",
        file_okay=False,
    ),
]


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
    for b, bone in enumerate(a.bones):
        v = a.vertices[:, b]
        extent = (v.max(axis=1) - v.min(axis=1)).mean(axis=0)
        centroid = v.mean(axis=(0, 1))
        table.add_row(
            bone,
            str(v.shape[1]),
            str(len(a.faces[b])),
            " / ".join(f"{x:.1f}" for x in extent),
            " / ".join(f"{x:.1f}" for x in centroid),
        )
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


@app.command("demo")
def demo(
    out: Annotated[Path, typer.Option(help="Folder for the demo's figures.")] = Path("demo-output"),
    atlas: AtlasOption = None,
) -> None:
    """Show what the toolkit does so far: C-arm geometry and the atlas projected into views."""
    from pelvicnav.demo import run_demo

    try:
        run_demo(out, atlas=atlas)
    except ValueError as err:
        raise _fail(str(err)) from None


def main() -> None:
    """Entry point of the ``pelvicnav`` script."""
    app()


if __name__ == "__main__":
    main()
