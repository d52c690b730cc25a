"""Points as 3D Slicer Markups JSON (``.mrk.json``): landmarks, beads, femoral heads.

One point list per file, LPS millimetres (``coordinateSystem: LPS``), in the schema Slicer 5
writes (markups-schema-v1.0.3). Slicer opens the file by drag and drop; each point keeps its label.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["MARKUPS_SCHEMA", "read_markups", "write_markups"]

MARKUPS_SCHEMA = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/"
    "Schema/markups-schema-v1.0.3.json#"
)


def write_markups(
    path: str | os.PathLike, points: dict[str, ArrayLike], *, name: str = "pelvicnav"
) -> Path:
    """Write labelled points (LPS mm) as one Slicer point list; atomic.

    Raises
    ------
    ValueError
        A point that is not 3 finite numbers.
    """
    control = []
    for n, (label, p) in enumerate(points.items(), start=1):
        xyz = np.asarray(p, dtype=np.float64).reshape(-1)
        if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
            raise ValueError(f"point {label!r} must be 3 finite numbers, got {p}")
        control.append({
            "id": str(n), "label": str(label), "description": "", "associatedNodeID": "",
            "position": xyz.tolist(), "orientation": [-1.0, 0, 0, 0, -1.0, 0, 0, 0, 1.0],
            "selected": True, "locked": True, "visibility": True, "positionStatus": "defined",
        })  # fmt: skip
    doc = {
        "@schema": MARKUPS_SCHEMA,
        "markups": [{
            "type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
            "locked": True, "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d",
            "lastUsedControlPointNumber": len(control), "controlPoints": control,
            "measurements": [], "name": name,
        }],
    }  # fmt: skip
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(doc, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def read_markups(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read the points of a Slicer Markups JSON file as ``{label: (3,) LPS mm}``.

    RAS files (Slicer's other choice) are converted. Raises ValueError naming the file.
    """
    from pelvicnav.io.jsonfile import read_json

    doc = read_json(path)
    try:
        markup = doc["markups"][0]
        flip = np.array([-1.0, -1.0, 1.0]) if markup.get("coordinateSystem") == "RAS" else 1.0
        return {
            str(c["label"]): np.asarray(c["position"], dtype=np.float64) * flip
            for c in markup["controlPoints"]
        }
    except (KeyError, IndexError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: not a Slicer Markups JSON point list ({err})") from None
