"""``/api/modules``: the teaching modules, their steps, controls (JSON Schema) and datasets."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path

from lab.api.deps import CatalogDep
from lab.api.errors import LabJSONResponse, ModuleUnavailable, error_responses
from lab.core.pipeline import Pipeline
from lab.core.step import type_name

router = APIRouter(prefix="/api/modules", tags=["modules"],
                   responses=error_responses({404: "Unknown module.", 503: "The module failed to load."}))


def module_overview(pipeline: Pipeline) -> dict[str, Any]:
    """A module in brief, for listings: its steps in order and its datasets."""
    return {
        "name": pipeline.name, "title": pipeline.title, "summary": pipeline.summary, "available": True,
        "steps": [{"name": s.name, "title": s.title, "summary": s.summary, "long": s.is_generator}
                  for s in pipeline.steps],
        "datasets": [{"name": d.name, "summary": d.summary, "takes_path": d.takes_path}
                     for d in pipeline.datasets],
    }


def uploadable_values(pipeline: Pipeline) -> list[dict[str, Any]]:
    """State values a client may upload (every value some step reads), with their type."""
    found: dict[str, dict[str, Any]] = {}
    for spec in pipeline.steps:
        for inp in spec.inputs:
            entry = found.setdefault(inp.name, {
                "name": inp.name, "type": type_name(pipeline.input_annotation(inp.name)),
                "produced_by": getattr(pipeline.producer(inp.name), "name", None), "read_by": []})
            entry["read_by"].append(spec.name)
    return list(found.values())


@router.get("", summary="List the modules",
            description="Every teaching module in listing order, with its steps and datasets. A module that "
                        "fails to load is listed with `available: false` and the reason.")
def list_modules(catalog: CatalogDep) -> LabJSONResponse:
    listed = []
    for name in catalog.names:
        try:
            listed.append(module_overview(catalog.get(name)))
        except ModuleUnavailable as exc:
            listed.append({"name": name, "title": name.replace("_", " ").capitalize(), "summary": "",
                           "available": False, "reason": exc.reason, "steps": [], "datasets": []})
    return LabJSONResponse(listed)


@router.get("/{module}", summary="Describe one module",
            description="The module's steps in order (inputs, controls as a JSON Schema of the request body "
                        "of `POST /api/sessions/{id}/steps/{step}`, outputs, metrics, whether the step is "
                        "long and streams progress), its datasets with the JSON Schema of their options, and "
                        "the values a client may upload.")
def describe_module(catalog: CatalogDep,
                    module: Annotated[str, Path(description="Module name, e.g. `calibration`.")]
                    ) -> LabJSONResponse:
    pipeline = catalog.get(module)
    described = pipeline.describe()
    described["evaluated_steps"] = sorted(pipeline.evaluations)
    described["uploadable"] = uploadable_values(pipeline)
    return LabJSONResponse(described)
