"""Request and response models (pydantic v2), layered by direction: ``XRequest`` / ``XResponse``."""
from __future__ import annotations

from typing import Annotated, Literal, Union

from annotated_types import Len
from pydantic import BaseModel, ConfigDict, Field, FiniteFloat

from inference.body import PHENOTYPE_RANGES
from inference.options import DrapeOptions  # the one options model (pipeline, jobs and contract)

ID_PATTERN = r"^[A-Za-z0-9_\-]{1,64}$"
BINARY = {"schema": {"type": "string", "format": "binary"}}  # a binary response body, so that generated clients keep the bytes
NUM_BONES = 31


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


def _phenotype(name: str, default: float, description: str):
    lo, hi = PHENOTYPE_RANGES[name]
    return Field(default, ge=lo, le=hi, allow_inf_nan=False, description=f"{description} [{lo}, {hi}]")


class Phenotypes(_Strict):
    """The 6 anny phenotypes (adults only: age 0.77 is 18 years, 1.0 is 110)."""

    gender: float = _phenotype("gender", 0.5, "0 male, 1 female")
    age: float = _phenotype("age", 0.8, "anny age; 0.77 = 18 y, 0.8 = ~41 y, 1.0 = 110 y")
    muscle: float = _phenotype("muscle", 0.5, "0 min, 1 max muscle")
    weight: float = _phenotype("weight", 0.5, "0 min, 1 max weight")
    height: float = _phenotype("height", 0.5, "0 min, 1 max height")
    proportions: float = _phenotype("proportions", 0.5, "0 ideal, 1 uncommon proportions")


class PhenotypeQuery(Phenotypes):
    """The phenotypes as query parameters (numbers parsed from the query string)."""

    model_config = ConfigDict(extra="forbid", strict=False)


class BodySpec(_Strict):
    phenotypes: Phenotypes = Field(default_factory=Phenotypes)


class ClipMotion(_Strict):
    """A bundled motion clip (see GET /v1/motions), retargeted to the requested body."""

    type: Literal["clip"] = Field(description="the motion's kind (the discriminator: required)")
    clip: str = Field(pattern=ID_PATTERN, examples=["walk"])
    start_s: float = Field(0.0, ge=0.0, le=3600.0, allow_inf_nan=False, description="start time in the clip, seconds")
    duration_s: float | None = Field(None, gt=0.0, le=3600.0, allow_inf_nan=False, description="seconds to drape (default: to the end, within max_frames)")
    in_place: bool = Field(True, description="remove the root's horizontal travel from the output (the body walks on the spot, "
                                             "so it stays in a viewer's frame); the garments move as on the travelling motion. "
                                             "Default true for bundled clips")


Vec3 = Annotated[list[FiniteFloat], Len(3, 3)]


class PoseMotion(_Strict):
    """An explicit pose sequence in the body model's pose contract (GET /v1/body-model)."""

    type: Literal["poses"] = Field(description="the motion's kind (the discriminator: required)")
    fps: float = Field(30.0, gt=0.0, le=240.0, allow_inf_nan=False)
    rotations: Annotated[list[Annotated[list[Vec3], Len(NUM_BONES, NUM_BONES)]], Len(1, 20_000)] = Field(
        description="(T, 31, 3) axis-angle per bone, radians, relative to the bone's rest orientation in its rest frame"
    )
    translation: Annotated[list[Vec3], Len(1, 20_000)] = Field(description="(T, 3) root displacement from rest, metres, Z-up")
    in_place: bool = Field(False, description="remove the root's horizontal travel from the output (see ClipMotion); default false: "
                                              "the motion as given")


class BvhMotion(_Strict):
    """A BVH file (CMU MotionBuilder, CMU 3ds Max or Mixamo joint names), retargeted onto the body."""

    type: Literal["bvh"] = Field(description="the motion's kind (the discriminator: required)")
    bvh: str = Field(min_length=1, max_length=4 * 1024 * 1024, description="the BVH text")
    units: Literal["auto", "metres", "centimetres", "inches", "cmu"] = Field("auto", description="BVH length unit")
    in_place: bool = Field(False, description="remove the root's horizontal travel from the output (see ClipMotion); default false: "
                                              "the motion as given")


class AsfAmcMotion(_Strict):
    """A CMU-style ASF skeleton and AMC motion (the CMU mocap database's native format), retargeted onto the body."""

    type: Literal["asf_amc"] = Field(description="the motion's kind (the discriminator: required)")
    asf: str = Field(min_length=1, max_length=1024 * 1024, description="the ASF text (skeleton)")
    amc: str = Field(min_length=1, max_length=4 * 1024 * 1024, description="the AMC text (motion); with the ASF within the BVH text limit")
    fps: float = Field(120.0, gt=0.0, le=480.0, allow_inf_nan=False, description="the AMC's frame rate (AMC files do not say; CMU: 120)")
    units: Literal["auto", "metres", "centimetres", "inches", "cmu"] = Field("auto", description="ASF length unit; auto: the ASF's own")
    in_place: bool = Field(False, description="remove the root's horizontal travel from the output (see ClipMotion); default false: "
                                              "the motion as given")


Motion = Annotated[Union[ClipMotion, PoseMotion, BvhMotion, AsfAmcMotion], Field(discriminator="type")]


class GarmentSpec(_Strict):
    id: str = Field(pattern=ID_PATTERN, examples=["tshirt"])


class DrapeRequest(_Strict):
    body: BodySpec = Field(default_factory=BodySpec)
    motion: Motion
    garments: Annotated[list[GarmentSpec], Len(1, 8)] = Field(
        description="garments, innermost first: the layer order, as listed (a shirt listed before trousers is tucked into them; "
                    "after them, it hangs over them). A garment's catalog layer is its usual place, not enforced")
    format: Literal["glb", "npz"] = "glb"
    options: DrapeOptions = Field(default_factory=DrapeOptions)


DRAPE_EXAMPLE = {
    "body": {"phenotypes": {"gender": 0.5, "age": 0.8, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5}},
    "motion": {"type": "clip", "clip": "walk", "duration_s": 2.0},
    "garments": [{"id": "tshirt"}],
    "format": "glb",
    "options": {"fps": 30, "include_body": True},
}


# ------------------------------------------------------------------ responses
class BeyondRangeResponse(BaseModel):
    """The default's method on bodies beyond its learned canonical model's body range."""

    fit: Literal["canonical", "learned-canonical", "learned", "retarget"]
    dynamics: Literal["learned", "none"]
    reason: str = Field(description="why, in one sentence")


class DefaultMethodResponse(BaseModel):
    """What a drape runs for this garment when its options name no fit or dynamics. In a request
    that layers several garments, a fit 'learned-canonical' here (or in ``beyond_range``) runs fit
    'canonical' with dynamics 'none' instead (the layers share the static form's grading)."""

    fit: Literal["canonical", "learned-canonical", "learned", "retarget"]
    dynamics: Literal["learned", "none"]
    reason: str = Field(description="why this method is the garment's default, in one sentence")
    evidence: str = Field(description="where the measurements behind it are")
    beyond_range: BeyondRangeResponse | None = Field(
        None, description="fit 'canonical' with dynamics 'learned' runs on bodies within a body range of the ones its model was "
        "trained on (model_versions names what ran); beyond it, this method (absent: fit 'canonical', dynamics 'none')")


class GarmentSummary(BaseModel):
    id: str
    name: str
    category: str
    layer: int = Field(description="its usual place in an outfit (0 innermost): a client's default order; a drape keeps the "
                                   "request's order")
    vertices: int
    faces: int
    template_url: str
    default_method: DefaultMethodResponse = Field(description="the fit and dynamics a drape runs for this garment when "
                                                              "options.fit / options.dynamics are omitted")


class GarmentDetail(GarmentSummary):
    material: dict[str, float]
    source: str
    licence: str


class GarmentListResponse(BaseModel):
    garments: list[GarmentSummary]


class MotionSummary(BaseModel):
    id: str
    title: str
    frames: int
    fps: float
    duration_s: float
    test_only: bool
    description: str


class MotionListResponse(BaseModel):
    motions: list[MotionSummary]
    acknowledgement: str


class PhenotypeInfo(BaseModel):
    name: str
    min: float
    max: float
    default: float


class BodyModelResponse(BaseModel):
    name: str
    units: str
    axes: str
    bones: list[str]
    parents: list[int]
    rest_bone_heads: list[list[float]] = Field(description="(31, 3) neutral body bone heads, metres")
    rest_bone_tails: list[list[float]] = Field(description="(31, 3) neutral body bone tails, metres")
    phenotypes: list[PhenotypeInfo]
    pose_format: str
    vertices: int
    faces: int


def _tape(name: str, lo: float, hi: float, iso: str, example: float):
    return Field(ge=lo, le=hi, allow_inf_nan=False, examples=[example], description=f"{iso}, centimetres [{lo:g}, {hi:g}]")


class BodyFitRequest(_Strict):
    """Tape measurements of a shopper (ISO 8559-1 definitions; ``GET /v1/bodies/measurements``
    says how the service takes them on its bodies)."""

    height_cm: float = _tape("height", 100, 250, "stature: crown to floor", 175)
    chest_cm: float = _tape("chest", 50, 200, "chest girth under the armpits, over the fullest part of the chest", 98)
    waist_cm: float = _tape("waist", 40, 200, "waist girth at the natural (narrowest) waist", 84)
    hips_cm: float = _tape("hips", 50, 200, "hip girth at the fullest part of the buttocks", 102)
    inseam_cm: float = _tape("inseam", 40, 130, "inside leg length: crotch to floor", 80)
    weight_kg: float | None = Field(None, ge=25, le=250, allow_inf_nan=False, examples=[75],
                                    description="body mass, kilograms [25, 250] (optional: fitted when given)")
    gender: Literal["female", "male"] | None = Field(None, description="optional: keeps the gender phenotype on its half "
                                                                          "(male 0-0.5, female 0.5-1); without it the fit may choose any")
    tolerance_cm: float = Field(1.0, ge=0.2, le=10.0, allow_inf_nan=False,
                                description="a measurement the closest adult body misses by more is a 422 naming it (the weight's "
                                            "tolerance is the same number in kg)")


class BodyMeasurements(BaseModel):
    """What a body measures (ISO 8559-1, taken on the rest body: see ``standard``)."""

    height_cm: float
    chest_cm: float
    waist_cm: float
    hips_cm: float
    inseam_cm: float
    weight_kg: float = Field(description="mesh volume x the whole-body density (985 kg/m^3)")


class BodyMeasurementResiduals(BaseModel):
    """Fitted minus asked, per measurement (centimetres; kilograms for the weight, null when not asked)."""

    height_cm: float
    chest_cm: float
    waist_cm: float
    hips_cm: float
    inseam_cm: float
    weight_kg: float | None = None


class BodyMeasurementsResponse(BaseModel):
    phenotypes: Phenotypes
    measurements: BodyMeasurements
    standard: str = Field(description="how each measurement is taken on the mesh")


class BodyFitResponse(BaseModel):
    """The adult body that has the asked measurements: use ``phenotypes`` as a drape request's
    ``body.phenotypes``."""

    phenotypes: Phenotypes
    measurements: BodyMeasurements = Field(description="what the fitted body measures")
    residuals: BodyMeasurementResiduals
    tolerance_cm: float = Field(description="every residual is within this (else the answer is a 422 naming the measurement)")
    tolerance_kg: float
    standard: str


class HealthResponse(BaseModel):
    status: str


class ReadyResponse(BaseModel):
    status: str
    garments: int
    motions: int
    workers: list["ReadyWorker"] = Field(default_factory=list)
    queue_depth: int = 0
    jobs_backend: str = "off"


class ProblemFieldError(BaseModel):
    """One invalid field: ``pointer`` into the request body, or ``parameter`` (with ``in``)."""

    pointer: str | None = Field(None, description="RFC 6901 JSON pointer into the request document (/motion/clip, /garments/0/id; '' the whole document)")
    parameter: str | None = Field(None, description="the path, query or header parameter, by name")
    in_: Literal["path", "query", "header", "cookie"] | None = Field(None, alias="in", description="where ``parameter`` is")
    detail: str
    type: str | None = None


class Problem(BaseModel):
    """RFC 9457 problem details."""

    type: str = "about:blank"
    title: str
    status: int
    detail: str
    instance: str | None = None
    errors: list[ProblemFieldError] | None = None


class JobProgress(BaseModel):
    frames_done: int
    frames_total: int | None = Field(None, description="known once the motion is imported")
    fraction: float = Field(description="frames_done / frames_total (0 while unknown)")


class JobResponse(BaseModel):
    """An asynchronous drape (POST /v1/jobs): its state, progress, and where its result is."""

    id: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    format: Literal["glb", "npz"]
    progress: JobProgress
    created_at: float = Field(description="unix time, seconds")
    finished_at: float | None = None
    expires_at: float | None = Field(None, description="unix time after which the job and its result are deleted")
    result_url: str | None = Field(None, description="GET it for the output (state succeeded)")
    result_bytes: int | None = None
    error: Problem | None = Field(None, description="why the job failed")


class ReadyWorker(BaseModel):
    index: int
    pid: int | None
    alive: bool
