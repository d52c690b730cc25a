"""The embedded pelvis model: shape, pose and planning models fitted from the Han 2019 atlas."""

from pelvicnav.model.file import (
    MODEL_ENV,
    ModelFileError,
    build_model_file,
    load_model,
    resolve_model_path,
    save_model,
)
from pelvicnav.model.pelvis import OBSERVED_SETS, PelvisModel, build_model

__all__ = [
    "MODEL_ENV",
    "OBSERVED_SETS",
    "ModelFileError",
    "PelvisModel",
    "build_model",
    "build_model_file",
    "load_model",
    "resolve_model_path",
    "save_model",
]
