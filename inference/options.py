"""The options of a drape: one model for the pipeline, the jobs and the HTTP contract
(``service.schemas.DrapeRequest.options`` is this class).

``collisions`` is the one choice of collision handling after skinning, each level adding a stage:

    off    nothing: the skinned garments as they are
    push   the guard's push out of the body along the nearest body vertex's normal, layer by
           layer (``inference.guard``); an outfit's layer stage after it (``inference.layers``:
           each inner garment under the ones outside it)
    check  push, then every nearby vertex checked against the closest body triangle and moved
           out where it is still inside (up to ~4x fewer vertices left inside; ~3-4 ms per
           garment-frame)
    exact  check, then every vertex tested against the posed body with the exact winding number
           and moved, where it is still inside, to the nearest outside skin point
           (``inference.repair``; ~7 ms per garment-frame): no vertex is inside the body

The three booleans of API 0.2 (``guard``, ``guard_check``, ``guard_exact``) are still read on input
and mapped to a level (``guard: false`` -> off; else ``guard_exact`` -> exact, ``guard_check``
-> check, neither -> push); the model itself only holds ``collisions``.
"""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from inference.guard import DEFAULT_LAYER_GAP_M, DEFAULT_MARGIN_M

Collisions = Literal["off", "push", "check", "exact"]
LEGACY_COLLISION_FLAGS = ("guard", "guard_check", "guard_exact")


def collisions_from_flags(guard: bool = True, guard_check: bool = True, guard_exact: bool = True) -> Collisions:
    """The level of the API 0.2 booleans (push + repair without the check is not a level: exact)."""
    if not guard:
        return "off"
    return "exact" if guard_exact else "check" if guard_check else "push"


class DrapeOptions(BaseModel):
    """What a drape runs, and (``fps``, ``include_body``, ``normals``, ``compression``) what its output holds."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    fps: float = Field(30.0, ge=1.0, le=120.0, allow_inf_nan=False, description="output frame rate")
    include_body: bool = Field(True, description="add the posed body to the output")
    normals: bool = Field(True, description="glb: smooth per-frame vertex normals for the garments (quantized, +4 bytes per "
                                            "vertex per frame) and the body; false: players shade flat (smaller file)")
    compression: Literal["none", "meshopt"] = Field(
        "none", description="glb: 'meshopt' encodes the buffers with EXT_meshopt_compression (decoded by three.js with "
        "MeshoptDecoder, model-viewer, Babylon.js; not by Blender 3.x): about half the size (README example: 5.3 to 2.8 MB), "
        "'none' (default) plays in every glTF reader")
    fit: Literal["canonical", "learned-canonical", "learned", "retarget", "none"] | None = Field(
        None,
        description="garment fit to the body shape, for every garment of the request: 'canonical' = the garment in the "
        "canonical space of thesis ch. 6, shaped and skinned by the diffused body model (skinning weights and shape offsets "
        "read at the garment's own points; collisions: the final exact stage alone); 'learned-canonical' = the garment "
        "of 'learned', skinned and collision-handled as 'canonical' (weights read at the canonical template); 'learned' = "
        "the .mhclo retarget + the fit regressor R_G (ONNX, trained self-supervised on the SNUG physics energies); 'retarget' = the .mhclo "
        "retarget baseline; 'none' = plain LBS of the neutral template. Null or omitted (default): each garment's own "
        "default fit, the method chosen for it on the validation protocol (GET /v1/garments/{id}, default_method)",
    )
    dynamics: Literal["learned", "none"] | None = Field(
        None,
        description="dynamic wrinkles, for every garment of the request: 'learned' = the wrinkle GRU R_L over the motion "
        "descriptor (eq. 6.17); 'none' = static fit. Null or omitted (default): each garment's own default dynamics "
        "(GET /v1/garments/{id}, default_method)",
    )
    collisions: Collisions = Field(
        "exact",
        description="collision handling after skinning, each level adding a stage: 'off' none; 'push' the guard's push out "
        "of the body along the nearest body vertex's normal, layer by layer (an outfit of several garments then has each "
        "inner garment sink under the ones outside it); 'check' the push, then each nearby vertex "
        "checked against the closest body triangle (up to ~4x fewer vertices left inside, ~3-4 ms per garment-frame; "
        "not in an outfit whose garments all run fit 'canonical', where the final stage follows at every level but 'off'); "
        "'exact' (default) the check, then the exact winding-number test of every vertex against the posed body, moving "
        "any still inside to the nearest outside skin point (~7 ms per garment-frame): no vertex inside the body. "
        "(API 0.2's guard / guard_check / guard_exact booleans are still accepted and mapped to a level.)",
    )
    margin_m: float = Field(DEFAULT_MARGIN_M, ge=0.0, le=0.02, allow_inf_nan=False, description="guard margin to the body, metres")
    layer_gap_m: float = Field(DEFAULT_LAYER_GAP_M, ge=0.0, le=0.02, allow_inf_nan=False, description="extra margin per garment layer, metres")
    lift_arms: bool = Field(
        True,
        description="abduct the upper arms about the shoulder, per frame, where the body shape sinks them into the torso "
        "(a clip retargeted onto a heavier body); the returned body follows the corrected pose. false: the pose as given",
    )

    @model_validator(mode="before")
    @classmethod
    def _legacy_flags(cls, data):
        if isinstance(data, dict) and any(k in data for k in LEGACY_COLLISION_FLAGS):
            data = dict(data)
            flags = {k: data.pop(k) for k in LEGACY_COLLISION_FLAGS if k in data}
            if not all(isinstance(v, bool) for v in flags.values()):
                raise ValueError(f"{', '.join(flags)} must be booleans (or use collisions)")
            level = collisions_from_flags(**flags)
            if "collisions" in data and data["collisions"] != level:
                raise ValueError(f"collisions {data['collisions']!r} contradicts {flags} (= {level!r}); send collisions alone")
            data["collisions"] = level
        return data

    @property
    def guard(self) -> bool:
        """The guard's push runs."""
        return self.collisions != "off"

    @property
    def guard_check(self) -> bool:
        """The closest-triangle check runs after the push."""
        return self.collisions in ("check", "exact")

    @property
    def guard_exact(self) -> bool:
        """The exact winding-number repair runs last."""
        return self.collisions == "exact"

    def replace(self, **changes) -> "DrapeOptions":
        """A copy with ``changes`` (validated; the API 0.2 flags are read too, relative to this
        copy's level: ``replace(guard=False)`` is collisions 'off')."""
        data = self.model_dump()
        if any(k in changes for k in LEGACY_COLLISION_FLAGS):
            flags = {"guard": self.guard, "guard_check": self.guard_check, "guard_exact": self.guard_exact}
            flags.update({k: changes.pop(k) for k in LEGACY_COLLISION_FLAGS if k in changes})
            data.pop("collisions")
            data.update(flags)
        return type(self).model_validate({**data, **changes})

    def pipeline_key(self) -> tuple:
        """What the pipeline reads besides the per-garment methods (``fit`` and ``dynamics``
        resolve into those, ``inference.defaults.resolve_methods``): drapes with equal keys and
        equal methods may share one call. Not the output options ``fps``, ``include_body``,
        ``normals`` and ``compression``."""
        return (self.collisions, self.margin_m, self.layer_gap_m, self.lift_arms)
