"""A generated population (sampled from the model, or procedural) against the real atlas: a size
table and a figure."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from pelvicnav.io.atlas import Atlas
from pelvicnav.io.atomic import save_figure, write_text

__all__ = [
    "plot_population",
    "population_study",
    "run_population_study",
    "size_table",
]

_MEASURES = (
    ("sacrum_extent", 0, "sacrum width (x)"),
    ("sacrum_extent", 1, "sacrum depth (y)"),
    ("sacrum_extent", 2, "sacrum height (z)"),
    ("left_hip_extent", 0, "left innominate x"),
    ("left_hip_extent", 1, "left innominate y"),
    ("left_hip_extent", 2, "left innominate z"),
    ("right_hip_extent", 0, "right innominate x"),
    ("right_hip_extent", 1, "right innominate y"),
    ("right_hip_extent", 2, "right innominate z"),
    ("pelvic_width", None, "pelvic width"),
    ("inter_acetabular", None, "hip centre distance"),
)


def size_table(
    ours: dict[str, NDArray], reference: dict[str, NDArray] | None = None
) -> list[dict[str, object]]:
    """Rows of mean, sd, min and max (mm) per size measure, with the reference's when given.

    ``inside`` is True when our min..max lies within the reference's min..max;
    ``mean_difference_pct`` is our mean against the reference's, in percent.
    """
    rows = []
    for key, axis, label in _MEASURES:
        row: dict[str, object] = {"measure": label}
        for name, stats in (("sampled", ours), ("atlas", reference)):
            if stats is None:
                continue
            v = np.asarray(stats[key], dtype=float)
            v = v if axis is None else v[:, axis]
            row |= {
                f"{name}_mean": round(float(v.mean()), 1),
                f"{name}_sd": round(float(v.std(ddof=1)), 1),
                f"{name}_min": round(float(v.min()), 1),
                f"{name}_max": round(float(v.max()), 1),
            }
        if reference is not None:
            row["mean_difference_pct"] = round(
                100 * (row["sampled_mean"] / row["atlas_mean"] - 1), 1
            )
            row["inside"] = bool(
                row["sampled_min"] >= row["atlas_min"] and row["sampled_max"] <= row["atlas_max"]
            )
        rows.append(row)
    return rows


def _markdown(rows: list[dict[str, object]]) -> str:
    has_ref = "atlas_mean" in rows[0]
    head = "| measure (mm) | sampled mean ± sd | sampled range |"
    sep = "|---|---|---|"
    if has_ref:
        head += " atlas mean ± sd | atlas range | inside | mean difference % |"
        sep += "---|---|---|---|"
    lines = [head, sep]
    for r in rows:
        line = (
            f"| {r['measure']} | {r['sampled_mean']} ± {r['sampled_sd']} | "
            f"{r['sampled_min']}–{r['sampled_max']} |"
        )
        if has_ref:
            line += (
                f" {r['atlas_mean']} ± {r['atlas_sd']} | {r['atlas_min']}–{r['atlas_max']} |"
                f" {'yes' if r['inside'] else 'NO'} | {r['mean_difference_pct']:+.1f} |"
            )
        lines.append(line)
    return "\n".join(lines) + "\n"


def _shaded(ax, meshes, colours, i: int, j: int, toward: int, sign: float) -> None:
    """Flat-shaded orthographic view of meshes on axes (i, j), viewer along ``sign * toward``.

    All triangles of all meshes are depth-sorted together (painter's algorithm).
    """
    from matplotlib.collections import PolyCollection

    tris, rgbs = [], []
    for (vertices, faces), colour in zip(meshes, colours, strict=True):
        tri = vertices[faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        shade = 0.25 + 0.75 * np.clip(sign * n[:, toward], 0, 1)
        tris.append(tri)
        rgbs.append(np.asarray(colour)[None, :] * shade[:, None])
    tri, rgb = np.concatenate(tris), np.concatenate(rgbs)
    order = np.argsort(sign * tri.mean(axis=1)[:, toward])
    ax.add_collection(PolyCollection(tri[order][:, :, [i, j]], facecolors=rgb[order], lw=0))


def plot_population(atlas: Atlas, path: str | os.PathLike, *, n_overlay: int = 8) -> Path:
    """Subject 1 shaded from the front, above and the side; outlines of further subjects.

    Each subject is centred on its pelvis centroid (placements in the CT frame differ).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    views = (
        (0, 2, 1, -1.0, "anterior (x right-left, z up)"),
        (0, 1, 2, 1.0, "superior (x, y posterior down)"),
        (1, 2, 0, 1.0, "left lateral (y, z)"),
    )
    colours = ((0.95, 0.85, 0.6), (0.75, 0.85, 0.95), (0.75, 0.95, 0.8))
    fig, axes = plt.subplots(2, 3, figsize=(15, 10))
    V = atlas.vertices
    for col, (i, j, toward, sign, title) in enumerate(views):
        ax = axes[0, col]
        centre = V[0].reshape(-1, 3).mean(axis=0)
        meshes = [(V[0, b] - centre, atlas.faces[b]) for b in range(3)]
        _shaded(ax, meshes, colours, i, j, toward, sign)
        ax.set_title(f"subject {atlas.subject_ids[0]}: {title}")
        ax2 = axes[1, col]
        for s in range(min(n_overlay, atlas.n_subjects)):
            c = V[s].reshape(-1, 3).mean(axis=0)
            for b in range(3):
                p = V[s, b, ::4] - c
                ax2.scatter(p[:, i], p[:, j], s=0.3, color=plt.cm.tab10(s % 10), alpha=0.4)
        ax2.set_title(f"{min(n_overlay, atlas.n_subjects)} subjects ({atlas.source})")
        for a in (ax, ax2):
            a.autoscale()
            a.set_aspect("equal")
            if (i, j) == (0, 1):
                a.invert_yaxis()
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return path


def run_population_study(
    out: str | os.PathLike,
    population: Atlas,
    reference: Atlas | None = None,
) -> list[dict[str, object]]:
    """Write ``sizes.csv``, ``sizes.md`` and ``population.png`` into ``out``; return the rows."""
    import csv
    import io

    from pelvicnav.phantom.population import atlas_statistics

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = size_table(
        atlas_statistics(population), None if reference is None else atlas_statistics(reference)
    )
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_text(out / "sizes.csv", buf.getvalue())
    write_text(out / "sizes.md", _markdown(rows))
    plot_population(population, out / "population.png")
    return rows


def population_study(
    out: str | os.PathLike,
    population: str,
    atlas: str | os.PathLike | None = None,
    *,
    subjects: int = 40,
    seed: int = 0,
) -> tuple[list[dict[str, object]], Atlas | None, str]:
    """``pelvicnav study population``: draw a population ("model" or "procedural") and compare
    it with the atlas when there is one. Returns the rows, the atlas (or None) and a note saying
    why there is no comparison (or "").

    Raises
    ------
    ValueError
        An unknown population kind. AtlasNotFoundError: an atlas path given but not there.
    """
    from pelvicnav.io.atlas import AtlasNotFoundError, load_atlas
    from pelvicnav.phantom.population import MODEL, PROCEDURAL, load_population

    if population not in (MODEL, PROCEDURAL):
        raise ValueError(f"--population must be 'model' or 'procedural', got {population!r}")
    note = ""
    try:
        reference = load_atlas(atlas)
    except AtlasNotFoundError as err:
        if atlas is not None:
            raise
        reference, note = None, f"{err}\nno atlas: the table shows the population only"
    pop = load_population(population, n_subjects=subjects, seed=seed)
    return run_population_study(out, pop, reference), reference, note
