"""Export the anny body model (rig cmu_mb) to ``assets/body/`` as plain float32 arrays.

Run: ``python -m training.assets.build_body``

Writes
- ``assets/body/body.npz``: the skin mesh (topology ``anny``, 13,718 vertices): template,
  phenotype blendshapes (anny's compact basis), the phenotype -> coefficient mapping, bone
  heads/tails/rolls and their blendshapes, skinning weights, parents, faces, UVs.
- ``assets/body/hm08_helpers.npz``: the MakeHuman hm08 vertices that ``anny`` drops but
  ``.mhclo`` garment bindings refer to (from topology ``anny-full``), with that topology's
  own compact blendshapes and phenotype projection.
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from training.assets.anny_model import REPO_ROOT, load_anny

log = logging.getLogger(__name__)

# anny's phenotype machinery (anny.models.model_data / phenotype), mirrored in inference/body.py.
FEATURE_ORDER = ["age", "gender", "muscle", "weight", "height", "proportions", "cupsize", "firmness"]


def _np(t) -> np.ndarray:
    return t.detach().cpu().numpy()


def phenotype_tables(model) -> dict[str, np.ndarray]:
    """The arrays that map the 6 exposed phenotypes to blendshape coefficients."""
    from anny.models.model_data import PHENOTYPE_VARIATIONS

    variation_names = [v for vs in PHENOTYPE_VARIATIONS.values() for v in vs]
    variation_feature = [k for k, vs in PHENOTYPE_VARIATIONS.items() for _ in vs]
    anchors = {k: _np(model.anchors[k]) for k in FEATURE_ORDER}
    # anchors padded into one (8, 5) table with a count per feature
    anchor_table = np.full((len(FEATURE_ORDER), 5), np.nan)
    anchor_count = np.zeros(len(FEATURE_ORDER), np.int32)
    for i, k in enumerate(FEATURE_ORDER):
        anchor_table[i, : len(anchors[k])] = anchors[k]
        anchor_count[i] = len(anchors[k])
    return dict(
        phenotype_labels=np.array(model.phenotype_labels),
        feature_order=np.array(FEATURE_ORDER),
        feature_anchors=anchor_table.astype(np.float64),
        feature_anchor_count=anchor_count,
        variation_names=np.array(variation_names),
        variation_feature=np.array(variation_feature),
        phenotype_mask=_np(model.stacked_phenotype_blend_shapes_mask).astype(np.float32),
        phenotype_projection=_np(model.phenotype_blendshape_projection).astype(np.float64),
    )


def body_arrays(model) -> dict[str, np.ndarray]:
    """The skin-mesh arrays of the anny model (topology ``anny``)."""
    faces = _np(model.faces).astype(np.int32)
    return dict(
        template_vertices=_np(model.template_vertices).astype(np.float32),
        blendshapes=_np(model.blendshapes).astype(np.float32),
        faces=faces,
        uvs=_np(model.texture_coordinates).astype(np.float32),
        face_uvs=_np(model.face_texture_coordinate_indices).astype(np.int32),
        skin_indices=_np(model.vertex_bone_indices).astype(np.int32),
        skin_weights=_np(model.vertex_bone_weights).astype(np.float32),
        bone_names=np.array(model.bone_labels),
        parents=np.array(model.bone_parents, np.int32),
        template_bone_heads=_np(model.template_bone_heads).astype(np.float32),
        bone_heads_blendshapes=_np(model.bone_heads_blendshapes).astype(np.float32),
        template_bone_tails=_np(model.template_bone_tails).astype(np.float32),
        bone_tails_blendshapes=_np(model.bone_tails_blendshapes).astype(np.float32),
        bone_rolls=_np(model.bone_rolls_rotmat[0]).astype(np.float32),
        hm08_index=_np(model.base_mesh_vertex_indices).astype(np.int32),
    )


def helper_arrays(model, full) -> dict[str, np.ndarray]:
    """hm08 helper vertices of ``anny-full`` that ``anny`` drops, with ``anny-full``'s own
    compact blendshapes and projection (its basis differs from the skin's: the skin basis
    reproduces the helpers only to ~6 mm, measured, so the helpers keep theirs)."""
    in_skin = np.zeros(full.template_vertices.shape[0], bool)
    in_skin[_np(model.base_mesh_vertex_indices)] = True
    helper_ids = np.flatnonzero(~in_skin)
    if not np.array_equal(_np(full.stacked_phenotype_blend_shapes_mask), _np(model.stacked_phenotype_blend_shapes_mask)):
        raise RuntimeError("anny and anny-full disagree on the phenotype variation mask")
    return dict(
        helper_ids=helper_ids.astype(np.int32),
        helper_template=_np(full.template_vertices[helper_ids]).astype(np.float32),
        helper_blendshapes=_np(full.blendshapes[:, helper_ids]).astype(np.float32),
        helper_projection=_np(full.phenotype_blendshape_projection).astype(np.float64),
        hm08_vertex_count=np.int32(full.template_vertices.shape[0]),
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "assets" / "body")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")

    model = load_anny("anny")
    full = load_anny("anny-full")
    args.out.mkdir(parents=True, exist_ok=True)
    arrays = {**body_arrays(model), **phenotype_tables(model)}
    np.savez(args.out / "body.npz", **arrays)
    helpers = helper_arrays(model, full)
    np.savez(args.out / "hm08_helpers.npz", **helpers)
    info = {
        "source": "anny 0.6.2 (Apache-2.0 code, CC0 data), rig cmu_mb, topology anny (+ anny-full helpers)",
        "vertices": int(arrays["template_vertices"].shape[0]),
        "blendshapes": int(arrays["blendshapes"].shape[0]),
        "bones": int(len(arrays["bone_names"])),
        "hm08_helpers": int(len(helpers["helper_ids"])),
    }
    (args.out / "body.json").write_text(json.dumps(info, indent=2) + "\n")
    log.info("wrote %s", info)


if __name__ == "__main__":
    main()
