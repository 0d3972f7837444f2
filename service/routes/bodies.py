"""Bodies from tape measurements (POST /v1/bodies/fit) and the measurements of any body
(GET /v1/bodies/measurements), ISO 8559-1 definitions (``inference.measurements``)."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Query, Request

from service.schemas import BodyFitRequest, BodyFitResponse, BodyMeasurementsResponse, Phenotypes, PhenotypeQuery

router = APIRouter(prefix="/v1/bodies", tags=["body"])
_BUSY = {503: {"description": "the queue is full (Retry-After)", "content": {"application/problem+json": {}}},
         504: {"description": "not done within the deadline", "content": {"application/problem+json": {}}}}

_EXAMPLES = {
    "shopper": {"summary": "a shopper's tape measurements", "value": {
        "height_cm": 168, "chest_cm": 92, "waist_cm": 76, "hips_cm": 102, "inseam_cm": 78, "weight_kg": 63, "gender": "female"}},
    "measurements_only": {"summary": "the five measurements alone", "value": {
        "height_cm": 180, "chest_cm": 100, "waist_cm": 86, "hips_cm": 101, "inseam_cm": 86}},
    "looser": {"summary": "accept the closest body within 2 cm", "value": {
        "height_cm": 180, "chest_cm": 100, "waist_cm": 86, "hips_cm": 101, "inseam_cm": 84, "tolerance_cm": 2}},
}


@router.post("/fit", response_model=BodyFitResponse, responses={
    422: {"description": "invalid, or outside the adult body space: ``errors`` names each measurement no adult body "
                         "with the others reaches, and what the closest body has", "content": {"application/problem+json": {}}},
    **_BUSY})
async def fit_body(request: Request, measurements: Annotated[BodyFitRequest, Body(openapi_examples=_EXAMPLES)]) -> BodyFitResponse:
    """The adult body (phenotypes) that has these tape measurements, each within ``tolerance_cm`` (default 1 cm; kg for the weight)."""
    return await request.app.state.pool.body("fit", measurements)


@router.get("/measurements", response_model=BodyMeasurementsResponse, responses=_BUSY)
async def measure_body(request: Request, phenotypes: Annotated[PhenotypeQuery, Query()]) -> BodyMeasurementsResponse:
    """What the body with these phenotypes measures (query parameters; omitted ones take their default)."""
    return await request.app.state.pool.body("measure", Phenotypes(**phenotypes.model_dump()))
