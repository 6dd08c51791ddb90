"""The core every front end builds on: steps, pipelines, the planner, sessions, the store and value codecs."""

from lab.core.errors import (Cancelled, CapacityExceeded, Forbidden, InvalidControl, InvalidValue, LabError,
                             MissingInput, SessionBusy, StepFailed, UnknownName)
from lab.core.pipeline import DatasetSpec, Export, Loaded, Pipeline, Plan, RunRecord, Session, open_session
from lab.core.step import Control, Progress, Range, StepSpec, Warnings, describe_step, metric, step_result
from lab.core.store import SessionStore
from lab.core.values import (Cameras, Curve, GaussianSplats, Image, ImageSet, Mesh, PointCloud, Points2D,
                             Segments2D, Segments3D)

__all__ = [
    "Cameras", "Cancelled", "CapacityExceeded", "Control", "Curve", "DatasetSpec", "Export", "Forbidden",
    "GaussianSplats", "Image", "ImageSet", "InvalidControl", "InvalidValue", "LabError", "Loaded", "Mesh",
    "MissingInput", "Pipeline", "Plan", "PointCloud", "Points2D", "Progress", "Range", "RunRecord",
    "Segments2D", "Segments3D", "Session", "SessionBusy", "SessionStore", "StepFailed", "StepSpec",
    "UnknownName", "Warnings", "describe_step", "metric", "open_session", "step_result",
]
