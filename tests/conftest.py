"""Shared fixtures: seeded hypothesis profile, the real atlas (when present) and tiny atlases."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

from pelvicnav.io.atlas import BONE_FILES
from pelvicnav.io.vtk_legacy import write_polydata

# Shared helpers (tests/helpers) importable from every test folder.
sys.path.insert(0, str(Path(__file__).parent))

# Property tests are derandomised: every run draws the same examples (reproducible CI).
settings.register_profile("pelvicnav", derandomize=True, max_examples=200, deadline=None)
settings.load_profile("pelvicnav")

# An octahedron: 6 vertices, 8 triangles (a closed surface with consistent orientation).
OCTA_VERTICES = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float
)
OCTA_FACES = np.array(
    [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
)
BONE_OFFSETS = {"sacrum": (0, 30, 0), "left_hip": (80, 0, 0), "right_hip": (-80, 0, 0)}


@pytest.fixture(autouse=True)
def _own_cache(tmp_path_factory, monkeypatch):
    """Every test its own cache of CT-derived bone models (never the user's ~/.cache)."""
    monkeypatch.setenv("PELVICNAV_CACHE", str(tmp_path_factory.mktemp("cache")))


@pytest.fixture
def real_atlas_path() -> Path:
    """The real Han atlas, or skip: it is not committed and only present where CI provides it."""
    path = os.environ.get("PELVICNAV_ATLAS")
    if not path:
        pytest.skip("PELVICNAV_ATLAS is not set: the real Han atlas is not available here")
    if not Path(path).is_dir():
        pytest.skip(f"PELVICNAV_ATLAS={path} is not a folder")
    return Path(path)


def write_tiny_atlas(root: Path, ids: tuple[int, ...] = (1, 2, 3), *, seed: int = 0) -> Path:
    """Write a small atlas in the Han layout: octahedra standing in for the three bones."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    (root / "table.csv").write_text(
        "TCIA Subject ID,Atlas ID\n" + "".join(f"CASE_{i:03d},{i}\n" for i in ids)
    )
    for bone, (folder, prefix) in BONE_FILES.items():
        d = root / "surface" / folder
        d.mkdir(parents=True, exist_ok=True)
        for i in ids:
            v = OCTA_VERTICES * 20 + BONE_OFFSETS[bone] + rng.normal(0, 1, (6, 3))
            write_polydata(d / f"{prefix}{i}_cpd.vtk", v, OCTA_FACES)
    return root


@pytest.fixture
def tiny_atlas(tmp_path: Path) -> Path:
    return write_tiny_atlas(tmp_path / "atlas")


@pytest.fixture
def make_tiny_atlas() -> Callable[..., Path]:
    return write_tiny_atlas
