"""Build the garment catalog ``assets/garments/<id>/`` from the CC0 MakeHuman outfits.

    python -m training.assets.build_garments [--out assets/garments] [--only tshirt,dress]

Per garment (DESIGN.md section 3, thesis ch. 4.2.1 and 4.3.1):
1. cut the garment's connected components out of its outfit (``training/sources/makehuman``),
   triangulate (shorter quad diagonal), weld, collapse sliver edges, orient consistently and
   outward; dress: drop the blouse's folded collar, weld its button placket, trim the skirt
   under the blouse hem and stitch the two; subdivide 1-to-4 to a few thousand vertices. The
   ``.mhclo`` binding follows every step exactly (``garments_mesh``);
2. bind it on the neutral anny body and relax it out of the skin to a margin: the collision-free
   template T_c-bar; store the correction T_c-bar - bind(neutral) (``garments_fit.relax_template``);
3. skinning weights W_c from the closest body triangle, finger/toe bones folded into the
   hand/foot, weights < 0.1 % dropped; dress skirt: diffused over the cloth (no tear between legs);
4. write ``garment.npz`` (float32/int32), ``garment.json`` and ``template.glb`` (Y-up), and log
   inside rates (neutral before/after, retargeted on the two extreme adult shapes) and layer order.
Deterministic: same sources and body asset -> byte-identical files.
"""
from __future__ import annotations

import argparse
import io
import json
import logging
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from inference.body import ASSETS_DIR, NEUTRAL_PHENOTYPES, BodyModel
from inference.garment import bind_garment
from inference.mesh import vertex_normals
from training.assets import appearance
from training.assets import garments_fit as fit
from training.assets import garments_mesh as gm

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SOURCES = REPO / "training" / "sources" / "makehuman"
OUT_DIR = ASSETS_DIR / "garments"
BUILD_COMMAND = "python -m training.assets.build_garments"
MH_UNIT_M = 0.1  # MakeHuman unit (decimetre) in metres
WELD_TOL_MH = 1e-5  # vertices closer than this (MakeHuman units) are one vertex
MIN_EDGE_M = 0.003  # shorter edges of the bound garment (before the 1-to-4 split) are collapsed
# The two extreme adult shapes on which the retargeted garments are checked (reported only).
EXTREME_PHENOTYPES = np.array([[0.0, 0.77, 0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]], np.float32)

# Finger and toe bones: their garment weights go to the hand / foot (fit.fold_into_parents).
FOLDED_BONES = ("LThumb", "LeftFingerBase", "LeftHandFinger1", "RThumb", "RightFingerBase", "RightHandFinger1",
                "LeftToeBase", "RightToeBase")
# Skinning weights below this are dropped (rows renormalised): no visible effect, smaller files.
MIN_SKIN_WEIGHT = 1e-3
# Depth along the inward garment normal of the point whose closest body triangle gives W_c, metres.
SKIN_PROBE_DEPTH_M = 0.015

# SNUG material (thesis ch. 5.3.1), SI units.
MATERIAL = {
    "density_kg_m3": 426.0,
    "thickness_m": 0.47e-3,
    "lame_lambda_pa": 4.44e4,
    "lame_mu_pa": 2.36e4,
    "k_bend": 3.96e-5,
    "k_collision": 250.0,
}


@dataclass(frozen=True)
class GarmentSpec:
    """How one catalog garment is made.

    components         : connected components of the outfit (``garments_mesh.quad_components``
                         labels), checked against ``component_vertices``
    subdivide_pieces   : which of those pieces get the 1-to-4 split
    template_margin_m  : clearance of the template from the neutral body (build time)
    collision_margin_m : collision margin of the cloth model (physics, runtime)
    """

    id: str
    name: str
    category: str
    layer: int
    outfit: str
    components: tuple[int, ...]
    component_vertices: tuple[int, ...]
    subdivide_pieces: tuple[int, ...]
    template_margin_m: float
    collision_margin_m: float
    description: str


GARMENTS = (
    GarmentSpec("tshirt", "T-shirt", "top", 1, "female_casualsuit01", (0,), (1311,), (0,), 0.004, 0.003,
                "Short-sleeved T-shirt (the top of female_casualsuit01; its leggings are left out)."),
    GarmentSpec("longsleeve", "Long-sleeve top", "top", 1, "male_casualsuit02", (1,), (1250,), (0,), 0.004, 0.003,
                "Long-sleeved crew-neck top (the top of male_casualsuit02)."),
    GarmentSpec("trousers", "Trousers", "bottom", 0, "male_casualsuit02", (0,), (886,), (0,), 0.004, 0.003,
                "Straight trousers (the bottom of male_casualsuit02)."),
    GarmentSpec("dress", "Dress", "dress", 1, "female_elegantsuit01", (1, 0), (1810, 395), (0, 1), 0.004, 0.003,
                "Long-sleeved dress: the blouse of female_elegantsuit01 (folded collar removed, button "
                "placket closed) stitched at its hem to the outfit's skirt (back vent kept)."),
    GarmentSpec("crewtee", "Crew-neck tee", "top", 1, "male_casualsuit04", (0,), (810,), (0,), 0.004, 0.003,
                "Fitted short-sleeved crew-neck tee (the top of male_casualsuit04; its trousers are left out)."),
    GarmentSpec("leggings", "Leggings", "bottom", 0, "female_casualsuit01", (1,), (886,), (0,), 0.004, 0.003,
                "Ankle-length leggings (the bottom of female_casualsuit01)."),
    GarmentSpec("shorts", "Shorts", "bottom", 0, "female_casualsuit02", (0,), (1320,), (0,), 0.004, 0.003,
                "Short shorts (the bottom of female_casualsuit02; its top is the T-shirt's mesh again)."),
    GarmentSpec("croptop", "Crop top", "top", 1, "female_sportsuit01", (0,), (911,), (0,), 0.004, 0.003,
                "Sports crop top (the top of female_sportsuit01; its leggings are the catalog's leggings)."),
    GarmentSpec("shirt", "Shirt", "top", 1, "male_casualsuit06", (0,), (2822,), (), 0.004, 0.003,
                "Short-sleeved collared shirt (the top of male_casualsuit06; its trousers are left out)."),
    GarmentSpec("suittrousers", "Suit trousers", "bottom", 0, "male_elegantsuit01", (0,), (1357,), (0,), 0.004, 0.003,
                "Suit trousers (the bottom of male_elegantsuit01; its suit jacket is left out)."),
    GarmentSpec("jacket", "Jacket", "outer", 2, "male_casualsuit05", (1,), (1659,), (0,), 0.014, 0.008,
                "Open-front field jacket with pockets (the jacket of male_casualsuit05; its collar, "
                "shirt front and trousers are left out). Outer layer: worn over a top."),
)
# Dress surgery (metres, on the neutral body): placket vertex pairs closer than this are welded,
# up to this height (the V-neck opens above it).
PLACKET_WELD_M = 0.012
PLACKET_TOP_Z_M = 0.62
# The stitched waist: positions within this many edges of the seam are smoothed this many steps.
SEAM_SMOOTH_HOPS = 3
SEAM_SMOOTH_STEPS = 10
# Skirt weights: diffused below the top of the skirt piece, over this height ramp.
SKIRT_RAMP_M = 0.12
SKIRT_DIFFUSION_ITERATIONS = 60


# ---------------------------------------------------------------------------- body
@dataclass(frozen=True)
class NeutralBody:
    """The neutral body in rest pose: hm08 vertices (1, 19158, 3), skin (Vb, 3), faces, weights (Vb, J), rig."""

    hm08: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray
    skin_faces: np.ndarray  # largest component only (no eyes), for projections
    weights: np.ndarray
    bone_names: list[str]
    parents: np.ndarray


def neutral_body(body: BodyModel) -> NeutralBody:
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    v = shape.rest_vertices[0].astype(np.float64)
    return NeutralBody(
        body.hm08_vertices(shape),
        v,
        body.faces.astype(np.int64),
        fit.largest_component_faces(body.faces.astype(np.int64), len(v)),
        body.dense_weights,
        body.bone_names,
        body.parents,
    )


def outward_directions(points: np.ndarray, nb: NeutralBody) -> np.ndarray:
    """(N, 3) direction from the closest skin point to each point (flipped for inside points)."""
    _, _, c = fit.closest_points(points, nb.vertices, nb.skin_faces)
    inside = fit.body_inside_mask(points, nb.vertices, nb.faces)
    d = points - c
    return np.where(inside[:, None], -d, d)


# ---------------------------------------------------------------------------- dress surgery
def remove_collar(mesh: gm.GarmentMesh) -> gm.GarmentMesh:
    """Drop the blouse's folded-over collar (piece 0): the faces outside its largest consistently
    wound patch. The collar lies folded on the blouse, two cloth layers in contact that a cloth
    model without self-collision cannot keep apart; the neckline stays as modelled."""
    patch = gm.orientation_patches(mesh.faces)
    blouse = mesh.piece[mesh.faces[:, 0]] == 0
    main = np.argmax(np.bincount(patch[blouse]))
    return gm.remove_faces(mesh, ~blouse | (patch == main))


def close_placket(mesh: gm.GarmentMesh, pos: np.ndarray) -> gm.GarmentMesh:
    """Weld the blouse's overlapping button-placket edges (piece 0) into a seam below the V-neck."""
    loop = max((l for l in gm.boundary_loops(mesh.faces) if mesh.piece[l[0]] == 0), key=len)
    p = pos[loop]
    n = len(loop)
    cand = np.flatnonzero((p[:, 2] < PLACKET_TOP_Z_M) & (np.abs(p[:, 0]) < 0.05) & (p[:, 1] < -0.05))
    d = np.linalg.norm(p[cand, None] - p[None, cand], axis=2)
    sep = np.abs(cand[:, None] - cand[None, :])
    d[np.minimum(sep, n - sep) < 6] = np.inf  # only pairs from the two opposite flaps
    nn = np.argmin(d, axis=1)
    groups = np.arange(mesh.n_vertices)
    pairs = 0
    for i, j in enumerate(nn):
        if nn[j] == i and i < j and d[i, j] < PLACKET_WELD_M:
            groups[loop[cand[j]]] = loop[cand[i]]
            pairs += 1
    if pairs < 5:
        raise ValueError(f"close_placket: only {pairs} vertex pairs found")
    log.info("dress: placket closed with %d welded vertex pairs", pairs)
    return gm.merge_vertices(mesh, groups)


def trim_skirt_under_hem(mesh: gm.GarmentMesh, pos: np.ndarray, centre: np.ndarray) -> gm.GarmentMesh:
    """Remove the skirt (piece 1) faces that reach above the blouse hem (hidden under it)."""
    hem = min((l for l in gm.boundary_loops(mesh.faces) if mesh.piece[l[0]] == 0), key=lambda l: pos[l, 2].mean())
    az_h = np.arctan2(pos[hem, 1] - centre[1], pos[hem, 0] - centre[0])
    order = np.argsort(az_h)
    az_h, z_h = az_h[order], pos[hem, 2][order]
    az_h = np.concatenate([az_h - 2 * np.pi, az_h, az_h + 2 * np.pi])
    z_h = np.tile(z_h, 3)
    az = np.arctan2(pos[:, 1] - centre[1], pos[:, 0] - centre[0])
    hem_z = np.interp(az, az_h, z_h)
    above = (pos[:, 2] > hem_z - 0.005) & (mesh.piece == 1)
    keep = ~above[mesh.faces].any(1)
    return gm.remove_faces(mesh, keep)


def stitch_skirt(mesh: gm.GarmentMesh, pos: np.ndarray, centre: np.ndarray) -> gm.GarmentMesh:
    """Bridge the blouse hem loop (piece 0, lowest) to the skirt's top loop (piece 1, highest)."""
    loops = gm.boundary_loops(mesh.faces)
    hem = min((l for l in loops if mesh.piece[l[0]] == 0), key=lambda l: pos[l, 2].mean())
    top = max((l for l in loops if mesh.piece[l[0]] == 1), key=lambda l: pos[l, 2].mean())
    return gm.bridge_loops(mesh, hem, top, pos, centre)


def smooth_seam(mesh: gm.GarmentMesh, pos: np.ndarray) -> np.ndarray:
    """Taubin-smooth the positions (V, 3) within ``SEAM_SMOOTH_HOPS`` edges of the blouse-skirt seam
    (the bridge faces, whose corners come from both pieces), so the stitched waist is not a step."""
    f_piece = mesh.piece[mesh.faces]
    seam = np.unique(mesh.faces[f_piece.min(1) != f_piece.max(1)])
    band = gm.graph_distance_from(mesh.faces, mesh.n_vertices, seam) <= SEAM_SMOOTH_HOPS
    L = fit.uniform_laplacian(mesh.faces, mesh.n_vertices)
    return fit.taubin_smooth(pos, L, SEAM_SMOOTH_STEPS, mask=band)


# ---------------------------------------------------------------------------- build
def build_mesh(spec: GarmentSpec, outfit: gm.OutfitSource, nb: NeutralBody) -> tuple[gm.GarmentMesh, np.ndarray]:
    """Clean triangle mesh of one garment and the outfit's source positions on the neutral body (Vs, 3)."""
    src_idx, src_w, src_off = gm.binding_arrays(
        gm.GarmentMesh(np.zeros((0, 3), np.int64), np.zeros((0, 2)), np.zeros((0, 3), np.int64),
                       sp.identity(len(outfit.vertices), format="csr"), np.zeros(len(outfit.vertices), np.int64)),
        outfit,
    )
    src_pos = bind_garment(nb.hm08, src_idx, src_w, src_off, outfit.scale_refs.astype(np.float32))[0].astype(np.float64)
    mesh = gm.select_components(outfit, spec.components, spec.component_vertices)
    mesh = gm.weld_duplicates(mesh, mesh.positions(outfit.vertices), WELD_TOL_MH)
    mesh = gm.collapse_short_edges(mesh, mesh.positions(src_pos), MIN_EDGE_M)
    if spec.id == "dress":
        mesh = remove_collar(mesh)
    mesh = gm.orient_consistently(mesh)
    if spec.id == "dress":
        centre = mesh.positions(src_pos)[mesh.piece == 1, :2].mean(0)
        mesh = close_placket(mesh, mesh.positions(src_pos))
        mesh = trim_skirt_under_hem(mesh, mesh.positions(src_pos), centre)
    for piece in spec.subdivide_pieces:
        mesh = gm.subdivide(mesh, mesh.piece[mesh.faces[:, 0]] == piece)
    if spec.id == "dress":
        mesh = stitch_skirt(mesh, mesh.positions(src_pos), centre)
        mesh = gm.orient_consistently(mesh)
    pos = mesh.positions(src_pos)
    mesh = gm.orient_outward(mesh, pos, outward_directions(pos, nb))
    return mesh, src_pos


def inside_fraction(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray) -> float:
    return float(fit.body_inside_mask(points, body_vertices, body_faces).mean())


def build_garment(spec: GarmentSpec, body: BodyModel, nb: NeutralBody, out_dir: Path) -> dict:
    """Build one garment into ``out_dir/<id>/`` and return its build report."""
    t0 = time.perf_counter()
    outfit = gm.load_outfit(SOURCES / spec.outfit)
    mesh, src_pos = build_mesh(spec, outfit, nb)
    idx, w, off = gm.binding_arrays(mesh, outfit)
    scale_refs = outfit.scale_refs.astype(np.float32)
    bound = bind_garment(nb.hm08, idx, w, off, scale_refs)[0].astype(np.float64)
    err = np.abs(bound - mesh.positions(src_pos)).max()
    if err > 1e-5:
        raise AssertionError(f"{spec.id}: sparse binding differs from the source map by {err} m")

    start = smooth_seam(mesh, bound) if spec.category == "dress" else bound
    template, report = fit.relax_template(start, mesh.faces, nb.vertices, nb.faces, spec.template_margin_m)
    correction = (template - bound).astype(np.float32)

    # Weights of the body surface the garment faces: project from a point SKIN_PROBE_DEPTH_M
    # inside the garment along its inward normal. The plain closest triangle of a vertex on the
    # chest side of the armpit is often the arm's (A-pose); skinned to the arm, it sinks into the
    # torso when the arm comes down (seen on the test clip 01_01: ~2 % of T-shirt vertices).
    normals = vertex_normals(template[None].astype(np.float32), mesh.faces)[0].astype(np.float64)
    skin = fit.project_skin_weights(template - SKIN_PROBE_DEPTH_M * normals, nb.vertices, nb.skin_faces, nb.weights)
    fold = [nb.bone_names.index(n) for n in FOLDED_BONES]
    skin = fit.fold_into_parents(skin, nb.parents, np.array(fold))
    if spec.category == "dress":
        skirt = mesh.piece == 1
        top = float(template[skirt, 2].max())
        skin = fit.smooth_skirt_weights(skin, mesh.faces, template[:, 2], skirt | (template[:, 2] < top), top,
                                        SKIRT_RAMP_M, SKIRT_DIFFUSION_ITERATIONS)

    skin = np.where(skin < MIN_SKIN_WEIGHT, 0.0, skin)
    skin /= skin.sum(1, keepdims=True)

    # retargeting baseline on the extreme adult shapes (reported; the runtime guard handles it)
    ext = body.shape(EXTREME_PHENOTYPES)
    ext_fit = bind_garment(body.hm08_vertices(ext), idx, w, off, scale_refs) + correction[None]
    ext_raw = bind_garment(body.hm08_vertices(ext), idx, w, off, scale_refs)
    for k, name in enumerate(("min", "max")):
        bv = ext.rest_vertices[k].astype(np.float64)
        report[f"extreme_{name}_inside_bind"] = inside_fraction(ext_raw[k], bv, nb.faces)
        report[f"extreme_{name}_inside_retarget"] = inside_fraction(ext_fit[k], bv, nb.faces)

    edges = gm.unique_edges(mesh.faces)
    arrays = {
        "vertices": template.astype(np.float32),
        "rest_vertices": template.astype(np.float32),
        "faces": mesh.faces.astype(np.int32),
        "edges": edges.astype(np.int32),
        "uvs": mesh.uvs.astype(np.float32),
        "face_uvs": mesh.face_uvs.astype(np.int32),
        "binding_indices": idx,
        "binding_weights": w,
        "binding_offsets": off,
        "scale_refs": scale_refs,
        "template_correction": correction,
        "skin_weights": skin.astype(np.float32),
    }
    gdir = out_dir / spec.id
    gdir.mkdir(parents=True, exist_ok=True)
    save_npz_deterministic(gdir / "garment.npz", arrays)
    meta = {
        "id": spec.id,
        "name": spec.name,
        "category": spec.category,
        "layer": spec.layer,
        "description": spec.description,
        "vertices": int(len(template)),
        "faces": int(len(mesh.faces)),
        "edges": int(len(edges)),
        "uv_corners": int(len(mesh.uvs)),
        "binding_max_refs": int(idx.shape[1]),
        "skin_bones": list(nb.bone_names),
        "material": {**MATERIAL, "collision_margin_m": spec.collision_margin_m},
        "template_margin_m": spec.template_margin_m,
        "units": "metres, Z-up, anny rest A-pose (template.glb: Y-up)",
        "source": f"MakeHuman system assets, outfit {spec.outfit} (components {', '.join(map(str, spec.components))})",
        "source_outfit": spec.outfit,
        "source_components": list(spec.components),
        "source_files": [f"training/sources/makehuman/{spec.outfit}/{spec.outfit}.obj",
                         f"training/sources/makehuman/{spec.outfit}/{spec.outfit}.mhclo"],
        "licence": "CC0-1.0",
        "build": {
            "command": BUILD_COMMAND,
            "body_phenotypes": [float(x) for x in NEUTRAL_PHENOTYPES],
            "inside_fraction_bound": round(report["inside_before"], 6),
            "inside_fraction_template": round(report["inside_after"], 6),
        },
    }
    (gdir / "garment.json").write_text(json.dumps(meta, indent=2) + "\n")
    appearance.update(gdir, float(nb.vertices[:, 2].min()))  # "appearance" in garment.json, template.glb
    report.update(id=spec.id, vertices=len(template), faces=len(mesh.faces), seconds=time.perf_counter() - t0,
                  npz_bytes=(gdir / "garment.npz").stat().st_size, glb_bytes=(gdir / "template.glb").stat().st_size)
    return report


def save_npz_deterministic(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez_compressed`` with fixed zip timestamps, so identical arrays give identical bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for key in sorted(arrays):
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            data = io.BytesIO()
            np.lib.format.write_array(data, np.ascontiguousarray(arrays[key]), allow_pickle=False)
            z.writestr(info, data.getvalue())
    path.write_bytes(buf.getvalue())


# (inner, outer) template pairs whose layer order the build reports (information only: the
# runtime layering stage, thesis ch. 7, resolves them on every frame).
LAYER_PAIRS = (("tshirt", "jacket"), ("longsleeve", "jacket"), ("dress", "jacket"), ("trousers", "tshirt"), ("trousers", "longsleeve"))


def report_layers(out_dir: Path) -> None:
    """Log the % of inner-template vertices outside the outer template where it covers them."""
    try:
        from inference.metrics import layer_violations
    except ImportError:  # pragma: no cover - metrics are another module's work
        return
    for inner, outer in LAYER_PAIRS:
        if not ((out_dir / inner / "garment.npz").exists() and (out_dir / outer / "garment.npz").exists()):
            continue
        with np.load(out_dir / inner / "garment.npz") as a, np.load(out_dir / outer / "garment.npz") as b:
            bad, covered = layer_violations(a["vertices"][None], b["vertices"][None], b["faces"])
        log.info("layers: %-10s under %-10s %5.2f%% of %d covered vertices outside", inner, outer,
                 100 * bad.sum() / max(covered.sum(), 1), int(covered.sum()))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=OUT_DIR)
    parser.add_argument("--only", default="", help="comma-separated garment ids (default: all)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    only = {s for s in args.only.split(",") if s}
    t0 = time.perf_counter()
    body = BodyModel.load()
    nb = neutral_body(body)
    for spec in GARMENTS:
        if only and spec.id not in only:
            continue
        r = build_garment(spec, body, nb, args.out)
        log.info(
            "%-10s V=%5d F=%5d inside bound %.2f%% -> template %.2f%% (%d), min clearance %.1f mm, "
            "correction mean %.1f / max %.1f mm | extremes bind %.2f%% / %.2f%%, retarget %.2f%% / %.2f%% | "
            "npz %d KB, glb %d KB, %.1f s",
            r["id"], r["vertices"], r["faces"], 100 * r["inside_before"], 100 * r["inside_after"], r["inside_after_count"],
            1e3 * r["min_clearance_m"], 1e3 * r["correction_mean_m"], 1e3 * r["correction_max_m"],
            100 * r["extreme_min_inside_bind"], 100 * r["extreme_max_inside_bind"],
            100 * r["extreme_min_inside_retarget"], 100 * r["extreme_max_inside_retarget"],
            r["npz_bytes"] // 1024, r["glb_bytes"] // 1024, r["seconds"],
        )
    report_layers(args.out)
    log.info("built in %.1f s", time.perf_counter() - t0)


if __name__ == "__main__":
    main()
