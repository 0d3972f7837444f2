"""Garment assets at runtime: the catalog, the MakeHuman binding, the retargeting baseline.

Each garment lives in ``assets/garments/<id>/`` (built by ``python -m training.assets.build_garments``):
``garment.json`` (metadata, material in SI units) and ``garment.npz`` (float32/int32 arrays):

- ``vertices`` (V, 3) metres, Z-up: the template T_c-bar on the neutral body in rest pose
  (thesis eq. 4.2), collision-free; ``rest_vertices`` (V, 3): the rest geometry for the cloth
  material (the same surface: the undeformed state whose edge lengths and angles are "rest").
- ``faces`` (F, 3), ``edges`` (E, 2) (sorted unique), ``uvs`` (Vt, 2), ``face_uvs`` (F, 3).
- ``binding_indices`` (V, K) into the hm08 body, ``binding_weights`` (V, K) (padding: weight 0),
  ``binding_offsets`` (V, 3) in ``.mhclo`` offset units along hm08 axes, ``scale_refs`` (3, 3):
  per hm08 axis x, y, z the row (a, b, s) (a, b: hm08 vertex ids stored as exact floats, s in
  MakeHuman decimetres). See ``bind_garment``.
- ``template_correction`` (V, 3) metres: T_c-bar - bind(neutral body).
- ``skin_weights`` (V, 31) W_c, rows sum to 1 (thesis eq. 4.3), bones in the body's order.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inference.body import ASSETS_DIR
from inference.errors import InputShapeError, UnknownAssetError

HM08_VERTEX_COUNT = 19158
CATEGORIES = ("top", "bottom", "dress", "outer")


def srgb_to_linear(hex_colour: str) -> list[float]:
    """'#rrggbb' sRGB -> linear RGB in [0, 1] (IEC 61966-2-1 transfer function)."""
    c = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)], np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).tolist()


def pbr_appearance(entry: dict) -> dict:
    """A garment.json "appearance" (``training.assets.appearance``) -> the glTF PBR values of
    ``inference.export.GarmentTrack.appearance``: linear base colour, roughness, and a sheen of
    the base colour lightened toward white by ``sheen_lighten``."""
    base = np.asarray(srgb_to_linear(entry["color_srgb"]))
    out = {"base_color": base.tolist(), "roughness": float(entry.get("roughness", 0.8))}
    if "sheen_lighten" in entry:
        out["sheen_color"] = (base + float(entry["sheen_lighten"]) * (1.0 - base)).tolist()
        out["sheen_roughness"] = float(entry.get("sheen_roughness", 0.5))
    return out
# hm08 axis n (x, y, z; Y-up) is anny axis HM08_AXIS_IN_ANNY[n]; anny = 0.1 * (x, -z, y).
HM08_AXIS_IN_ANNY = (0, 2, 1)


def bind_garment(
    hm08_vertices: np.ndarray,
    indices: np.ndarray,
    weights: np.ndarray,
    offsets: np.ndarray,
    scale_refs: np.ndarray,
) -> np.ndarray:
    """Place garment vertices on bodies through their MakeHuman ``.mhclo`` binding.

    MakeHuman proxy fitting (``proxy.py``), generalised to K reference vertices:
    x_v = sum_k w_vk B[i_vk] + A (o_v * s),  s_n = |B[a_n] - B[b_n]|_(axis n) / s_n(ref),
    with the offset o_v along hm08 axes and A the hm08 -> anny axis map (x, y, z) -> (x, -z, y).
    In anny metres the factor 0.1 of the unit change cancels between B and the offset.

    hm08_vertices : (B, 19158, 3) float32, metres, anny axes (``BodyModel.hm08_vertices``)
    indices       : (V, K) int32 into hm08 ; weights : (V, K) float32, rows sum to 1
    offsets       : (V, 3) float32, offset units, hm08 axes
    scale_refs    : (3, 3) float32, rows (a, b, s) for hm08 axes x, y, z
    returns       : (B, V, 3) float32, metres
    """
    H = np.asarray(hm08_vertices, np.float32)
    if H.ndim != 3 or H.shape[1:] != (HM08_VERTEX_COUNT, 3):
        raise InputShapeError("hm08_vertices", f"(B, {HM08_VERTEX_COUNT}, 3)", H.shape)
    a = scale_refs[:, 0].astype(np.int64)
    b = scale_refs[:, 1].astype(np.int64)
    axis = np.array(HM08_AXIS_IN_ANNY)
    # scale[b, n] = |H[b, a_n, axis_n] - H[b, b_n, axis_n]| / s_n   (metres per offset unit)
    scale = np.abs(H[:, a, axis] - H[:, b, axis]) / scale_refs[:, 2].astype(np.float32)
    u = offsets[None] * scale[:, None, :]  # (B, V, 3) hm08 axes, metres
    offset_anny = np.stack([u[..., 0], -u[..., 2], u[..., 1]], axis=-1)
    # x[b, v] = sum_k w[v, k] H[b, i[v, k]]
    return (np.einsum("vk,bvkc->bvc", weights, H[:, indices], optimize=True) + offset_anny).astype(np.float32)


@dataclass(frozen=True)
class GarmentAsset:
    """One catalog garment (see the module docstring for the arrays' meaning, shapes and units)."""

    id: str
    name: str
    category: str
    layer: int
    material: dict
    metadata: dict
    vertices: np.ndarray
    rest_vertices: np.ndarray
    faces: np.ndarray
    edges: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    binding_indices: np.ndarray
    binding_weights: np.ndarray
    binding_offsets: np.ndarray
    scale_refs: np.ndarray
    template_correction: np.ndarray
    skin_weights: np.ndarray
    directory: Path = field(default=Path("."))

    @property
    def template(self) -> np.ndarray:
        """(V, 3) float32 metres: the template T_c-bar (alias of ``vertices``)."""
        return self.vertices

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    @property
    def appearance(self) -> dict | None:
        """glTF PBR values of the garment's look (``pbr_appearance``), None when garment.json has none."""
        entry = self.metadata.get("appearance")
        return pbr_appearance(entry) if entry else None

    @classmethod
    def load(cls, directory: Path | str) -> "GarmentAsset":
        """Read ``directory/garment.json`` and ``directory/garment.npz``."""
        directory = Path(directory)
        meta = json.loads((directory / "garment.json").read_text())
        with np.load(directory / "garment.npz", allow_pickle=False) as f:
            a = dict(f)
        V = len(a["vertices"])
        for key, shape in (
            ("vertices", (V, 3)), ("rest_vertices", (V, 3)), ("binding_offsets", (V, 3)),
            ("template_correction", (V, 3)), ("scale_refs", (3, 3)),
        ):
            if a[key].shape != shape:
                raise ValueError(f"{directory.name}/garment.npz: {key} has shape {a[key].shape}, expected {shape}")
        if meta["category"] not in CATEGORIES:
            raise ValueError(f"{directory.name}: category {meta['category']!r} not in {CATEGORIES}")
        return cls(
            id=meta["id"],
            name=meta["name"],
            category=meta["category"],
            layer=int(meta["layer"]),
            material=dict(meta["material"]),
            metadata=meta,
            vertices=a["vertices"],
            rest_vertices=a["rest_vertices"],
            faces=a["faces"],
            edges=a["edges"],
            uvs=a["uvs"],
            face_uvs=a["face_uvs"],
            binding_indices=a["binding_indices"],
            binding_weights=a["binding_weights"],
            binding_offsets=a["binding_offsets"],
            scale_refs=a["scale_refs"],
            template_correction=a["template_correction"],
            skin_weights=a["skin_weights"],
            directory=directory,
        )

    def bind(self, hm08_vertices: np.ndarray) -> np.ndarray:
        """The raw ``.mhclo`` placement on bodies (B, 19158, 3) -> (B, V, 3) float32 metres.

        On non-neutral bodies it may intersect the skin (MakeHuman garments are modelled for
        a body with the covered skin deleted): use ``retarget_fit``.
        """
        return bind_garment(hm08_vertices, self.binding_indices, self.binding_weights, self.binding_offsets, self.scale_refs)

    def retarget_fit(self, hm08_vertices: np.ndarray) -> np.ndarray:
        """Retargeting baseline (thesis fig. 4.6): bind + template correction, (B, V, 3) float32 metres.

        Equals the template on the neutral body; follows the body's shape elsewhere.
        """
        return self.bind(hm08_vertices) + self.template_correction[None]

    def summary(self) -> dict:
        """JSON-friendly description for catalog listings."""
        m = self.metadata
        return {
            "id": self.id,
            "name": self.name,
            "category": self.category,
            "layer": self.layer,
            "vertices": int(len(self.vertices)),
            "faces": int(len(self.faces)),
            "material": dict(self.material),
            "source": m.get("source", ""),
            "licence": m.get("licence", ""),
        }


def catalog_ids(assets_dir: Path | str = ASSETS_DIR) -> list[str]:
    """The catalog's garment ids without loading the garments: the folders
    ``assets_dir/garments/<id>/`` that hold a ``garment.json``, sorted."""
    return sorted(p.parent.name for p in (Path(assets_dir) / "garments").glob("*/garment.json"))


class GarmentCatalog:
    """All garments under ``<assets_dir>/garments/<id>/``, loaded once (a few MB)."""

    def __init__(self, garments: dict[str, GarmentAsset]):
        self._garments = dict(sorted(garments.items()))

    @classmethod
    def load(cls, assets_dir: Path | str = ASSETS_DIR) -> "GarmentCatalog":
        """Load every ``assets_dir/garments/*/garment.json`` garment (``assets_dir`` defaults to the repo's ``assets``)."""
        garments = {}
        for folder_id in catalog_ids(assets_dir):
            g = GarmentAsset.load(Path(assets_dir) / "garments" / folder_id)
            if g.id != folder_id:
                raise ValueError(f"{g.directory / 'garment.json'}: id {g.id!r} differs from its folder name")
            garments[g.id] = g
        return cls(garments)

    def ids(self) -> list[str]:
        """Garment ids, sorted."""
        return list(self._garments)

    def get(self, garment_id: str) -> GarmentAsset:
        """The garment with this id; ``UnknownAssetError`` if the catalog has none."""
        try:
            return self._garments[garment_id]
        except KeyError:
            raise UnknownAssetError("garment", f"unknown garment id {garment_id!r}; known ids: {', '.join(self._garments)}") from None

    def __contains__(self, garment_id: object) -> bool:
        return garment_id in self._garments

    def __len__(self) -> int:
        return len(self._garments)

    def list(self) -> list[dict]:
        """Summaries of all garments (``GarmentAsset.summary``), sorted by id."""
        return [g.summary() for g in self._garments.values()]
