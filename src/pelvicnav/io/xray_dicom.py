"""X-ray images from a C-arm (DICOM XA, RF, DX, CR; PNG/TIFF with a JSON sidecar) into views.

Geometry (DICOM PS3.3 C.8.7.5, XA Positioner)
---------------------------------------------
* Positioner Primary Angle (0018,1510), alpha, is a longitude in the patient's transverse plane and
  the Secondary Angle (0018,1511), beta, a latitude in the sagittal plane; at 0/0 the patient faces
  the detector, +90 primary puts the detector at the patient's left (LAO), +90 secondary cranial.
  The unit vector from the isocentre to the detector is therefore, in LPS,
  ``d = (sin(alpha) cos(beta), -cos(alpha) cos(beta), sin(beta))``.
  pelvicnav's C-arm (:mod:`pelvicnav.geometry.projection`) puts the *source* anterior at orbit 0,
  so ``orbit = alpha - 180`` and ``tilt = -beta``. The angles are relative to the patient, whatever
  the Patient Position (0018,5100); it is recorded, not needed.
* Distance Source to Detector (0018,1110) is the SDD; Distance Source to Isocenter (0018,9402), or
  Distance Source to Patient (0018,1111) (XA/RF: to the isocentre), the SID; Imager Pixel Spacing
  (0018,1164) the pixel size at the detector. What the tags lack comes from a C-arm profile (JSON:
  ``source_to_detector_mm``, ``source_to_isocenter_mm``, ``pixel_spacing_mm``,
  ``principal_point_px``, ``roll_deg``, and for images without positioner tags
  ``primary_angle_deg``, ``secondary_angle_deg``); every value taken from it or assumed (principal
  point at the detector centre, no detector roll) is listed in the view's ``assumed``.
* DICOM does not say where the patient's CT lies relative to the isocentre: the caller gives the
  isocentre's position in the CT's world (the registration then finds the set-up error).
* Image axes: pelvicnav's images are seen from the source, columns along the C-arm's x. When
  Patient Orientation (0020,0020) says the rows or columns run the other way (an image displayed
  mirrored), the pixels are flipped to match, and the flip is recorded.
* Multi-frame images (rotational or dynamic runs): one view per frame; Positioner Primary/Secondary
  Angle Increment (0018,1520/1521) hold one value (the change per frame) or one offset per frame.

Intensities: modality values (rescaled) become line integrals. Pixel Intensity Relationship
(0028,1040) LIN (proportional to the X-ray intensity) is log-transformed against a flat-field
estimate (the 99.5th percentile, or the profile's ``flat_field``); LOG and display images keep
their values, oriented so that attenuation is positive (Pixel Intensity Relationship Sign
(0028,1041) when present, else MONOCHROME1/2), with air at zero. ``intensities="keep"`` uses
the values as displayed (MONOCHROME1 inverted) and nothing else.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pelvicnav.geometry import projection as pj
from pelvicnav.io.dicom_base import (
    XA_IMAGE_STORAGE,
    DicomIdentity,
    ds_number,
    new_dataset,
    save_dataset,
)
from pelvicnav.io.views import View

__all__ = [
    "CArmProfile",
    "XrayFileError",
    "angles_from_carm",
    "bone_centroid",
    "carm_angles",
    "convert_views",
    "patient_orientation",
    "read_profile",
    "read_xray",
    "views_from_files",
    "write_xray_dicom",
]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
_LETTERS = {"L": (1, 0, 0), "R": (-1, 0, 0), "P": (0, 1, 0), "A": (0, -1, 0), "H": (0, 0, 1)}
_LETTERS["F"] = (0, 0, -1)


class XrayFileError(ValueError):
    """An X-ray image whose pixels or geometry cannot be used; names the file and the tag."""


@dataclass(frozen=True)
class CArmProfile:
    """What a C-arm's images may not say about it (all optional).

    Attributes
    ----------
    source_to_detector_mm, source_to_isocenter_mm : float or None
    pixel_spacing_mm : (row, column) or None
        At the detector.
    principal_point_px : (u0, v0) or None
        Where the central ray meets the detector (column, row); default the detector centre.
    roll_deg : float or None
        Detector rotation about the central ray (pelvicnav's convention); default 0.
    primary_angle_deg, secondary_angle_deg : float or None
        For images without positioner tags (most DX/CR, PNG/TIFF).
    flat_field : float or None
        Unattenuated intensity of raw (LIN) images.
    source : str
        Where the profile came from, for messages.
    """

    source_to_detector_mm: float | None = None
    source_to_isocenter_mm: float | None = None
    pixel_spacing_mm: tuple[float, float] | None = None
    principal_point_px: tuple[float, float] | None = None
    roll_deg: float | None = None
    primary_angle_deg: float | None = None
    secondary_angle_deg: float | None = None
    flat_field: float | None = None
    source: str = "profile"

    @classmethod
    def from_dict(cls, doc: dict, source: str) -> CArmProfile:
        """Validate a JSON object; unknown keys and bad values raise, naming ``source``."""
        names = {f for f in cls.__dataclass_fields__ if f != "source"}
        if not isinstance(doc, dict):
            raise XrayFileError(f"{source}: expected a JSON object")
        unknown = set(doc) - names - {"name", "comment", "photometric", "intensity"}
        if unknown:
            raise XrayFileError(f"{source}: unknown keys {sorted(unknown)}; known: {sorted(names)}")
        values = {}
        for key in names & set(doc):
            v = doc[key]
            try:
                arr = np.asarray(v, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise XrayFileError(f"{source}: {key} must be numeric, got {v!r}") from None
            size = 2 if key in ("pixel_spacing_mm", "principal_point_px") else 1
            if arr.size != size or not np.all(np.isfinite(arr)):
                raise XrayFileError(f"{source}: {key} must be {size} finite number(s), got {v!r}")
            values[key] = tuple(float(x) for x in arr) if size == 2 else float(arr[0])
        return cls(**values, source=source)


def read_profile(path: str | os.PathLike) -> CArmProfile:
    """Read a C-arm profile (JSON)."""
    from pelvicnav.io.jsonfile import read_json

    return CArmProfile.from_dict(read_json(path), str(path))


# ---- angles -------------------------------------------------------------------------------------


def _wrap(deg: float) -> float:
    return float((deg + 180.0) % 360.0 - 180.0)


def angles_from_carm(orbit_deg: float, tilt_deg: float) -> tuple[float, float]:
    """DICOM (primary, secondary) positioner angles of a pelvicnav C-arm's (orbit, tilt)."""
    return _wrap(orbit_deg + 180.0), -float(tilt_deg)


def carm_angles(primary_deg: float, secondary_deg: float) -> tuple[float, float]:
    """pelvicnav (orbit, tilt) of DICOM (primary, secondary) positioner angles."""
    return _wrap(primary_deg - 180.0), -float(secondary_deg)


def patient_orientation(carm: pj.CArm) -> tuple[str, str]:
    """Patient Orientation (0020,0020) of a C-arm's image: row and column directions as letters."""
    R = carm.rotation
    return _letters(R[:, 0]), _letters(R[:, 1])


def _letters(v: NDArray) -> str:
    order = np.argsort(-np.abs(v))
    names = (("R", "L"), ("A", "P"), ("F", "H"))
    return "".join(names[a][int(v[a] > 0)] for a in order if abs(v[a]) > 1e-3) or "L"


def _direction(letters: str, where: str) -> NDArray[np.float64]:
    try:
        v = np.sum([_LETTERS[c] for c in letters.upper()], axis=0).astype(float)
    except KeyError:
        raise XrayFileError(f"{where}: Patient Orientation (0020,0020) {letters!r} is not made of "
                            "L R A P H F") from None  # fmt: skip
    return v / max(np.linalg.norm(v), 1e-12)


# ---- writing ------------------------------------------------------------------------------------


def write_xray_dicom(
    path: str | os.PathLike,
    line_integrals: ArrayLike,
    carm: pj.CArm,
    *,
    identity: DicomIdentity | None = None,
    description: str = "pelvicnav radiograph",
    dose_ugy: float | None = None,
) -> Path:
    """Write a radiograph as a DICOM XA image whose tags carry its geometry.

    Line integrals are stored as 16-bit LOG values (sign -1: higher values, less intensity) with a
    rescale that recovers them to 1/65535 of their range. The isocentre's world position is not
    stored (DICOM has no place for it): readers are told it.

    Raises
    ------
    ValueError
        An image that does not fit the detector, or a C-arm DICOM's legacy tags cannot express
        (a detector roll, or a principal point off the detector centre).
    """
    from pydicom.uid import generate_uid

    p = np.asarray(line_integrals, dtype=np.float64)
    if p.shape != (carm.rows, carm.cols) or not np.all(np.isfinite(p)):
        raise ValueError(f"image {p.shape} does not match the detector ({carm.rows}, {carm.cols})")
    centre = ((carm.cols - 1) / 2.0, (carm.rows - 1) / 2.0)
    if carm.roll_deg != 0 or not np.allclose(carm.principal_point_px, centre):
        raise ValueError("DICOM XA tags cannot carry a detector roll or an offset principal point")
    ident = (identity or DicomIdentity()).filled()
    ds = new_dataset(XA_IMAGE_STORAGE, "XA", ident, generate_uid())
    primary, secondary = angles_from_carm(carm.orbit_deg, carm.tilt_deg)
    ds.SeriesDescription = description
    ds.ImageType = ["DERIVED", "SECONDARY", "SINGLE PLANE"]
    ds.PatientPosition = "HFS"
    ds.PatientOrientation = list(patient_orientation(carm))
    ds.PositionerMotion = "STATIC"
    ds.PositionerPrimaryAngle = ds_number(primary)
    ds.PositionerSecondaryAngle = ds_number(secondary)
    ds.DistanceSourceToDetector = ds_number(carm.source_to_detector)
    ds.DistanceSourceToPatient = ds_number(carm.source_to_isocenter)
    ds.ImagerPixelSpacing = [ds_number(x) for x in carm.pixel_spacing]
    if dose_ugy is not None:
        ds.add_new(0x00189473, "FL", float(dose_ugy) / 1000.0)  # Acquired Image Area Dose Product
        ds.ImageComments = f"air kerma {dose_ugy:g} uGy/frame at the isocentre"
    lo, hi = float(p.min()), float(p.max())
    slope = max((hi - lo) / 65535.0, 1e-9)
    ds.Rows, ds.Columns = p.shape
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
    ds.PixelIntensityRelationship, ds.PixelIntensityRelationshipSign = "LOG", -1
    ds.RescaleSlope, ds.RescaleIntercept, ds.RescaleType = ds_number(slope), ds_number(lo), "US"
    stored = np.clip(np.round((p - lo) / float(ds.RescaleSlope)), 0, 65535).astype(np.uint16)
    ds.PixelData = stored.tobytes()
    ds.InstanceNumber = 1
    return save_dataset(ds, path)


# ---- reading ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Geometry:
    sdd: float
    sid: float
    spacing: tuple[float, float]
    primary: NDArray[np.float64]  # (frames,)
    secondary: NDArray[np.float64]
    principal_point: tuple[float, float] | None
    roll: float
    orientation: tuple[str, str] | None
    assumed: list[str] = field(default_factory=list)


def read_xray(
    path: str | os.PathLike,
    *,
    isocenter: ArrayLike,
    profile: CArmProfile | None = None,
    intensities: str = "auto",
) -> list[View]:
    """Views from one X-ray file: a DICOM image (one view per frame) or a PNG/TIFF + JSON sidecar.

    Parameters
    ----------
    path : path
    isocenter : (3,) float, mm
        The C-arm isocentre's position in the CT's world (LPS).
    profile : CArmProfile, optional
        Geometry the file lacks.
    intensities : {"auto", "keep"}
        Conversion to line integrals (module docstring).

    Returns
    -------
    list of View
        Named after the file (``_fNNN`` per frame); ``meta`` holds the angles, the tags' source
        (``dicom``: file, SOP Instance UID, patient and study identifiers) and ``assumed``.

    Raises
    ------
    XrayFileError
        Unreadable pixels, geometry missing from tags and profile (naming the tag), increments
        inconsistent with the number of frames, a Patient Orientation at odds with the angles.
    """
    path = Path(path)
    if intensities not in ("auto", "keep"):
        raise ValueError(f"intensities must be 'auto' or 'keep', got {intensities!r}")
    iso = np.asarray(isocenter, dtype=np.float64).reshape(-1)
    if iso.shape != (3,) or not np.all(np.isfinite(iso)):
        raise ValueError(f"isocenter must be 3 finite numbers (mm), got {isocenter}")
    profile = profile or CArmProfile()
    if not path.is_file():
        raise XrayFileError(f"{path}: file not found")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        frames, geometry, tags, source = _read_plain_image(path, profile)
    else:
        frames, geometry, tags, source = _read_dicom_xray(path, profile, intensities)
    views = []
    for f, image in enumerate(frames):
        name = path.stem if len(frames) == 1 else f"{path.stem}_f{f:03d}"
        views.append(_view(name, image, geometry, f, iso, tags | {"source": source}, path))
    return views


def _view(name, image, g: _Geometry, f: int, iso, tags: dict, path: Path) -> View:
    orbit, tilt = carm_angles(g.primary[f], g.secondary[f])
    carm = pj.CArm(
        source_to_detector=g.sdd, source_to_isocenter=g.sid, rows=image.shape[0],
        cols=image.shape[1], pixel_spacing=g.spacing, principal_point=g.principal_point,
        orbit_deg=orbit, tilt_deg=tilt, roll_deg=g.roll, isocenter=tuple(iso),
    )  # fmt: skip
    flips = []
    if g.orientation is not None:
        R = carm.rotation
        for axis, (letters, ours) in enumerate(zip(g.orientation, (R[:, 0], R[:, 1]), strict=True)):
            cos = float(_direction(letters, str(path)) @ ours)
            if abs(cos) < 0.5:
                raise XrayFileError(
                    f"{path}: Patient Orientation (0020,0020) {'/'.join(g.orientation)} does not "
                    f"match the positioner angles ({g.primary[f]:g}, {g.secondary[f]:g}); a "
                    "detector rotated about the beam needs roll_deg in the profile"
                )
            if cos < 0:
                image = np.flip(image, axis=1 - axis)
                flips.append("columns" if axis == 0 else "rows")
    meta = {
        "orbit_deg": orbit, "tilt_deg": tilt, "roll_deg": g.roll,
        "primary_angle_deg": float(g.primary[f]), "secondary_angle_deg": float(g.secondary[f]),
        "source_to_detector_mm": g.sdd, "source_to_isocenter_mm": g.sid,
        "isocenter_mm": [float(x) for x in iso], "assumed": list(g.assumed),
        "flipped": flips, "frame": f, **tags,
    }  # fmt: skip
    return View(name, np.ascontiguousarray(image, dtype=np.float32), carm.projection_matrix,
                carm.pixel_spacing, meta)  # fmt: skip


def _number(ds, keyword: str, tag: str, fallback, what: str, path: Path, g_assumed: list):
    value = getattr(ds, keyword, None) if ds is not None else None
    if value not in (None, ""):
        return value
    if fallback is not None:
        g_assumed.append(f"{what} from the profile")
        return fallback
    raise XrayFileError(
        f"{path}: no {keyword} {tag} and no C-arm profile giving it: {what} unknown "
        "(pass --profile carm.json; for unknown geometry register with 9 DoF)"
    )


def _geometry(ds, profile: CArmProfile, path: Path, frames: int) -> _Geometry:
    assumed: list[str] = []
    spacing = _number(ds, "ImagerPixelSpacing", "(0018,1164)", profile.pixel_spacing_mm,
                      "the detector pixel spacing", path, assumed)  # fmt: skip
    sdd = _number(ds, "DistanceSourceToDetector", "(0018,1110)", profile.source_to_detector_mm,
                  "the source-detector distance", path, assumed)  # fmt: skip
    sid = getattr(ds, "DistanceSourceToIsocenter", None) if ds is not None else None
    if sid in (None, ""):
        sid = _number(ds, "DistanceSourceToPatient", "(0018,1111)",
                      profile.source_to_isocenter_mm, "the source-isocentre distance", path,
                      assumed)  # fmt: skip
    primary = _number(ds, "PositionerPrimaryAngle", "(0018,1510)", profile.primary_angle_deg,
                      "the primary positioner angle", path, assumed)  # fmt: skip
    secondary = _number(ds, "PositionerSecondaryAngle", "(0018,1511)",
                        profile.secondary_angle_deg, "the secondary positioner angle", path,
                        assumed)  # fmt: skip
    prim = float(primary) + _increments(ds, "PositionerPrimaryAngleIncrement", "(0018,1520)",
                                        frames, path)  # fmt: skip
    sec = float(secondary) + _increments(ds, "PositionerSecondaryAngleIncrement", "(0018,1521)",
                                         frames, path)  # fmt: skip
    if profile.principal_point_px is None:
        assumed.append("principal point at the detector centre")
    if profile.roll_deg is None:
        assumed.append("no detector roll")
    orientation = None
    po = getattr(ds, "PatientOrientation", None) if ds is not None else None
    if po is not None and len(po) == 2 and all(str(x) for x in po):
        orientation = (str(po[0]), str(po[1]))
    else:
        assumed.append("image seen from the source, head at the top (no Patient Orientation)")
        if str(getattr(ds, "PatientPosition", "")).upper().startswith("FF"):
            assumed.append("feet-first patient: check that the head is at the image's top")
    try:
        sp = tuple(float(x) for x in np.asarray(spacing, dtype=float).reshape(-1))
        sp = sp * 2 if len(sp) == 1 else sp
        geometry = _Geometry(float(sdd), float(sid), sp, prim, sec, profile.principal_point_px,
                             float(profile.roll_deg or 0.0), orientation, assumed)  # fmt: skip
        pj.CArm(source_to_detector=geometry.sdd, source_to_isocenter=geometry.sid,
                pixel_spacing=geometry.spacing)  # fmt: skip
    except (TypeError, ValueError) as err:
        raise XrayFileError(f"{path}: impossible geometry ({err})") from None
    return geometry


def _increments(ds, keyword: str, tag: str, frames: int, path: Path) -> NDArray[np.float64]:
    raw = getattr(ds, keyword, None) if ds is not None else None
    if raw in (None, ""):
        if frames > 1 and str(getattr(ds, "PositionerMotion", "")).upper() == "DYNAMIC":
            raise XrayFileError(
                f"{path}: Positioner Motion is DYNAMIC but {keyword} {tag} is missing: the "
                f"geometry of frames 2-{frames} is unknown"
            )
        return np.zeros(frames)
    values = [raw] if isinstance(raw, int | float | str) else list(raw)
    inc = np.asarray([float(x) for x in values])
    if inc.size == 1:
        return np.arange(frames) * inc[0]
    if inc.size != frames:
        raise XrayFileError(
            f"{path}: inconsistent geometry: {keyword} {tag} has {inc.size} values for "
            f"{frames} frames (one value, or one per frame)"
        )
    return inc


def _read_dicom_xray(path: Path, profile: CArmProfile, intensities: str):
    import pydicom
    from pydicom.pixels import apply_modality_lut

    try:
        ds = pydicom.dcmread(path)
        raw = ds.pixel_array
    except Exception as err:  # pydicom raises many types for non-DICOM or broken files
        raise XrayFileError(f"{path}: not a readable DICOM image ({err})") from None
    frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
    if "PerFrameFunctionalGroupsSequence" in ds:
        raise XrayFileError(
            f"{path}: an enhanced multi-frame image (per-frame functional groups) is not "
            "supported; export the run as legacy XA/RF images"
        )
    if int(getattr(ds, "SamplesPerPixel", 1)) != 1:
        raise XrayFileError(f"{path}: a colour image (Samples per Pixel > 1) is not an X-ray")
    raw = raw.reshape(frames, int(ds.Rows), int(ds.Columns))
    values = np.asarray(apply_modality_lut(raw, ds), dtype=np.float64)
    g = _geometry(ds, profile, path, frames)
    relationship = str(getattr(ds, "PixelIntensityRelationship", "")).upper()
    sign = getattr(ds, "PixelIntensityRelationshipSign", None)
    photometric = str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2")).upper()
    images = [
        _line_integrals(v, relationship, sign, photometric, intensities, profile.flat_field)
        for v in values
    ]
    tags = {"dicom": {
        "file": str(path), "modality": str(getattr(ds, "Modality", "")),
        "sop_class_uid": str(getattr(ds, "SOPClassUID", "")),
        "sop_instance_uid": str(getattr(ds, "SOPInstanceUID", "")),
        "patient_position": str(getattr(ds, "PatientPosition", "")),
        "pixel_intensity_relationship": relationship, "photometric": photometric,
        **asdict(DicomIdentity.of(ds)),
    }}  # fmt: skip
    return images, g, tags, "dicom"


def _read_plain_image(path: Path, profile: CArmProfile):
    from PIL import Image

    from pelvicnav.io.jsonfile import read_json

    sidecar = path.with_suffix(".json")
    if not sidecar.is_file():
        raise XrayFileError(f"{path}: a PNG/TIFF needs its geometry in {sidecar.name} beside it")
    doc = read_json(sidecar)
    side = CArmProfile.from_dict(doc, str(sidecar))
    merged = CArmProfile(**{
        k: getattr(side, k) if getattr(side, k) is not None else getattr(profile, k)
        for k in CArmProfile.__dataclass_fields__ if k != "source"
    }, source=str(sidecar))  # fmt: skip
    try:
        with Image.open(path) as im:
            values = np.asarray(im, dtype=np.float64)
    except Exception as err:  # Pillow raises several types for broken files
        raise XrayFileError(f"{path}: not a readable image ({err})") from None
    if values.ndim != 2:
        raise XrayFileError(f"{path}: expected a greyscale image, got shape {values.shape}")
    intensity = str(doc.get("intensity", "log")).lower()
    photometric = str(doc.get("photometric", "MONOCHROME2")).upper()
    if intensity not in ("log", "lin", "display"):
        raise XrayFileError(f"{sidecar}: intensity must be log, lin or display")
    g = _geometry(None, merged, path, 1)
    image = _line_integrals(values, intensity.upper(), None, photometric, "auto", side.flat_field)
    return [image], g, {"sidecar": str(sidecar)}, "image"


def _line_integrals(values, relationship, sign, photometric, intensities, flat_field):
    bright_is_attenuating = photometric != "MONOCHROME1"
    if intensities == "keep":
        return values if bright_is_attenuating else -values
    if relationship == "LIN":
        intensity = values if sign in (None, 1) else values.max() - values
        i0 = float(flat_field) if flat_field else float(np.percentile(intensity, 99.5))
        i0 = max(i0, 1e-12)
        return -np.log(np.maximum(intensity, i0 * 1e-6) / i0)
    if sign is not None:
        bright_is_attenuating = int(sign) == -1
    att = values if bright_is_attenuating else -values
    return att - float(np.percentile(att, 0.5))


def views_from_files(
    files: list[str | os.PathLike],
    *,
    isocenter: ArrayLike,
    profile: CArmProfile | None = None,
    intensities: str = "auto",
) -> list[View]:
    """Views from several X-ray files, names made unique."""
    views: list[View] = []
    for f in files:
        for v in read_xray(f, isocenter=isocenter, profile=profile, intensities=intensities):
            name, n = v.name, 2
            while name in {w.name for w in views}:
                name, n = f"{v.name}_{n}", n + 1
            views.append(View(name, v.image, v.projection_matrix, v.pixel_spacing, v.meta))
    return views


def convert_views(
    files: list[str | os.PathLike],
    out: str | os.PathLike,
    *,
    isocenter: ArrayLike | None = None,
    ct: str | os.PathLike | None = None,
    profile: CArmProfile | str | os.PathLike | None = None,
    intensities: str = "auto",
    degrees_of_freedom: int = 6,
) -> list[View]:
    """Read X-ray files and write them as a view set (``out``: the JSON, images beside it).

    The isocentre's place in the CT's world is ``isocenter`` (mm) or the centroid of the bone
    of ``ct`` (exactly one of them). ``profile``: a :class:`CArmProfile` or its JSON file.
    Everything is read and checked before anything is written.
    """
    from pelvicnav.io.views import write_views

    if (isocenter is None) == (ct is None):
        raise ValueError(
            "give the isocentre's place in the CT's world: --isocenter x,y,z (mm) or --ct CT "
            "(the centroid of its bone); DICOM X-ray tags do not say where the patient lies"
        )
    if ct is not None:
        isocenter = bone_centroid(ct)
    if profile is not None and not isinstance(profile, CArmProfile):
        profile = read_profile(profile)
    if degrees_of_freedom not in (6, 9):
        raise ValueError(f"degrees of freedom must be 6 or 9, got {degrees_of_freedom}")
    if not files:
        raise ValueError("no X-ray files given")
    views = views_from_files(files, isocenter=isocenter, profile=profile, intensities=intensities)
    out = Path(out)
    write_views(out.parent, views, degrees_of_freedom=degrees_of_freedom, filename=out.name)
    return views


def bone_centroid(ct: str | os.PathLike, threshold_hu: float = 200.0) -> NDArray[np.float64]:
    """World position (mm) of the centroid of a CT's voxels at or above ``threshold_hu``."""
    from pelvicnav.io.volume import read_ct

    data, A = read_ct(ct)
    ijk = np.argwhere(np.asarray(data) >= threshold_hu)
    return (A[:3, :3] @ ijk.mean(axis=0)) + A[:3, 3]
