"""The look of each catalog garment (``garment.json`` "appearance") and its ``template.glb``.

    python -m training.assets.appearance [--garments assets/garments]

Appearance: MakeHuman's ``.mhmat`` gives the cloth's shininess (0-1) and names a diffuse
texture, but the CC0 release ships no textures and its diffuse colour is white (the texture's
multiplier). So the colour is the catalog's own (``COLOURS``, sRGB), the roughness is
1 - shininess (0.196 -> 0.80: matte cotton), and every garment gets a sheen (glTF
``KHR_materials_sheen``: the grazing-angle highlight of fibres) of its own colour lightened by
``SHEEN_LIGHTEN``. ``inference.garment.GarmentAsset.appearance`` turns it into linear PBR values.

template.glb: the template mesh T_c-bar, Y-up, standing on the floor (lifted by the neutral
body's sole height), with smooth normals and the garment's material, written by the same
``inference.export.write_glb`` as the service's drapes (so it renders as they do).
Rerunning it changes only ``appearance`` in garment.json and template.glb (the geometry is
``training.assets.build_garments``'s, which calls the same functions).
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.export import GarmentTrack, write_glb
from inference.garment import GarmentAsset, pbr_appearance

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SOURCES = REPO / "training" / "sources" / "makehuman"
GARMENTS_DIR = REPO / "assets" / "garments"
COLOURS = {  # sRGB, chosen per garment (the sources' textures are not part of the CC0 release)
    "tshirt": "#a8323a",  # red
    "longsleeve": "#5b6b82",  # heather blue-grey
    "trousers": "#2f3e5c",  # dark denim
    "dress": "#1f6f73",  # deep teal
    "jacket": "#5c6338",  # olive field jacket
    "crewtee": "#d9c9a3",  # oatmeal
    "leggings": "#2b2b30",  # charcoal
    "shorts": "#c2a878",  # khaki
    "croptop": "#d8707e",  # rose
    "shirt": "#e6e2d6",  # off-white
    "suittrousers": "#3a3a42",  # suit grey
}
SHEEN_LIGHTEN = 0.3
SHEEN_ROUGHNESS = 0.5


def read_mhmat(path: Path) -> dict[str, str]:
    """``key value`` lines of a MakeHuman material file (comments and blank lines skipped)."""
    out: dict[str, str] = {}
    for line in Path(path).read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, _, value = line.partition(" ")
            out.setdefault(key, value.strip())
    return out


def garment_appearance(garment_id: str, outfit: str) -> dict:
    """The "appearance" entry of a garment.json, from its outfit's .mhmat and ``COLOURS``."""
    mat = read_mhmat(SOURCES / outfit / f"{outfit}.mhmat")
    shininess = float(mat.get("shininess", "0.2"))
    return {
        "color_srgb": COLOURS[garment_id],
        "roughness": round(1.0 - shininess, 3),
        "sheen_lighten": SHEEN_LIGHTEN,
        "sheen_roughness": SHEEN_ROUGHNESS,
        "source": f"{outfit}.mhmat: shininess {shininess:g} -> roughness 1 - shininess; its diffuse texture "
                  f"{mat.get('diffuseTexture', '(none)')} is not in the CC0 release, so the colour is the catalog's",
    }


def template_glb(asset: GarmentAsset, floor_z: float) -> bytes:
    """The template mesh as a one-frame glb on the floor (no body), with the garment's material."""
    track = GarmentTrack(asset.id, asset.template[None], asset.faces, asset.uvs, asset.face_uvs,
                         {"id": asset.id, "layer": asset.layer, "category": asset.category}, appearance=asset.appearance)
    # float positions (one frame: quantization would save little, and every glTF reader takes floats)
    return write_glb([track], None, quantize=False, floor_z=floor_z, metadata={"garment": asset.id, "template": True})


def neutral_floor_z(body: BodyModel) -> float:
    """Height of the neutral body's soles in the rest pose (Z-up metres)."""
    return float(body.shape(NEUTRAL_PHENOTYPES[None]).rest_vertices[0, :, 2].min())


def update(garment_dir: Path, floor_z: float) -> None:
    """Write ``appearance`` into garment.json and rewrite template.glb."""
    meta_path = garment_dir / "garment.json"
    meta = json.loads(meta_path.read_text())
    meta["appearance"] = garment_appearance(meta["id"], meta["source_outfit"])
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    asset = GarmentAsset.load(garment_dir)
    (garment_dir / "template.glb").write_bytes(template_glb(asset, floor_z))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--garments", type=Path, default=GARMENTS_DIR)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    floor_z = neutral_floor_z(BodyModel.load())
    for meta_path in sorted(args.garments.glob("*/garment.json")):
        update(meta_path.parent, floor_z)
        appearance = pbr_appearance(json.loads(meta_path.read_text())["appearance"])
        log.info("%-10s base colour (linear) %s, roughness %.2f", meta_path.parent.name,
                 np.round(appearance["base_color"], 3).tolist(), appearance["roughness"])


if __name__ == "__main__":
    main()
