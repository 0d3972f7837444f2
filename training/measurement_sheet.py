"""A contact sheet of where the body measurements are taken (``inference.measurements``).

Run:
    python -m training.measurement_sheet [--out docs/contact_sheets/measurements.png] [--size 200x300]

One row per body (the neutral adult and extreme adults), columns front and left side. The body is
grey; the tape of each girth is drawn as a band round the convex hull of its torso slice, 8 mm
outside the skin: chest red, waist green, hips blue; the crotch (top of the inseam) is a black
marker. Labels give the measurements in cm, so a wrong landmark shows as a band in the wrong place
or a number that does not match the band.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from inference.body import BodyModel
from inference.measurements import MEASUREMENTS, BodyMeasurer
from training.render import fit_scale, camera_axes, render, tile, write_png

# gender, age, muscle, weight, height, proportions
BODIES = {
    "neutral": (0.5, 0.8, 0.5, 0.5, 0.5, 0.5),
    "male, heavy": (0.0, 0.9, 0.3, 1.0, 0.6, 0.5),
    "female, slim": (1.0, 0.8, 0.2, 0.0, 0.4, 0.3),
    "female, heavy, short": (1.0, 1.0, 0.5, 1.0, 0.0, 0.8),
    "male, muscular, tall": (0.0, 0.8, 1.0, 0.6, 1.0, 1.0),
}
BAND_RGB = ((0.85, 0.15, 0.15), (0.15, 0.65, 0.2), (0.15, 0.3, 0.9))
BODY_RGB = (0.72, 0.72, 0.72)
BAND_OFFSET_M = 0.008
BAND_HALF_HEIGHT_M = 0.006


def band_mesh(points: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    """A vertical ribbon round the convex hull of 2D points at height z, pushed outward."""
    hull = points[ConvexHull(points).vertices]
    centre = hull.mean(axis=0)
    out = hull + BAND_OFFSET_M * (hull - centre) / np.linalg.norm(hull - centre, axis=1, keepdims=True)
    n = len(out)
    lower = np.c_[out, np.full(n, z - BAND_HALF_HEIGHT_M)]
    upper = np.c_[out, np.full(n, z + BAND_HALF_HEIGHT_M)]
    i = np.arange(n)
    j = (i + 1) % n
    faces = np.concatenate([np.c_[i, j, n + i], np.c_[j, n + j, n + i]])
    return np.vstack([lower, upper]), faces


def marker_mesh(centre: np.ndarray, half: float = 0.012) -> tuple[np.ndarray, np.ndarray]:
    """A small octahedron at ``centre``."""
    d = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64) * half
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return centre + d, faces


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs/contact_sheets/measurements.png"))
    ap.add_argument("--size", default="200x300")
    args = ap.parse_args(argv)
    W, H = (int(v) for v in args.size.split("x"))
    body = BodyModel.load()
    measurer = BodyMeasurer(body)
    shape = body.shape(np.array(list(BODIES.values()), np.float32))
    m = measurer.measure(shape.rest_vertices, shape.bone_heads)
    views = ("front", "left")
    all_points = shape.rest_vertices.reshape(-1, 3)
    px_per_m = min(fit_scale(all_points, camera_axes(v), (W, H)) for v in views)
    images, labels = [], []
    for b, name in enumerate(BODIES):
        v = shape.rest_vertices[b]
        meshes = [(v, body.faces, BODY_RGB)]
        for k, rgb in enumerate(BAND_RGB):
            z = float(m.levels[b, k])
            meshes.append((*band_mesh(measurer.slice_points(v, z), z), rgb))
        crotch_z = float(v[:, 2].min() + m.inseam[b])
        meshes.append((*marker_mesh(np.array([0.0, v[measurer.midline, 1].mean(), crotch_z])), (0.0, 0.0, 0.0)))
        values = " ".join(f"{n[0]}{getattr(m, n)[b] * 100:.0f}" for n in MEASUREMENTS)
        for view in views:
            images.append(render(meshes, view, (W, H), px_per_m=px_per_m, supersample=2))
            labels.append(f"{name} {view}\n{values} {m.mass_kg[b]:.0f}kg")
    sheet = tile(images, len(BODIES), len(views), labels,
                 title="girths: chest red, waist green, hips blue; crotch black (h c w h i in cm)")
    return write_png(args.out, sheet)


if __name__ == "__main__":
    print(main())
