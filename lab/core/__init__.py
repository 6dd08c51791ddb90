"""The core every front end builds on: steps, pipelines, sessions, the store and value codecs."""

from lab.core.errors import (Cancelled, CapacityExceeded, Forbidden, InvalidControl, InvalidValue, LabError, MissingInput,
                             SessionBusy, StepFailed, UnknownName)
from lab.core.pipeline import DatasetSpec, Export, Loaded, Pipeline, Plan, RunRecord, Session, open_session
from lab.core.step import Control, Progress, Range, StepSpec, Warnings, describe_step, metric, step_result
from lab.core.store import SessionStore
from lab.core.values import (Cameras, Curve, GaussianSplats, Image, ImageSet, Mesh, PointCloud, Points2D,
                             Segments2D, Segments3D)

__all__ = [
    "Cancelled", "CapacityExceeded", "Forbidden", "InvalidControl", "InvalidValue", "LabError", "MissingInput", "SessionBusy",
    "StepFailed", "UnknownName", "DatasetSpec", "Export", "Loaded", "Pipeline", "Plan", "RunRecord", "Session",
    "open_session", "Control", "Progress", "Range", "StepSpec", "Warnings", "describe_step", "metric", "step_result", "SessionStore", "Cameras", "Curve",
    "GaussianSplats", "Image", "ImageSet", "Mesh", "PointCloud", "Points2D", "Segments2D", "Segments3D",
]
