"""Contact sheets of draped garments, rendered headless (``training.render``), as small PNGs.

Run:
    python -m training.contact_sheet --garment tshirt [--method default|learned|retarget|lbs|canonical]
        [--clip CLIP] [--frames 3] [--size 200x300] [--out docs/contact_sheets]
    python -m training.contact_sheet --garments tshirt,jacket          # a layered outfit, innermost first
    python -m training.contact_sheet --garment tshirt --vertices build/reference/tshirt_01_01.npz

A sheet has one row per body (``BODIES``: the neutral body and two extreme adults) and one column
per (moment, view): ``--frames`` moments spread over the clip (20 % .. 80 % of its frames) x the
'front' and 'back' views. Garments are drawn in ``GARMENT_RGB`` (innermost first), the body in
``BODY_RGB``; every tile has the same scale (px per metre), so sizes compare across bodies. The
camera turns with the body: 'front' looks at the body's face even after it has turned
(``facing_yaw_rad``, the torso's heading in the horizontal plane). Each tile is labelled with the
body, the clip frame, its time in seconds and the view.

Default clip: the first bundled clip marked ``test_only`` in ``assets/motions/index.json`` (held out
from all training: ``01_01``), else ``walk``; ``--clip`` takes any bundled clip id.

Methods (``inference.pipeline.DrapeOptions``): default = ``DrapeOptions()`` as the service runs a
request that names no method (the sheet's title says what each garment ran), learned = fit 'learned' + dynamics 'learned', retarget = fit 'retarget' + dynamics 'none',
lbs = fit 'none' + dynamics 'none', canonical = fit 'canonical' + dynamics 'none', canonical-learned = fit
'canonical' + dynamics 'learned', learned-canonical = fit 'learned-canonical' + dynamics 'none'. With dynamics the clip is draped from frame 0 up to the last
moment shown (the wrinkle GRU's state builds up as at run time); without, each frame is
independent and only the moments shown are draped (the arms are lifted over the whole clip first,
as the pipeline would).

``--vertices FILE.npz`` renders garment frames made elsewhere (a physics simulation, a service
response) with the same camera, one row for the file's body. Arrays (metres, Z-up):
    vertices       (T, V, 3) one garment, faces from ``--garment`` (or ``faces`` (F, 3));
                   or garment_{i}_vertices (T, V_i, 3) [+ garment_{i}_faces] per garment (the
                   service's NPZ, ``inference.export.npz``), innermost first
    body_vertices  (T, Vb, 3) optional: the posed body; without it, a ``phenotypes`` (6,) +
                   ``rotations`` (T, 31, 3) + ``translation`` (T, 3) triple poses the body model
                   (``training.simulate`` writes those); with neither, the garments alone
    frames         (T,) int optional: the clip frame of each row (labels; else ``metadata``
                   JSON's ``start`` + 0..T-1, else 0..T-1) ; fps () optional (default 30)
``--frames`` of its T frames are shown (all when T <= --frames).

Output: ``<out>/<garment>_<method>.png`` (``<out>/<a>+<b>_<method>.png`` for an outfit,
``<out>/<garment>_<file stem>.png`` for ``--vertices``).
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.garment import GarmentCatalog
from inference.motion.clips import ClipLibrary
from inference.pipeline import DrapeOptions, PoseSequence, drape
from training.render import camera_axes, fit_scale, render, tile, write_png

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO_ROOT / "docs" / "contact_sheets"
FALLBACK_CLIP = "walk"
# phenotypes: gender, age, muscle, weight, height, proportions (inference.body.PHENOTYPE_LABELS)
BODIES: dict[str, np.ndarray] = {
    "neutral": NEUTRAL_PHENOTYPES,
    "heavy [1,1,1,1,1,1]": np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0], np.float32),
    "light-tall [0,.77,0,1,1,0]": np.array([0.0, 0.77, 0.0, 1.0, 1.0, 0.0], np.float32),
}
METHODS: dict[str, DrapeOptions] = {
    "default": DrapeOptions(),  # as the service runs a request that names no method
    "learned": DrapeOptions(fit="learned", dynamics="learned"),
    "retarget": DrapeOptions(fit="retarget", dynamics="none"),
    "lbs": DrapeOptions(fit="none", dynamics="none"),
    "canonical": DrapeOptions(fit="canonical", dynamics="none"),
    "canonical-learned": DrapeOptions(fit="canonical", dynamics="learned"),
    "learned-canonical": DrapeOptions(fit="learned-canonical", dynamics="none"),
}
VIEWS = ("front", "back")
FIRST_FRACTION, LAST_FRACTION = 0.2, 0.8  # of the clip's frames, where the moments are taken
BODY_RGB = (0.74, 0.71, 0.66)  # grey-beige
GARMENT_RGB = ((0.93, 0.42, 0.12), (0.18, 0.46, 0.86), (0.22, 0.66, 0.32), (0.68, 0.30, 0.74))  # orange, blue, green, purple
TORSO_BONES = ("Hips", "LowerBack", "Spine", "Spine1")  # their skin gives the body's heading
TORSO_WEIGHT = 0.95
DEFAULT_FPS = 30.0


@dataclass
class SheetRow:
    """One body at M moments, as one row of the sheet shows it.

    frames   : (M,) int, clip frame indices ; fps : frames per second of the clip
    body     : (M, Vb, 3) float32 metres, posed body, or None (garments alone)
    garments : per garment, innermost first, (M, V_i, 3) float32 metres
    yaw_rad  : (M,) float, the body's heading about +Z relative to the rest pose (camera turn)
    """

    name: str
    frames: np.ndarray
    fps: float
    body: np.ndarray | None
    garments: list[np.ndarray]
    yaw_rad: np.ndarray = field(default_factory=lambda: np.zeros(0))


def default_clip(library: ClipLibrary) -> str:
    """The first bundled test-only (held-out) clip, else ``FALLBACK_CLIP``."""
    held_out = [c for c in library.ids() if library.summary(c)["test_only"]]
    return held_out[0] if held_out else FALLBACK_CLIP


def moment_indices(num_frames: int, count: int) -> np.ndarray:
    """``count`` frame indices spread evenly from 20 % to 80 % of ``num_frames`` (the middle for one;
    first to last where 20-80 % holds too few frames; all frames when ``count >= num_frames``).
    returns (M,) int64, increasing, unique, M = min(count, num_frames)."""
    if count < 1 or num_frames < 1:
        raise ValueError(f"need at least one frame and one moment, got {num_frames} frames, {count} moments")
    if count >= num_frames:
        return np.arange(num_frames)
    fractions = np.array([0.5]) if count == 1 else np.linspace(FIRST_FRACTION, LAST_FRACTION, count)
    frames = np.unique(np.round(fractions * (num_frames - 1)).astype(np.int64))
    if len(frames) < count:  # steps of (num_frames - 1) / (count - 1) >= 1 frame: distinct
        frames = np.round(np.linspace(0, num_frames - 1, count)).astype(np.int64)
    return frames


def garment_methods(options: DrapeOptions, garment_ids: list[str]) -> list[tuple[str, str]]:
    """(fit, dynamics) each garment runs under ``options``: the option where given, else the
    garment's own default (``inference.defaults``, as ``drape`` resolves a None)."""
    if options.fit is not None and options.dynamics is not None:
        return [(options.fit, options.dynamics)] * len(garment_ids)
    from inference.defaults import resolve_methods

    return [(m.fit, m.dynamics) for m in resolve_methods(garment_ids, options.fit, options.dynamics, outfit=len(garment_ids) > 1)]


def describe(options: DrapeOptions, garment_ids: list[str]) -> str:
    """'fit F, dynamics D' (one method for all garments) or 'id: F/D; ...' per garment; a default
    learned canonical model is noted as running only within its body range (``inference.canonical.covers``)."""
    methods = garment_methods(options, garment_ids)
    note = ""
    if options.dynamics is None and ("canonical", "learned") in methods:
        from inference.defaults import default_methods

        table = default_methods()
        beyond = {g: (b.fit, b.dynamics) if (b := table.get(g).beyond_range) is not None and options.fit is None else ("canonical", "none")
                  for g, m in zip(garment_ids, methods) if m == ("canonical", "learned")}
        if len(set(beyond.values())) == 1:
            f, d = next(iter(beyond.values()))
            note = f" (learned canonical: on bodies beyond its range, fit {f}, dynamics {d})"
        else:
            note = " (learned canonical: on bodies beyond its range, " + "; ".join(f"{g}: {f}/{d}" for g, (f, d) in beyond.items()) + ")"
    if len(set(methods)) == 1:
        return f"fit {methods[0][0]}, dynamics {methods[0][1]}{note}"
    return "; ".join(f"{g}: {f}/{d}" for g, (f, d) in zip(garment_ids, methods)) + note


def torso_vertices(body: BodyModel) -> np.ndarray:
    """(N,) int: skin vertices bound to ``TORSO_BONES`` with weight >= ``TORSO_WEIGHT``."""
    bones = [body.bone_names.index(b) for b in TORSO_BONES]
    return np.flatnonzero(body.dense_weights[:, bones].sum(1) >= TORSO_WEIGHT)


def facing_yaw_rad(rest: np.ndarray, posed: np.ndarray) -> np.ndarray:
    """The heading of posed bodies about +Z relative to the rest one: 2-D Procrustes in the ground plane.

    rest  : (N, 3) float metres, torso points in the rest pose (which faces -Y)
    posed : (T, N, 3) float metres, the same points posed
    returns (T,) float64 radians, counter-clockwise seen from above:
        yaw = atan2(sum_n p_n x q_n, sum_n p_n . q_n), p, q the centred xy of rest and posed
    """
    p = rest[:, :2] - rest[:, :2].mean(0)  # (N, 2)
    q = posed[..., :2] - posed[..., :2].mean(-2, keepdims=True)  # (T, N, 2)
    cross = (p[None, :, 0] * q[..., 1] - p[None, :, 1] * q[..., 0]).sum(-1)
    dot = (p[None] * q).sum((-2, -1))
    return np.arctan2(cross, dot)


# ---------------------------------------------------------------------------------- drape
def drape_row(body: BodyModel, catalog: GarmentCatalog, clip, name: str, phenotypes: np.ndarray, garment_ids: list[str],
              options: DrapeOptions, count: int) -> SheetRow:
    """Drape ``garment_ids`` (innermost first) on one body along ``clip`` and keep ``count`` moments."""
    from training.evaluate_collisions import shaped_motion  # the evaluations' body + clip retarget

    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    shape, full = shaped_motion(body, clip, phenotypes, lift=options.lift_arms)  # arms lifted over the whole clip
    frames = moment_indices(full.num_frames, count)
    # dynamics: from frame 0 to the last moment (the GRU state); none: only the moments (independent frames)
    dynamic = any(d != "none" for _, d in garment_methods(options, garment_ids))
    keep = np.arange(frames[-1] + 1) if dynamic else frames
    motion = PoseSequence(full.rotations[keep], full.translation[keep], full.fps)
    result = drape(body, shape, motion, [catalog.get(g) for g in garment_ids], options.replace(lift_arms=False), neutral=neutral)
    at = np.searchsorted(keep, frames)
    posed = result.body_vertices
    if posed is None:  # no guard: pose the body from the bone poses, T = W P^-1
        transforms = result.bone_poses @ np.linalg.inv(shape.rest_bone_poses[0])
        posed = body.skin(shape.rest_vertices, transforms[None].astype(np.float32))[0]
    torso = torso_vertices(body)
    body_frames = posed[at]
    return SheetRow(name, frames, full.fps, body_frames, [g.vertices[at] for g in result.garments],
                    facing_yaw_rad(shape.rest_vertices[0, torso], body_frames[:, torso]))


def npz_row(path: Path, body: BodyModel, catalog: GarmentCatalog, garment_ids: list[str], count: int) -> tuple[SheetRow, list[np.ndarray]]:
    """The sheet row of an NPZ of garment frames (module docstring) and the garments' faces."""
    with np.load(path, allow_pickle=False) as z:
        arrays = dict(z)
    if "vertices" in arrays:
        garments = [arrays["vertices"]]
        faces = [arrays["faces"] if "faces" in arrays else None]
    else:
        n = 0
        while f"garment_{n}_vertices" in arrays:
            n += 1
        if n == 0:
            raise ValueError(f"{path}: no 'vertices' nor 'garment_0_vertices' array (have {sorted(arrays)})")
        garments = [arrays[f"garment_{i}_vertices"] for i in range(n)]
        faces = [arrays.get(f"garment_{i}_faces") for i in range(n)]
    for i, f in enumerate(faces):
        if f is None:
            if i >= len(garment_ids):
                raise ValueError(f"{path}: garment {i} has no faces and no --garment id gives them")
            faces[i] = catalog.get(garment_ids[i]).faces
    T = garments[0].shape[0]
    for i, g in enumerate(garments):
        if g.ndim != 3 or g.shape[0] != T or g.shape[2] != 3 or faces[i].max() >= g.shape[1]:
            raise ValueError(f"{path}: garment {i}: expected ({T}, V, 3) vertices for its faces, got {g.shape}")

    meta = json.loads(str(arrays["metadata"])) if "metadata" in arrays else {}
    if "frames" in arrays:
        frame_ids = np.asarray(arrays["frames"], np.int64)
    else:
        frame_ids = int(meta.get("start", 0)) + np.arange(T)
    fps = float(arrays["fps"]) if "fps" in arrays else DEFAULT_FPS
    at = moment_indices(T, count)

    posed, rest = arrays.get("body_vertices"), None
    phen = arrays.get("phenotypes", NEUTRAL_PHENOTYPES)
    shape = body.shape(np.asarray(phen, np.float32).reshape(1, 6))
    if posed is None and {"rotations", "translation"} <= set(arrays):
        _, transforms = body.pose(shape.rest_bone_poses, arrays["rotations"][None, at].astype(np.float32), arrays["translation"][None, at].astype(np.float32))
        posed = body.skin(shape.rest_vertices, transforms)[0]
    elif posed is not None:
        posed = posed[at]
    yaw = np.zeros(len(at))
    if posed is None:
        log.warning("%s: no body_vertices nor phenotypes/rotations/translation: garments alone, camera not turned", path)
    elif posed.shape[1] == body.num_vertices:
        torso = torso_vertices(body)
        rest = shape.rest_vertices[0, torso]
        yaw = facing_yaw_rad(rest, posed[:, torso])
    name = str(meta.get("clip", path.stem))
    return SheetRow(name, frame_ids[at], fps, posed, [g[at] for g in garments], yaw), faces


# ---------------------------------------------------------------------------------- sheet
def tile_label(row: SheetRow, m: int, view: str) -> str:
    """Two lines: the body, then clip frame, time and view."""
    return f"{row.name}\nf{int(row.frames[m])} {row.frames[m] / row.fps:.2f}s {view}"


def render_sheet(rows: list[SheetRow], body_faces: np.ndarray | None, garment_faces: list[np.ndarray], size: tuple[int, int] = (200, 300),
                 views: tuple[str, ...] = VIEWS, supersample: int = 2, title: str | None = None) -> tuple[np.ndarray, float]:
    """The contact sheet: rows = bodies, columns = (moment, view), moment-major.

    rows          : SheetRow per body, all with the same M moments
    body_faces    : (Fb, 3) int ; garment_faces : per garment (F_i, 3) int
    size          : (W, H) pixels per tile ; one scale (px / m) for every tile, the largest that fits all
    title         : optional text in a band over the tiles (``training.render.tile``; Pillow only)
    returns sheet (len(rows) * H [+ title band], M * len(views) * W, 3) uint8, mean seconds per tile
    """
    M = len(rows[0].frames)
    if any(len(r.frames) != M for r in rows):
        raise ValueError(f"every row needs the same number of moments, got {[len(r.frames) for r in rows]}")

    def meshes(row: SheetRow, m: int):
        out = [] if row.body is None or body_faces is None else [(row.body[m], body_faces, BODY_RGB)]
        return out + [(g[m], f, GARMENT_RGB[i % len(GARMENT_RGB)]) for i, (g, f) in enumerate(zip(row.garments, garment_faces))]

    def yaw(row: SheetRow, m: int) -> float:
        return float(row.yaw_rad[m]) if len(row.yaw_rad) else 0.0

    cells = [(row, m, view) for row in rows for m in range(M) for view in views]
    scale = min(fit_scale(np.concatenate([v for v, _, _ in meshes(r, m)]), camera_axes(view, yaw(r, m)), size) for r, m, view in cells)
    t0 = time.perf_counter()
    images = [render(meshes(r, m), view, size, yaw_rad=yaw(r, m), px_per_m=scale, supersample=supersample) for r, m, view in cells]
    seconds = (time.perf_counter() - t0) / len(cells)
    labels = [tile_label(r, m, view) for r, m, view in cells]
    return tile(images, len(rows), M * len(views), labels, title=title), seconds


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H) pixels."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, e.g. 200x300, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"tiles must be at least 8x8 px, got {text!r}")
    return w, h


def main(argv: list[str] | None = None) -> Path:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--garment", help="garment id (assets/garments/<id>)")
    which.add_argument("--garments", help="a layered outfit: garment ids, comma-separated, innermost first")
    p.add_argument("--method", default="default", choices=sorted(METHODS), help="drape options (module docstring)")
    p.add_argument("--clip", help="bundled clip id (default: the held-out test clip, else walk)")
    p.add_argument("--frames", type=int, default=3, help="moments per body, spread over 20-80%% of the clip")
    p.add_argument("--size", type=parse_size, default=(200, 300), help="tile size WxH in pixels")
    p.add_argument("--supersample", type=int, default=2, help="anti-aliasing: render at this multiple of the size")
    p.add_argument("--vertices", type=Path, help="render garment frames from this NPZ instead of draping (module docstring)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    garment_ids = [args.garment] if args.garment else [g.strip() for g in args.garments.split(",") if g.strip()]
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    t0 = time.perf_counter()
    if args.vertices is not None:
        row, faces = npz_row(args.vertices, body, catalog, garment_ids, args.frames)
        rows, tag, title = [row], args.vertices.stem, f"{'+'.join(garment_ids)} from {args.vertices.name}"
    else:
        library = ClipLibrary()
        clip = library.load(args.clip or default_clip(library))
        options = METHODS[args.method]
        rows = [drape_row(body, catalog, clip, name, phen, garment_ids, options, args.frames) for name, phen in BODIES.items()]
        faces = [catalog.get(g).faces for g in garment_ids]
        tag, title = args.method, f"{'+'.join(garment_ids)}, {args.method} ({describe(options, garment_ids)}), clip {clip.id}"
    t1 = time.perf_counter()
    sheet, per_tile = render_sheet(rows, body.faces, faces, args.size, supersample=args.supersample, title=title)
    path = write_png(args.out / f"{'+'.join(garment_ids)}_{tag}.png", sheet, palette=True)
    log.info("wrote %s: %d x %d px, %.0f KB (rows: %s; columns: frames %s x %s); drape %.1f s, render %.2f s per tile",
             path, sheet.shape[1], sheet.shape[0], path.stat().st_size / 1024, ", ".join(r.name for r in rows),
             rows[0].frames.tolist(), "/".join(VIEWS), t1 - t0, per_tile)
    return path


if __name__ == "__main__":
    main()
