"""Exact winding numbers of a closed triangle mesh by signed ray crossings (DESIGN.md §5).

The posed body is a closed, outward-oriented triangle mesh that intersects itself under LBS, so
"inside" means a winding number >= 1 (generalised winding number > 0.5), not the parity of ray
crossings and not a closest-face sign. For a closed mesh the winding number is an integer and
equals the signed number of crossings of any ray from the point:

    w(p) = sum over faces f hit by the ray p + t s e_y (t > 0, s = +1 or -1 per point) of sign(n_f . s e_y)

(an outward face is left through, +1, or entered, -1). ``WindingGrid`` bins the faces of a batch
of frames once, projected along the ray onto (x, z), into a 2-D grid; a point then tests only the
faces of its cell, so one grid answers many point sets (a garment's vertices, then the targets of
``inference.repair``), each point casting its ray up or down y (``ray_down``: the side its
garment's normal faces, so the ray leaves the body at once), and a grid can bin only the faces
over the part of the plane its points lie in (``region``). Point-in-projected-triangle uses edge functions evaluated from the edge's
two vertices in canonical (lower index first) order, so the two faces sharing an edge compute the
bitwise same value and a ray through the edge is counted once; a point on an edge's line takes
the side of the point moved by an infinitesimal (eps, eps^2) (``inference.winding_kernels``), so
a ray through a projected vertex counts as well. Only points on the surface are ambiguous. The crossing test runs in float64 on the candidate (point, face) pairs only,
compiled (numba: ``inference.winding_kernels``); a grid's bins live in per-thread buffers that the
next grid reuses.

Cost per frame (27,420-face body, 5,148 T-shirt points, one thread; ``python bench/bench_canonical.py``,
session 37): the grid ~1.8 ms, or ~0.9 over a garment's region (``WindingGrid``'s ``region``: only
the faces over the points asked), the count ~0.7 ms; the same algorithm in numpy took ~9 + ~7 ms
(session 42's kernels: ``inference.winding_kernels``). A
bounding-volume hierarchy refitted per frame (0.3 ms) with a ray along each point's outward axis
gave the same counts but cost 3.2 ms to count (a branchy traversal, ~45 boxes a point at ~30 ns
each, against ~18 contiguous pre-tests in a cell), so the grid stays.

Units: metres. Shapes: batch axis first; a frame is one (points, mesh) pair.
"""
from __future__ import annotations

import functools
import threading
import weakref

import numpy as np

from inference import mesh_kernels
from inference import winding_kernels as kernels
from inference.errors import InputShapeError
from inference.mesh import per_array

# Grid cell, in multiples of the median edge length.
CELL_EDGES = 2.0
# The median is taken over the first edge of every EDGE_SAMPLE-th face.
EDGE_SAMPLE = 8
# Frames binned at once by ``winding_numbers`` (bounds the memory of the face bins).
FRAME_BLOCK = 16


def _frames(name: str, a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 3 or a.shape[-1] != 3:
        raise InputShapeError(name, "(B, N, 3)", a.shape)
    return a


def check_faces(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(F, 3) int64 triangle indices into num_vertices vertices (InputShapeError otherwise)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= num_vertices:
        raise InputShapeError("faces", f"(F, 3) indices < {num_vertices}", faces.shape)
    return faces.astype(np.int64)


class _Pool(threading.local):
    """Per-thread free buffers: a grid takes the ones it needs and gives them back when it is
    collected, so that the next grid reuses their pages (fresh pages cost more than the binning
    itself: ~1 ms per MB touched here)."""

    def __init__(self):
        self.free: dict[tuple[str, str], list[np.ndarray]] = {}

    def take(self, name: str, size: int, dtype) -> np.ndarray:
        free = self.free.setdefault((name, np.dtype(dtype).str), [])
        for k, buf in enumerate(free):
            if buf.size >= size:
                return free.pop(k)
        return np.empty(max(size, 1024), dtype)

    def give(self, name: str, buf: np.ndarray) -> None:
        """Keep one buffer per name (the larger), so that a thread holds at most one grid's worth
        (~60 MB for FRAME_BLOCK frames of the body and its inflated copy, the binning's face
        records included)."""
        free = self.free.setdefault((name, buf.dtype.str), [])
        if not free or free[0].size < buf.size:
            free[:] = [buf]


_POOL = _Pool()
# ``first_outside``'s verdicts when the caller keeps none: no target known
_NOTHING_KNOWN = np.zeros((0, 0), np.int8)


def _topology(faces: np.ndarray) -> tuple[np.ndarray, ...]:
    """``_topology_cached`` of (F, 3) int64 faces: computed once per mesh topology."""
    return _topology_cached(faces.tobytes(), faces.shape)


@functools.lru_cache(maxsize=8)
def _topology_cached(faces_bytes: bytes, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """faces (contiguous int64) and the ids of the vertices they use."""
    faces = np.ascontiguousarray(np.frombuffer(faces_bytes, np.int64).reshape(shape))
    return faces, np.unique(faces)


@per_array
def _checked_topology(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, ...]:
    """``check_faces`` then ``_topology``, once per faces array (``inference.mesh.per_array``)."""
    return _topology(check_faces(faces, num_vertices))


class WindingGrid:
    """The faces of B frames of one closed mesh, binned for ray-crossing winding numbers.

    verts  : (B, V, 3) float, metres, closed mesh with outward (counter-clockwise) faces
    faces  : (F, 3) int
    second : optional (B, V, 3) float, metres, a second placement of the same mesh (the body and
             its inflated copy, ``inflated``): each face is binned over the boxes of both, so the
             one grid answers for either or both (``count_at``'s ``mesh``) for about the cost
             of one (the boxes grow by the distance between the two)
    region : optional (B, 4) float, metres, per frame the (x min, x max, z min, z max) of the
             points to be asked: only the faces whose projected box meets it are binned (a
             garment's neighbourhood holds a quarter to a third of the body's faces, and the
             binning's cost is in proportion); a point outside it is answered by a grid of the
             whole mesh in its frame, built when first needed

    The binning and the crossings run compiled (``inference.winding_kernels``).
    """

    def __init__(self, verts: np.ndarray, faces: np.ndarray, second: np.ndarray | None = None, region: np.ndarray | None = None):
        verts = _frames("verts", verts)
        self.faces, used = _checked_topology(faces, verts.shape[1])
        faces = self.faces
        B, V = verts.shape[:2]
        self.B, self.V, self.F = B, V, len(faces)
        sets = [verts] if second is None else [verts, _frames("second", second)]
        if second is not None and sets[1].shape != verts.shape:
            raise InputShapeError("second", str(verts.shape), sets[1].shape)
        # each vertex as (u, v, y) = (x, z, y), float64 (exact copies of float32 input), interleaved
        # so that a face's corners are three reads of 24 bytes
        names = ("X", "X2")[: len(sets)]
        bufs = [_POOL.take(name, B * V * 3, np.float64) for name in names]
        self.coords = []
        for mesh, buf in zip(sets, bufs):
            X = buf[: B * V * 3].reshape(B, V, 3)
            for c, k in enumerate((0, 2, 1)):
                np.copyto(X[..., c], mesh[..., k])
            self.coords.append(X.reshape(B * V, 3))  # per vertex set
        X2 = self.coords[-1]

        # grid over each frame's projected mesh (its own origin), cell CELL_EDGES median edges (of
        # every EDGE_SAMPLE-th face's first edge, frame 0)
        self.h = h = CELL_EDGES * max(float(kernels.median_edge(verts[0], faces, EDGE_SAMPLE)), 1e-6)
        lo, hi = np.empty((B, 2)), np.empty((B, 2))  # each frame's (u, v) box of the used vertices, both sets
        kernels.uv_bounds(self.coords[0], X2, used, B, V, lo, hi)
        self.bounded = region is not None
        if region is None:
            self.region = np.tile([-np.inf, np.inf, -np.inf, np.inf], (B, 1))
        else:
            self.region = np.ascontiguousarray(region, np.float64)
            if self.region.shape != (B, 4) or not np.isfinite(self.region).all():
                raise InputShapeError("region", f"({B}, 4) finite", self.region.shape)
            lo = np.maximum(lo, self.region[:, [0, 2]])
            hi = np.maximum(np.minimum(hi, self.region[:, [1, 3]]), lo)
        self.lo = lo
        self._sets = (verts, second)  # for the whole mesh's grid (``count_at``)
        self._whole: dict[int, WindingGrid] = {}  # per frame, the whole mesh's grid (``count_at``)
        # the kernels' own cell formula, floor((x - lo) / h) as a product (module winding_kernels)
        extent = (hi - lo).max(0)
        self.ncell = np.floor(extent * (1.0 / h)).astype(np.int64) + 1
        ni, nj = int(self.ncell[0]), int(self.ncell[1])
        # the bins, in buffers of this thread's pool (returned when the grid is collected); the
        # first pass's face records only for the second
        start = _POOL.take("start", B * ni * nj + 1, np.int64)
        code = _POOL.take("code", V, np.uint8)
        rec_face, rec_cells, rec_box = (_POOL.take("rec_face", B * self.F, np.int32), _POOL.take("rec_cells", 4 * B * self.F, np.int32),
                                        _POOL.take("rec_box", 6 * B * self.F, np.float32))
        m, pairs = kernels.bin_boxes(self.coords[0], X2, faces, B, V, 1.0 / h, self.lo, ni, nj, self.region, start[: B * ni * nj + 1],
                                     code[:V], rec_face[: B * self.F], rec_cells[: 4 * B * self.F].reshape(-1, 4),
                                     rec_box[: 6 * B * self.F].reshape(-1, 6))
        pairs = int(pairs)
        cell_face, pair_box, fill = (_POOL.take("cell_face", pairs, np.int32), _POOL.take("pair_box", 6 * pairs, np.float32),
                                     _POOL.take("fill", B * ni * nj, np.int64))
        self.start, self.cell_face = start[: B * ni * nj + 1], cell_face[:pairs]
        self.pair_box = pair_box[: 6 * pairs].reshape(pairs, 6)
        kernels.fill_pairs(int(m), nj, self.start, fill[: B * ni * nj], rec_face[: B * self.F], rec_cells[: 4 * B * self.F].reshape(-1, 4),
                           rec_box[: 6 * B * self.F].reshape(-1, 6), self.cell_face, self.pair_box)
        for name, buf in zip(("code", "rec_face", "rec_cells", "rec_box", "fill"), (code, rec_face, rec_cells, rec_box, fill)):
            _POOL.give(name, buf)
        for name, buf in zip(("start", "cell_face", "pair_box", *names), (start, cell_face, pair_box, *bufs)):
            weakref.finalize(self, _POOL.give, name, buf)

    def count(self, points: np.ndarray, mesh: str = "first", down: np.ndarray | None = None) -> np.ndarray:
        """Winding number at each point of each frame (``mesh`` and ``down`` as in ``count_at``).

        points : (B, N, 3) float, metres (frame b against frame b of the mesh)
        returns: (B, N) int32 (0 outside, 1 inside, 2 inside two overlapping parts, ...)
        """
        points = _frames("points", points)
        if points.shape[0] != self.B:
            raise InputShapeError("points", f"({self.B}, N, 3)", points.shape)
        B, N = points.shape[:2]
        if down is not None:
            down = np.asarray(down)
            if down.shape != (B, N):
                raise InputShapeError("down", f"({B}, {N})", down.shape)
            down = down.reshape(-1)
        return self.count_at(points.reshape(B * N, 3), np.repeat(np.arange(B), N), mesh, down).reshape(B, N)

    def count_at(self, points: np.ndarray, frame: np.ndarray, mesh: str = "first", down: np.ndarray | None = None) -> np.ndarray:
        """Winding number at points of any frames: points (P, 3) float, metres, point i against
        frame ``frame[i]`` (P,) int of the mesh; ``mesh``: "first" (the grid's vertex set),
        "second" (its second one) or "either" (the larger of the two numbers: inside either one);
        ``down`` (P,) bool: the points whose ray runs along -y instead of +y (the same numbers;
        a ray that leaves the body at once, ``ray_down``, meets fewer faces). returns (P,) int32."""
        if mesh not in ("first", "second", "either") or (mesh != "first" and len(self.coords) < 2):
            raise ValueError(f"mesh {mesh!r} of a grid of {len(self.coords)} vertex set(s)")
        points = np.asarray(points)
        frame = np.ascontiguousarray(frame, np.int64)
        if points.ndim != 2 or points.shape[1] != 3 or frame.shape != points.shape[:1]:
            raise InputShapeError("points", "(P, 3) with frame (P,)", points.shape)
        if len(frame) and (frame.min() < 0 or frame.max() >= self.B):
            raise InputShapeError("frame", f"indices < {self.B}", frame.shape)
        if points.dtype not in (np.float32, np.float64):
            points = points.astype(np.float64)
        first, second = (self.coords[-1], self.coords[0]) if mesh == "second" else (self.coords[0], self.coords[-1])
        points = np.ascontiguousarray(points)
        down = np.zeros(len(points), bool) if down is None else np.ascontiguousarray(down, bool)
        if down.shape != frame.shape:
            raise InputShapeError("down", "(P,)", down.shape)
        w = kernels.count_crossings(points, frame, down, first, second, self.faces, self.V, 1.0 / self.h, self.lo, int(self.ncell[0]),
                                    int(self.ncell[1]), self.region, self.bounded, self.start, self.cell_face, self.pair_box,
                                    mesh == "either")
        outside = np.flatnonzero(w == kernels.UNKNOWN)
        for b in np.unique(frame[outside]):  # beyond the region: the whole mesh's grid of that frame alone
            rows = outside[frame[outside] == b]
            if b not in self._whole:
                second = None if self._sets[1] is None else self._sets[1][b:b + 1]
                self._whole[b] = WindingGrid(self._sets[0][b:b + 1], self.faces, second=second)
            w[rows] = self._whole[b].count_at(points[rows], np.zeros(len(rows), np.int64), mesh, down[rows])
        return w


    def first_outside(self, points: np.ndarray, targets: np.ndarray, frame: np.ndarray, mesh: str = "first",
                      known: np.ndarray | None = None) -> np.ndarray:
        """Per point, its nearest target with winding number 0 (``mesh`` as in ``count_at``): points
        (n, 3) float32, targets (n, m, 3) float32, frame (n,) int; nearest by float32 distance, equal
        distances in their column order; each target's ray along its move's side of y (down where
        it lies below its point). Returns (n,) int64 columns, -1 where no target is outside; a
        target beyond the grid's region is counted by the whole mesh's grid, as ``count_at`` does
        (those points take ``count_at``'s path).

        known: (n, mk) int8, C-contiguous, the verdicts of each point's first mk targets already
        counted (0 outside, 1 inside, -1 not known), read and completed in place (the kernel's
        ``known``): a caller that asks the same targets again (``repair._keep_together``'s rounds)
        counts each once."""
        if mesh not in ("first", "second", "either") or (mesh != "first" and len(self.coords) < 2):
            raise ValueError(f"mesh {mesh!r} of a grid of {len(self.coords)} vertex set(s)")
        points = np.ascontiguousarray(points, np.float32)
        targets = np.ascontiguousarray(targets, np.float32)
        frame = np.ascontiguousarray(frame, np.int64)
        if points.ndim != 2 or points.shape[1] != 3 or targets.shape[::2] != (len(points), 3) or frame.shape != points.shape[:1]:
            raise InputShapeError("targets", "(n, m, 3) with points (n, 3) and frame (n,)", targets.shape)
        if known is not None and (known.dtype != np.int8 or known.ndim != 2 or len(known) != len(points)
                                  or known.shape[1] > targets.shape[1] or not known.flags.c_contiguous or not known.flags.writeable):
            raise InputShapeError("known", f"writeable C-contiguous int8 ({len(points)}, <= {targets.shape[1]})", known.shape)
        first, second = (self.coords[-1], self.coords[0]) if mesh == "second" else (self.coords[0], self.coords[-1])
        best = kernels.first_outside(points, targets, frame, first, second, self.faces, self.V, 1.0 / self.h, self.lo, int(self.ncell[0]),
                                     int(self.ncell[1]), self.region, self.bounded, self.start, self.cell_face, self.pair_box,
                                     mesh == "either", _NOTHING_KNOWN if known is None else known)
        for p in np.flatnonzero(best == -2):  # a target beyond the region: each in order, by count_at
            order = np.argsort(np.linalg.norm(targets[p] - points[p], axis=-1), kind="stable")
            down = targets[p, order, 1] < points[p, 1]
            free = np.flatnonzero(self.count_at(targets[p, order], np.full(len(order), frame[p]), mesh, down) == 0)
            best[p] = order[free[0]] if len(free) else -1
        return best


def ray_down(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which points' rays should run along -y (``WindingGrid.count``'s ``down``): those whose
    area-weighted vertex normal points down y, so that the ray leaves a garment lying on the skin
    at once (on the T-shirt the faces a point's ray must be tested against fall from ~3.8 to
    ~1.8). points (B, N, 3) float, metres, of a mesh with outward faces (F, 3) -> (B, N) bool."""
    points = np.ascontiguousarray(_frames("points", points))
    faces = _checked_topology(faces, points.shape[1])[0]
    out = np.empty(points.shape[:2], bool)
    mesh_kernels.normal_points_down(points, faces, out)  # the y component's sign alone (~1/3 of the normals' work)
    return out


def winding_numbers(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Winding number of a closed mesh at each point, by signed ray crossings (module doc).

    points : (B, N, 3) float, metres
    verts  : (B, V, 3) float, metres, closed mesh with outward (counter-clockwise) faces
    faces  : (F, 3) int
    returns: (B, N) int32 (0 outside, 1 inside, 2 inside two overlapping parts, ...)
    """
    points = _frames("points", points)
    verts = _frames("verts", verts)
    B, N = points.shape[:2]
    if verts.shape[0] != B:
        raise InputShapeError("verts", f"({B}, V, 3)", verts.shape)
    check_faces(faces, verts.shape[1])
    out = np.empty((B, N), np.int32)
    for b0 in range(0, B, FRAME_BLOCK):
        sl = slice(b0, b0 + FRAME_BLOCK)
        out[sl] = WindingGrid(verts[sl], faces).count(points[sl])
    return out


def inflated(verts: np.ndarray, faces: np.ndarray, distance_m: float) -> np.ndarray:
    """The mesh offset outward by ``distance_m`` along its unit area-weighted vertex normals,
    v + d n_v (compiled: ~0.3 ms a frame of the 14k-vertex body, where ``inference.mesh.
    vertex_normals`` takes ~8): verts (B, V, 3) float, metres -> (B, V, 3) float32. For a small d
    it holds the mesh inside it, and a point outside it is at least ~d from the mesh."""
    verts = np.ascontiguousarray(_frames("verts", verts), np.float32)
    faces = _checked_topology(faces, verts.shape[1])[0]
    out = np.empty_like(verts)
    kernels.inflate(verts, faces, float(distance_m), out)
    return out


def warm_up() -> None:
    """Compile the kernels (or load them from numba's cache: ``NUMBA_CACHE_DIR``, else beside this
    module or in the user's cache) with a tetrahedron, so that no request pays the ~5 s of a
    first compilation: every process that drapes calls it at start-up."""
    tet = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]], np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    WindingGrid(tet, faces).count(np.full((1, 1, 3), 0.1))
    WindingGrid(tet.astype(np.float32), faces)  # a request's float32 vertices (the cell's median edge)
    inflated(tet, faces, 0.0)
