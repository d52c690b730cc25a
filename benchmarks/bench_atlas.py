"""Loading the real Han atlas (40 subjects x 3 bones x 5000 vertices). Target: under 5 s."""

from __future__ import annotations

import os

from benchmarks.harness import measure

TARGET_S = 5.0


def run() -> dict:
    from pelvicnav.io.atlas import AtlasNotFoundError, load_atlas, resolve_atlas_path

    try:
        path = resolve_atlas_path(os.environ.get("PELVICNAV_ATLAS"))
    except AtlasNotFoundError as err:
        return {"skipped": str(err)}
    atlas = load_atlas(path)
    timing = measure(lambda: load_atlas(path), repeats=5, warmup=1)
    return {
        "atlas_load": {
            **timing,
            "subjects": atlas.n_subjects,
            "vertices_per_bone": atlas.n_vertices,
            "target_s": TARGET_S,
            "meets_target": timing["median_s"] < TARGET_S,
        }
    }
