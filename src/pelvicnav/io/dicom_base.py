"""What every DICOM file pelvicnav writes shares: file meta, identifiers, numbers as DS strings.

Files are written with pydicom, explicit VR little endian, under a temporary name and renamed.
The patient and study identifiers come from a :class:`DicomIdentity` so that derived images (a
secondary capture of an overlay) can carry those of the radiograph they came from.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "CT_IMAGE_STORAGE",
    "SECONDARY_CAPTURE_STORAGE",
    "XA_IMAGE_STORAGE",
    "DicomIdentity",
    "ds_number",
    "new_dataset",
    "save_dataset",
]

CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
XA_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.12.1"
SECONDARY_CAPTURE_STORAGE = "1.2.840.10008.5.1.4.1.1.7"


@dataclass(frozen=True)
class DicomIdentity:
    """Patient and study a file belongs to (new UIDs are made when left empty)."""

    patient_name: str = "PELVICNAV^SIMULATED"
    patient_id: str = "PELVICNAV-0"
    study_uid: str = ""
    study_id: str = "1"
    frame_of_reference_uid: str = ""

    def filled(self) -> DicomIdentity:
        """This identity with any missing UID generated."""
        from pydicom.uid import generate_uid

        return DicomIdentity(
            self.patient_name,
            self.patient_id,
            self.study_uid or generate_uid(),
            self.study_id,
            self.frame_of_reference_uid or generate_uid(),
        )

    @classmethod
    def from_tags(cls, tags: dict) -> DicomIdentity:
        """The identity in a dict of this class's fields (others ignored; missing ones default)."""
        return cls(**{k: str(tags[k]) for k in cls.__dataclass_fields__ if tags.get(k)})

    @classmethod
    def of(cls, ds) -> DicomIdentity:
        """The identity recorded in a dataset."""
        return cls(
            str(getattr(ds, "PatientName", "")),
            str(getattr(ds, "PatientID", "")),
            str(getattr(ds, "StudyInstanceUID", "")),
            str(getattr(ds, "StudyID", "")),
            str(getattr(ds, "FrameOfReferenceUID", "")),
        )


def ds_number(x: float) -> str:
    """A number as a DICOM Decimal String (at most 16 characters, as precise as that allows)."""
    from pydicom.valuerep import format_number_as_ds

    return format_number_as_ds(float(x))


def new_dataset(sop_class: str, modality: str, identity: DicomIdentity, series_uid: str):
    """A dataset with file meta, SOP, patient, study and series modules filled."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, ExplicitVRLittleEndian, generate_uid

    sop_uid = generate_uid()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    now = datetime.datetime.now()
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, sop_uid
    ds.Modality = modality
    ds.PatientName, ds.PatientID = identity.patient_name, identity.patient_id
    ds.StudyInstanceUID, ds.StudyID = identity.study_uid, identity.study_id
    ds.SeriesInstanceUID = series_uid
    if identity.frame_of_reference_uid:
        ds.FrameOfReferenceUID = identity.frame_of_reference_uid
    ds.StudyDate = ds.SeriesDate = ds.ContentDate = now.strftime("%Y%m%d")
    ds.StudyTime = ds.SeriesTime = ds.ContentTime = now.strftime("%H%M%S")
    ds.Manufacturer = "pelvicnav"
    ds.SeriesNumber = 1
    return ds


def save_dataset(ds, path: str | os.PathLike) -> Path:
    """Save a dataset atomically (temporary name, then rename)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    ds.save_as(tmp, enforce_file_format=True)
    os.replace(tmp, path)
    return path
