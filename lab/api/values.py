"""``/api/sessions/{id}/values/{name}``: read any state value as JSON, NPY, PNG or PLY; upload inputs.

Reading uses :mod:`lab.core.codecs`: ``json`` is the typed value's JSON (``{"type": "Points2D",
"xy": [...], ...}``; arrays as nested lists), ``npy`` the value's primary array, ``png`` images,
image sets (one view) and 2D arrays, ``ply`` point clouds and meshes. ``?index=N`` picks one view
of an image set, the points on view N, one camera, or row N of an array.

Uploading replaces a value some step reads, with the type that step declares
(:meth:`Pipeline.input_annotation`), and invalidates what was computed from the old one. The body
is the raw file or a multipart form with a file part: an image file for images and image sets
(``?append=true`` adds a view to an image set; several files in one form make a set), JSON or NPY
for arrays and typed values, PLY for point clouds and meshes.

Budgets (:mod:`lab.core.budgets`) keep one request bounded: a ``json`` answer holds at most
``MAX_JSON_NUMBERS`` numbers (a large array is read as ``npy`` or ``png``); an uploaded image is
refused from its header, before decoding, above ``MAX_IMAGE_PIXELS``, and one upload's images
together above ``MAX_DATASET_PIXELS`` (413); uploaded JSON nests at most ``MAX_JSON_DEPTH`` levels.
"""

from __future__ import annotations

import inspect
import io
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from lab.api.deps import SessionDep
from lab.api.errors import LabJSONResponse, error_responses
from lab.api.runs import check_idle
from lab.api.workers import MISDIRECTED
from lab.core import budgets, codecs
from lab.core.errors import InvalidValue, UnknownName
from lab.core.pipeline import Pipeline
from lab.core.step import type_name
from lab.core.values import Cameras, Image, ImageSet, Points2D, Segments2D

router = APIRouter(prefix="/api/sessions", tags=["values"], responses=error_responses(MISDIRECTED))

ValueName = Annotated[str, Path(description="State value name (GET /api/sessions/{id} lists them).")]

#: Shapes fixed by the conventions (DESIGN.md section 3) and the module contracts, by value name;
#: None is any length. Checked on upload when the value is an array.
KNOWN_SHAPES: dict[str, tuple[int | None, ...]] = {
    "K": (3, 3), "K_init": (3, 3), "dist": (5,), "dist_init": (5,),
    "homographies": (None, 3, 3), "board_points": (None, 3),
    "R_init": (None, 3, 3), "rotations": (None, 3, 3), "t_init": (None, 3), "translations": (None, 3),
    "F": (3, 3), "E": (3, 3), "H": (3, 3),
}
#: Values that are a pinhole camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]].
CAMERA_MATRICES = frozenset({"K", "K_init"})


def _shape_text(shape: tuple[int | None, ...]) -> str:
    comma = "," if len(shape) == 1 else ""
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + comma + ")"


def check_known_value(name: str, value: Any) -> None:
    """Extra checks where the contract knows more than the annotation (raise InvalidValue)."""
    if not isinstance(value, np.ndarray):
        return
    if value.dtype.kind not in "biuf":
        raise InvalidValue(name, f"must be a numeric array, got dtype {value.dtype}")
    if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
        raise InvalidValue(name, "contains NaN or infinite entries")
    shape = KNOWN_SHAPES.get(name)
    if shape is not None and (value.ndim != len(shape)
                              or any(s is not None and s != a  # strict: ndim was compared first
                                     for s, a in zip(shape, value.shape, strict=True))):
        raise InvalidValue(name, f"expected shape {_shape_text(shape)}, got {tuple(value.shape)}")
    if name in CAMERA_MATRICES:
        K = value.astype(np.float64)
        tolerance = 1e-6 * max(1.0, float(np.abs(K).max()))
        if abs(K[2, 2] - 1.0) > 1e-6:
            raise InvalidValue(name, f"a camera matrix has K[2, 2] = 1, got {K[2, 2]:g}")
        if max(abs(K[1, 0]), abs(K[2, 0]), abs(K[2, 1])) > tolerance:
            raise InvalidValue(name, "a camera matrix is upper triangular: K[1, 0], K[2, 0] and K[2, 1] "
                                     "must be 0")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InvalidValue(name, "focal lengths K[0, 0] and K[1, 1] must be positive, "
                                     f"got {K[0, 0]:g} and {K[1, 1]:g}")


def select_index(value: Any, index: int, name: str) -> Any:
    """One part of a value: a view of an image set, the points or segments on a view, a camera, a row."""
    def bounded(count: int) -> int:
        if not 0 <= index < count:
            raise InvalidValue("index", f"{name!r} has {count} entries; index must be in [0, {count - 1}]")
        return index

    if isinstance(value, ImageSet):
        return value[bounded(len(value))]
    if isinstance(value, (Points2D, Segments2D)):
        if value.view is None:
            raise InvalidValue("index", f"{name!r} is not split into views; leave out index")
        if isinstance(value, Points2D):
            return value.in_view(index)
        keep = value.view == index
        return Segments2D(value.start[keep], value.end[keep], value.view[keep],
                          None if value.colors is None else value.colors[keep], value.image)
    if isinstance(value, Cameras):
        i = bounded(len(value))
        part = slice(i, i + 1)
        return Cameras(value.K[part], value.R[part], value.t[part], value.width, value.height,
                       None if value.dist is None else value.dist[part], value.image,
                       None if value.views is None else value.views[part],
                       None if value.colors is None else value.colors[part])
    if isinstance(value, np.ndarray) and value.ndim >= 1:
        return value[bounded(len(value))]
    if isinstance(value, (list, tuple)):
        return value[bounded(len(value))]
    raise InvalidValue("index", f"{name!r} ({type(value).__name__}) has no parts to index; leave out index")


_SUFFIX_MEDIA = {"npy": "application/x-npy", "png": "image/png", "ply": "application/ply"}


@router.get("/{session_id}/values/{name}", summary="Read a state value",
            responses={200: {"content": {"application/json": {}, "image/png": {}, "application/x-npy": {},
                                         "application/ply": {}},
                             "description": "The value in the asked format."},
                       **error_responses({404: "Unknown session or value (the reason names the step that "
                                               "makes it).",
                                          422: "The value has no such format, a bad index, or more numbers "
                                               "than format=json may hold (read it as npy or png)."})},
            description="The value in `format`: `json` (the typed value's JSON, the same shape an upload "
                        "accepts), `npy` (its primary array: an image's pixels, points' xy, a cloud's xyz, "
                        "cameras' [R|t]), `png` (images, image sets and 2D arrays), `ply` (point clouds and "
                        "meshes). A `json` answer holds at most `lab.core.budgets.MAX_JSON_NUMBERS` numbers "
                        "(about a million); larger values are refused (422, field `format`) and read as "
                        "`npy` or `png`, or one view with `index`.")
async def read_value(session: SessionDep, name: ValueName,
                     format: Annotated[Literal["json", "npy", "png", "ply"],
                                       Query(description="Encoding.")] = "json",
                     index: Annotated[int | None,
                                      Query(ge=0, description="Pick one view / camera / row.")] = None
                     ) -> Response:
    value = session.get(name)
    if index is not None:
        value = select_index(value, index, name)
    if format == "json":
        codecs.check_json_answer(value, name=name)

        def render() -> bytes:
            try:
                return bytes(LabJSONResponse(codecs.to_json(value)).body)  # render() gives bytes
            except (TypeError, ValueError) as exc:
                raise InvalidValue("format", f"{name!r} ({type(value).__name__}) has no JSON form: "
                                             f"{exc}") from None

        return Response(await run_in_threadpool(render), media_type="application/json")
    payload = await run_in_threadpool(codecs.encode, value, format, name=name)
    suffix = f"_{index}" if index is not None else ""
    return Response(payload, media_type=_SUFFIX_MEDIA[format],
                    headers={"Content-Disposition": f'inline; filename="{name}{suffix}.{format}"'})


def _base_type(annotation: Any) -> Any:
    return codecs._base_type(annotation)


def uploadable_names(pipeline: Pipeline) -> list[str]:
    return sorted({inp.name for spec in pipeline.steps for inp in spec.inputs})


def _sniffed_name(payload: bytes) -> str:
    if payload[:6] == b"\x93NUMPY":
        return "upload.npy"
    if payload[:3] == b"ply" and payload[3:4] in (b"\n", b"\r"):
        return "upload.ply"
    return ""


async def _read_files(request: Request, filename: str | None) -> list[tuple[bytes, str, str]]:
    """``(payload, file name, content type)`` of each uploaded file (the body size is capped upstream)."""
    content_type = request.headers.get("content-type", "")
    if content_type.startswith("multipart/form-data"):
        try:
            form = await request.form(max_files=1000, max_fields=100)
        except StarletteHTTPException as exc:
            raise InvalidValue("file", f"malformed multipart body: {exc.detail}") from None
        try:
            files = [(await part.read(), part.filename or "", part.content_type or "")
                     for _, part in form.multi_items() if isinstance(part, UploadFile)]
        finally:
            await form.close()
        if not files:
            raise InvalidValue("file", "the multipart body has no file part (send the file as form field "
                                       "`file`)")
        for payload, name, _ in files:
            if not payload:
                raise InvalidValue("file", f"the uploaded file {name!r} is empty")
        return files
    payload = await request.body()
    if not payload:
        raise InvalidValue("body", "the upload is empty: send the file as the request body or a multipart "
                                   "form")
    return [(payload, filename or _sniffed_name(payload), content_type)]


def _check_image_pixels(files: list[tuple[bytes, str, str]], name: str) -> None:
    """Refuse, from the headers alone, an upload whose image files exceed the per-image or per-upload
    budget."""
    total = 0
    for payload, filename, content_type in files:
        if (filename or "").lower().endswith(".json") or "json" in (content_type or ""):
            continue  # JSON carries its pixels as text, which the body limit bounds
        width, height = codecs.check_image_header(io.BytesIO(payload), field=name,
                                                  what=repr(filename) if filename else "the upload")
        total += width * height
    budgets.check_upload_pixels(total, field=name)


def _decode(files: list[tuple[bytes, str, str]], annotation: Any, name: str) -> Any:
    cls = _base_type(annotation)
    if cls in (Image, ImageSet):
        _check_image_pixels(files, name)
    if cls is ImageSet:
        images = []
        for payload, filename, content_type in files:
            decoded = codecs.decode_upload(payload, filename=filename or _sniffed_name(payload),
                                           content_type=content_type, annotation=annotation, name=name)
            images.extend(decoded.images)
        return ImageSet(tuple(images))
    if len(files) != 1:
        raise InvalidValue("file", f"{name!r} takes one file, got {len(files)}")
    payload, filename, content_type = files[0]
    value = codecs.decode_upload(payload, filename=filename, content_type=content_type,
                                 annotation=annotation, name=name)
    if isinstance(cls, type) and cls is not inspect.Parameter.empty and not isinstance(value, cls):
        raise InvalidValue(name, f"{name!r} must be {cls.__name__}; the upload gave {type(value).__name__}")
    return value


@router.put("/{session_id}/values/{name}", summary="Upload an input value",
            responses=error_responses({404: "Unknown session, or a value no step of the module reads.",
                                       409: "A step is running.",
                                       413: "The body is over the upload limit, or an image has more pixels "
                                            "than the budget (read from its header, before decoding).",
                                       422: "Wrong type, shape or dtype, not an image, malformed "
                                            "JSON/NPY/PLY."}),
            openapi_extra={"requestBody": {"required": True, "content": {
                "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
                "image/png": {"schema": {"type": "string", "format": "binary"}},
                "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
                "application/json": {"schema": {}},
                "multipart/form-data": {"schema": {"type": "object", "properties": {
                    "file": {"type": "string", "format": "binary"}}}}}}},
            description="Replace a value that some step reads (its expected type is listed under "
                        "`uploadable` in GET /api/modules/{module}): an image file for an Image or ImageSet "
                        "(`?append=true` adds a view to an ImageSet), JSON or NPY for arrays and typed "
                        "values (the JSON that format=json returns), PLY for point clouds and meshes. Steps "
                        "downstream of it are invalidated; the answer lists them. Replacing a value that "
                        "comes from the dataset (no step makes it, e.g. the photos) drops the dataset's "
                        "ground truth, which no longer describes the data. On any error the session is "
                        "unchanged.")
async def upload_value(request: Request, session: SessionDep, name: ValueName,
                       append: Annotated[bool, Query(description="Add the image(s) as new views of an "
                                                                 "ImageSet.")] = False,
                       filename: Annotated[str | None, Query(description="File name of a raw-body upload "
                                                                         "(names the view; its suffix picks "
                                                                         "the decoder).")] = None
                       ) -> LabJSONResponse:
    pipeline = session.pipeline
    readers = [spec.name for spec in pipeline.steps if name in spec.reads]
    if not readers:
        known = name in session.state or pipeline.producer(name) is not None
        reason = (f"no step reads {name!r}, so it cannot be uploaded" if known else
                  f"module {pipeline.name!r} has no value {name!r}")
        raise UnknownName("value", f"{reason}; uploadable values are {uploadable_names(pipeline)}")
    annotation = pipeline.input_annotation(name)
    if append and _base_type(annotation) is not ImageSet:
        raise InvalidValue("append", "only image sets take ?append=true; "
                                     f"{name!r} is {type_name(annotation)}")
    check_idle(session, request.app.state.runs.monitor(session))
    files = await _read_files(request, filename)
    value = await run_in_threadpool(_decode, files, annotation, name)
    check_known_value(name, value)
    if append and isinstance(session.state.get(name), ImageSet):
        value = ImageSet(session.state[name].images + value.images)
    invalidated = session.put(name, value)
    if pipeline.producer(name) is None and session.truth:
        # A dataset value (the photos, the board) was replaced: the dataset's ground truth no
        # longer describes the state, and evaluating against it would compare unrelated things.
        session.truth = {}
    request.app.state.store.check_memory()
    shape = list(value.shape) if isinstance(value, np.ndarray) else None
    return LabJSONResponse({"session": session.id, "name": name, "type": type(value).__name__, "shape": shape,
                            "count": len(value) if isinstance(value, ImageSet) else None,
                            "read_by": readers, "invalidated": invalidated, "steps": session.step_status(),
                            "has_truth": bool(session.truth), "version": session.version})
