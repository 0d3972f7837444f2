"""GET /v1/body-model: what a client needs to build poses for the body model."""
from __future__ import annotations

from fastapi import APIRouter, Request

from inference.body import NEUTRAL_PHENOTYPES, PHENOTYPE_LABELS, PHENOTYPE_RANGES
from service.schemas import BodyModelResponse, PhenotypeInfo

router = APIRouter(prefix="/v1", tags=["body"])

POSE_FORMAT = (
    "rotations: (T, 31, 3) axis-angle in radians, one per bone in `bones` order: the bone's rotation relative "
    "to its rest orientation, expressed in the bone's own rest frame (Blender convention, local +Y from head to "
    "tail); world pose W_j = W_parent (P_parent^-1 P_j) R(rot_j) with P the rest bone frames. The root (Hips) "
    "rest frame is the identity, so its rotation is in world axes. translation: (T, 3) the root's displacement "
    "from its rest head position, metres, world axes (Z-up, the body faces -Y). All zeros = the rest A-pose."
)


@router.get("/body-model", response_model=BodyModelResponse)
def get_body_model(request: Request) -> BodyModelResponse:
    runtime = request.app.state.runtime
    body = runtime.body
    neutral = runtime.neutral_shape
    return BodyModelResponse(
        name="anny 0.6.2, rig cmu_mb, topology anny",
        units="metres, seconds, radians",
        axes="Z-up, right-handed; the body faces -Y (glb output is converted to Y-up)",
        bones=body.bone_names,
        parents=[int(p) for p in body.parents],
        rest_bone_heads=neutral.bone_heads[0].round(6).tolist(),
        rest_bone_tails=neutral.bone_tails[0].round(6).tolist(),
        phenotypes=[
            PhenotypeInfo(name=n, min=PHENOTYPE_RANGES[n][0], max=PHENOTYPE_RANGES[n][1], default=float(NEUTRAL_PHENOTYPES[i]))
            for i, n in enumerate(PHENOTYPE_LABELS)
        ],
        pose_format=POSE_FORMAT,
        vertices=body.num_vertices,
        faces=len(body.faces),
    )
