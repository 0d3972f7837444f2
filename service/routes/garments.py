"""Garment catalog: list and detail (each with the garment's default method), template glb."""
from __future__ import annotations

from fastapi import APIRouter, Path, Request
from fastapi.responses import FileResponse

from service.errors import ProblemException
from service.schemas import BINARY as _BINARY, ID_PATTERN, DefaultMethodResponse, GarmentDetail, GarmentListResponse, GarmentSummary

router = APIRouter(prefix="/v1/garments", tags=["garments"])
_NOT_FOUND = {404: {"description": "unknown garment", "content": {"application/problem+json": {}}}}


def _summary(request: Request, g) -> dict:
    default = request.app.state.runtime.defaults.get(g.id)
    return dict(
        id=g.id, name=g.name, category=g.category, layer=int(g.layer), vertices=int(len(g.template)),
        faces=int(len(g.faces)), template_url=f"/v1/garments/{g.id}/template.glb",
        default_method=DefaultMethodResponse(**default.as_dict()),
    )


def _get(request: Request, garment_id: str):
    catalog = request.app.state.runtime.catalog
    if garment_id not in catalog.ids():
        raise ProblemException(404, "Not found", f"no garment {garment_id!r}; see GET /v1/garments")
    return catalog.get(garment_id)


# default_method.beyond_range is left out where a garment has none (absent: the field's description)
@router.get("", response_model=GarmentListResponse, response_model_exclude_none=True)
def list_garments(request: Request) -> GarmentListResponse:
    catalog = request.app.state.runtime.catalog
    return GarmentListResponse(garments=[GarmentSummary(**_summary(request, catalog.get(i))) for i in catalog.ids()])


@router.get("/{garment_id}", response_model=GarmentDetail, response_model_exclude_none=True, responses=_NOT_FOUND)
def get_garment(request: Request, garment_id: str = Path(pattern=ID_PATTERN)) -> GarmentDetail:
    g = _get(request, garment_id)
    return GarmentDetail(
        **_summary(request, g),
        material={k: float(v) for k, v in g.material.items()},
        source=str(g.metadata.get("source", "")),
        licence=str(g.metadata.get("licence", "")),
    )


@router.get(
    "/{garment_id}/template.glb",
    response_class=FileResponse,
    responses={200: {"content": {"model/gltf-binary": _BINARY}, "description": "the garment template on the neutral body, Y-up metres"}, **_NOT_FOUND},
)
def get_garment_template(request: Request, garment_id: str = Path(pattern=ID_PATTERN)):
    g = _get(request, garment_id)
    return FileResponse(g.directory / "template.glb", media_type="model/gltf-binary")
