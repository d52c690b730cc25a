"""Reading a clinical-size CT (512 x 512 x 400 at 0.8 mm) as a DICOM series, NIfTI and MHA, and
turning two X-ray DICOMs into a view set. Target: a DICOM series read in at most 3 s on 2 cores."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from benchmarks.harness import measure

DICOM_TARGET_S = 3.0


def run() -> dict:
    from pelvicnav.geometry import projection as pj
    from pelvicnav.io.dicom_ct import write_ct_series
    from pelvicnav.io.volume import read_volume, write_volume
    from pelvicnav.io.xray_dicom import convert_views, write_xray_dicom

    rng = np.random.default_rng(0)
    data = rng.integers(-1000, 2000, (512, 512, 400)).astype(np.int16)
    A = np.diag([0.8, 0.8, 0.8, 1.0])
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_ct_series(root / "ct", data, A)
        write_volume(root / "ct.nii.gz", data, A)
        write_volume(root / "ct.mha", data, A)
        timing = measure(lambda: read_volume(root / "ct"), repeats=3)
        timing |= {"target_s": DICOM_TARGET_S, "meets_target": timing["median_s"] <= DICOM_TARGET_S}
        out["read_dicom_series_512x512x400"] = timing
        out["read_nifti_gz_512x512x400"] = measure(
            lambda: read_volume(root / "ct.nii.gz"), repeats=3
        )
        out["read_mha_512x512x400"] = measure(lambda: read_volume(root / "ct.mha"), repeats=3)
        files = []
        for name, orbit, tilt in (("ap", 0.0, 0.0), ("oblique", 30.0, -20.0)):
            carm = pj.CArm(orbit_deg=orbit, tilt_deg=tilt)
            image = rng.random((carm.rows, carm.cols))
            files.append(write_xray_dicom(root / f"{name}.dcm", image, carm))
        out["views_from_two_xray_dicoms"] = measure(
            lambda: convert_views(files, root / "set" / "views.json", isocenter=(0, 0, 0)),
            repeats=5,
        )
    return out
