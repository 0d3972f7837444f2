"""The guard's plan of one garment against one collider, built once per drape from the rest
pose: each point's candidate collider vertices (rest-pose nearest, skin-aware ones from other
bones, the dynamic points searched per frame), the collider's borders and one-rings.

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from inference.errors import InputShapeError
from inference.guard.constants import (
    DEFAULT_AHEAD_M,
    DEFAULT_CANDIDATES,
    DYNAMIC_REACH_M,
    DYNAMIC_REGION_M,
    DYNAMIC_RISK_M,
    DYNAMIC_VOXEL_M,
    _OPPOSING_COS,
)
from inference.guard import push_kernels
from inference.guard.push import _check_frames
from inference.mesh import content_key, major_components, per_array, vertex_face_incidence, vertex_normals
from inference.nearness import first_per_cell, nearest, within


def _gather(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """a (B, M, 3), idx (B, N) -> (B, N, 3)."""
    return np.take_along_axis(a, idx[..., None], axis=1)


def boundary_vertices(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(V,) bool: vertices on an edge used by a single face (the border of an open mesh)."""
    faces = np.asarray(faces, np.int64)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    # edge (a, b), a < b, as one int64 key a * V + b: a 1-D unique (np.unique(axis=0) is ~10x slower)
    uniq, count = np.unique(e[:, 0] * num_vertices + e[:, 1], return_counts=True)
    single = uniq[count == 1]
    out = np.zeros(num_vertices, bool)
    out[single // num_vertices] = True
    out[single % num_vertices] = True
    return out


def _one_rings(tris: np.ndarray, S: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, R, 2): the triangles around each vertex s < S, from triangles (n, 3) of local vertex
    ids, each rotated to (s, b, c) (same orientation) and stored as (b, c); a row repeats its
    first triangle up to R (the largest valence); a vertex on no triangle gets (s, s) (such
    vertices are never candidates: they only close the rings). Also the valences (S,)."""
    tris = np.asarray(tris, np.int64)
    vert = tris.ravel()
    corner = np.tile(np.arange(3), len(tris))
    tri = np.repeat(np.arange(len(tris)), 3)
    rest = np.stack([tris[tri, (corner + 1) % 3], tris[tri, (corner + 2) % 3]], axis=1)  # (3n, 2)
    order = np.argsort(vert, kind="stable")
    vert, rest = vert[order], rest[order]
    count = np.bincount(vert, minlength=S)
    first = np.cumsum(count) - count
    col = np.arange(len(vert)) - first[vert]
    table = np.repeat(np.arange(S)[:, None, None], 2, axis=2).repeat(max(int(count.max()), 1), axis=1)
    has = count > 0
    table[has] = rest[first[has]][:, None, :]
    table[vert, col] = rest
    return table.astype(np.int32), count.astype(np.int32)


@per_array
def collider_topology(collider_faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A collider's faces (F, 3) int64, checked; its boundary vertices (V,) bool; the vertices a
    garment can rest on (int64 ids): a closed collider's major components (anny's eyes and teeth
    sit in the head and are never the surface a garment rests on), an open one's every vertex.
    Once per faces array (``inference.mesh.per_array``: ~6 ms a call for the body)."""
    faces = np.array(collider_faces, np.int64)  # a copy: it is made read-only below
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= num_vertices:
        raise InputShapeError("collider_faces", f"(F, 3) indices < {num_vertices}", faces.shape)
    bnd = boundary_vertices(faces, num_vertices)
    usable = np.flatnonzero(major_components(faces, num_vertices)) if not bnd.any() else np.arange(num_vertices)
    for a in (faces, bnd, usable):
        a.flags.writeable = False
    return faces, bnd, usable


# Colliders at rest kept per process (``_collider_rest``): a shopper's body comes back with every
# garment and motion, and what a plan derives from the body alone is the same each time (~22 ms of
# a T-shirt's ~52 ms plan on the anny body; docs/benchmarks.md, "Outfits: the guard's cost"). An
# entry holds ~14 MB (the per-bone trees of an outfit's ~17 bones; 25 MB with all 31), so few are kept.
REST_CACHE_ENTRIES = 2
_RESTS: OrderedDict = OrderedDict()
_RESTS_LOCK = threading.Lock()


@dataclass
class _ColliderRest:
    """What ``GuardPlan.build`` derives from a collider at rest alone (one entry per frame b).

    trees   : KD-trees of the usable vertices per frame
    normals : (B, M, 3) float32 vertex normals, not yet oriented
    closed_orientation : +-1.0 of a closed collider (signed volume of frame 0), None for an open one
    reach   : median edge length, metres
    bones   : (U,) the dominant bone of each usable vertex (None without weights)
    others  : (b, bone) -> (ids, KD-tree) of the usable vertices of every other bone, built when first asked
    """

    trees: list
    normals: np.ndarray
    closed_orientation: float | None
    reach: float
    bones: np.ndarray | None
    others: dict = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def other_bones(self, b: int, bone: int, rest: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, cKDTree]:
        """The usable vertices skinned mostly to another bone than ``bone`` and their KD-tree
        (unbalanced, uncompacted: ~1 ms for ~13,000 vertices) in frame b."""
        with self.lock:
            hit = self.others.get((b, bone))
        if hit is None:
            others = usable[self.bones != bone]
            hit = (others, cKDTree(rest[b][others], balanced_tree=False, compact_nodes=False))
            with self.lock:
                self.others[(b, bone)] = hit
        return hit


def _collider_rest(collider_rest: np.ndarray, faces: np.ndarray, bnd: np.ndarray, usable: np.ndarray,
                   collider_weights: np.ndarray | None) -> _ColliderRest:
    """``_ColliderRest`` of a collider at rest, kept (LRU, REST_CACHE_ENTRIES) under the contents of
    its vertices and the identities of its faces array (``collider_topology``'s) and weights
    (model arrays, never changed in place; the entry holds them so that their ids stay theirs)."""
    key = (content_key(collider_rest), id(faces), id(collider_weights))
    with _RESTS_LOCK:
        hit = _RESTS.get(key)
        if hit is not None:
            _RESTS.move_to_end(key)
            return hit[1]
    B = collider_rest.shape[0]
    trees = [cKDTree(collider_rest[b][usable]) for b in range(B)]
    normals = vertex_normals(collider_rest, faces)
    orientation = None
    if not bnd.any():  # closed: outward iff the signed volume sum_f v0 . (v1 x v2) / 6 is positive
        tri = collider_rest[0].astype(np.float64)[faces]
        orientation = -1.0 if np.einsum("fc,fc->", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) < 0 else 1.0
    e = collider_rest[0][faces[:, [0, 1, 2]]] - collider_rest[0][faces[:, [1, 2, 0]]]
    reach = float(np.median(np.linalg.norm(e, axis=-1)))
    bones = None if collider_weights is None else np.argmax(np.asarray(collider_weights, np.float32)[usable], 1)
    value = _ColliderRest(trees, normals, orientation, reach, bones)
    with _RESTS_LOCK:
        _RESTS[key] = ((faces, collider_weights), value)
        while len(_RESTS) > REST_CACHE_ENTRIES:
            _RESTS.popitem(last=False)
    return value


# Cell of the representatives that ``dynamic_region``'s reach test asks first (``inference.nearness``).
_REPRESENTATIVE_CELL_M = 0.04


def dynamic_region(points: np.ndarray, collider: np.ndarray, region_m: float = DYNAMIC_REGION_M, reach_m: float = DYNAMIC_REACH_M,
                   voxel_m: float = DYNAMIC_VOXEL_M) -> np.ndarray:
    """The collider vertices a skin-aware plan searches per frame (sorted indices into ``collider``):
    those nearer than ``region_m`` to a point, and those nearer than ``reach_m`` thinned to one per
    ``voxel_m`` cell (the lowest index of each cell; ``voxel_m`` 0: all of them).

    One nearest query per collider vertex for region_m (~5x faster than ``query_ball_point``'s
    lists, the same set); reach_m by ``inference.nearness.within``, whose representatives settle
    ~98 % of the vertices: a bounded query that finds nothing searches its whole ball, and half the
    body lies beyond reach_m of a T-shirt (~9 -> ~6 ms for the learned T-shirt's plan).

    points   : (N, 3) float32, metres; collider (M, 3) float32, metres
    """
    tree = cKDTree(points)
    near = tree.query(collider, k=1, distance_upper_bound=region_m * (1 + 1e-6))[0] < region_m
    rest = np.flatnonzero(~near)
    far = rest[within(points, collider[rest], reach_m, _REPRESENTATIVE_CELL_M, tree)]
    if len(far) and voxel_m > 0:
        far = far[first_per_cell(collider[far], voxel_m)]
    return np.union1d(np.flatnonzero(near), far)


@dataclass(frozen=True)
class GuardPlan:
    """Per-request precomputation for ``guard``: candidates and normal data of one collider.

    collider_ids   : (S,) int, the collider vertices any point may touch (the union of candidates)
    candidates     : (B, N, k) int, indices into ``collider_ids``
    across         : (B, N, k) bool, candidates on another surface across a gap (module doc)
    face_ids       : (Fs,) int, collider faces touching ``collider_ids`` (for their normals)
    incidence      : (S, Fs) CSR 0/1, vertex-face incidence of those
    faces          : (F, 3) int, the collider's faces
    orientation    : +1.0, or -1.0 when the collider's faces wind inwards (normals are flipped)
    boundary       : (S,) bool or None, border vertices of an open collider
    reach_m        : median collider edge length, metres (border tolerance)
    dynamic_points : (Nd,) int or None, points that get per-frame nearest candidates (skin-aware
                     plans: points within DYNAMIC_RISK_M of a part skinned to another bone)
    dynamic_region : (R,) int or None, indices into ``collider_ids`` searched for them per frame
    ring           : (S, R, 2) int or None, closed colliders: the triangles around each collider
                     vertex s (its one-ring, padded by repetition) as (s, b, c) counter-clockwise,
                     b and c indices into ``collider_ids``, for the closest-triangle check
    ring_valence   : (S,) int or None, the number of distinct triangles in each ring
    """

    collider_ids: np.ndarray
    candidates: np.ndarray
    across: np.ndarray
    face_ids: np.ndarray
    incidence: sp.csr_matrix
    faces: np.ndarray
    orientation: float
    boundary: np.ndarray | None
    reach_m: float
    dynamic_points: np.ndarray | None = None
    dynamic_region: np.ndarray | None = None
    ring: np.ndarray | None = None
    ring_valence: np.ndarray | None = None

    @classmethod
    def build(
        cls,
        points_rest: np.ndarray,
        collider_rest: np.ndarray,
        collider_faces: np.ndarray,
        k: int = DEFAULT_CANDIDATES,
        *,
        k_ahead: int = 2,
        ahead_m: float = DEFAULT_AHEAD_M,
        frames: tuple[np.ndarray, np.ndarray] | None = None,
        k_frames: int = 4,
        skin: tuple[np.ndarray, np.ndarray] | None = None,
        k_skin: int = 4,
        rings: bool = True,
    ) -> "GuardPlan":
        """Candidates: the k collider vertices nearest to each point in the reference pose, plus
        the k_ahead nearest to p + ahead_m n_0 (n_0: normal of the nearest vertex), plus the
        k_skin nearest skinned mostly to another bone than the point (when ``skin`` is given).

        Where the rest pose puts two parts side by side (a sleeve's armpit against the torso in
        the A-pose), the plain nearest candidates may all lie on the part the point is skinned
        to; when a joint bends, the other part comes against it (seen on 01_01, a test clip:
        T-shirt vertices skinned to the arm sank into the torso unseen). The skin-aware candidates are
        the nearest collider vertices whose dominant bone differs from the point's.

        points_rest    : (B, N, 3) float32, metres, garment vertices in the rest pose
        collider_rest  : (B, M, 3) float32, metres, collider vertices in the same pose
        collider_faces : (F, 3) int
        k              : candidates per point from the rest pose
        k_ahead        : candidates per point from ahead_m (metres) along the rest normal
        frames         : optional (points (B, T', N, 3), collider (B, T', M, 3)) posed key frames;
                         each adds its ``k_frames`` nearest collider vertices per point
        skin           : optional (point weights (N, J), collider weights (M, J)) LBS weights
        rings          : closed colliders: also keep the candidates' one-ring triangles and
                         their corners (``ring``, for the closest-triangle check)
        """
        points_rest = _check_frames("points_rest", points_rest, 3)
        collider_rest = _check_frames("collider_rest", collider_rest, 3)
        B, N = points_rest.shape[:2]
        M = collider_rest.shape[1]
        if collider_rest.shape[0] != B:
            raise InputShapeError("collider_rest", f"({B}, M, 3)", collider_rest.shape)
        faces, bnd, usable = collider_topology(collider_faces, M)
        k = int(min(k, len(usable)))
        skinned = skin is not None and k_skin > 0
        if skinned:
            pw = np.asarray(skin[0], np.float32)
            cw = skin[1]
            if pw.shape[0] != N or cw.shape[0] != M or pw.shape[1] != cw.shape[1]:
                raise InputShapeError("skin", f"((N={N}, J), (M={M}, J))", (pw.shape, cw.shape))
        rest = _collider_rest(collider_rest, faces, bnd, usable, cw if skinned else None)
        near = np.stack([nearest(rest.trees[b], collider_rest[b], usable, points_rest[b], k) for b in range(B)])
        n_rest = rest.normals
        if bnd.any():
            # open collider (a garment): the points lie on its outer side in the reference pose
            side = np.einsum("bnc,bnc->bn", points_rest - _gather(collider_rest, near[..., 0]), _gather(n_rest, near[..., 0]))
            orientation = -1.0 if np.median(side) < 0 else 1.0
        else:
            orientation = rest.closed_orientation
        n_rest = n_rest * np.float32(orientation)
        parts = [near]
        n0 = _gather(n_rest, near[..., 0])  # (B, N, 3) the point's own surface normal
        if k_ahead > 0:
            q = points_rest + ahead_m * n0
            kk = int(min(k_ahead, len(usable)))
            parts.append(np.stack([nearest(rest.trees[b], collider_rest[b], usable, q[b], kk) for b in range(B)]))
        if skinned:
            # the nearest collider vertices skinned mostly to another bone than the point: the
            # parts that a bending joint can bring against it (arm vs torso at the armpit)
            point_bone = np.argmax(pw, 1)
            skin_part = np.empty((B, N, k_skin), np.int64)
            # per dominant bone of the points, a KD-tree of the collider vertices of the other bones
            # (kept with the collider at rest); scanning every point's 32 nearest first, with these
            # trees only where that held too few, took twice as long (~40 against ~20 ms for a
            # jacket's 6,333 vertices, the trees built per request)
            for b in range(B):
                for bone in np.unique(point_bone):
                    rows = np.flatnonzero(point_bone == bone)
                    others, tree = rest.other_bones(b, int(bone), collider_rest, usable)
                    kb = int(min(k_skin, len(others)))
                    got = others[tree.query(points_rest[b][rows], k=kb)[1].reshape(len(rows), kb)]
                    skin_part[b, rows] = np.pad(got, ((0, 0), (0, k_skin - kb)), mode="edge")
            parts.append(skin_part)
            # Points that another part can reach when a joint bends: their rest-pose candidates
            # cannot follow that part (it moves relative to the point), so the guard searches
            # the region around them in every posed frame.
            d_other = np.linalg.norm(points_rest[0] - collider_rest[0][skin_part[0, :, 0]], axis=-1)
            dynamic_points = np.flatnonzero(d_other < DYNAMIC_RISK_M)
            region = np.zeros(0, np.int64)
            if len(dynamic_points):
                region = dynamic_region(points_rest[0][dynamic_points], collider_rest[0][usable])
            dynamic_region_ids = usable[region]
        else:
            dynamic_points, dynamic_region_ids = None, None
        if frames is not None:
            fp, fc = (_check_frames("frames[0]", frames[0]), _check_frames("frames[1]", frames[1]))
            kk = int(min(k_frames, len(usable)))
            parts += [
                np.stack([usable[cKDTree(fc[b, t][usable]).query(fp[b, t], k=kk)[1].reshape(N, kk)] for b in range(B)])
                for t in range(fp.shape[1])
            ]
        cand = np.concatenate(parts, axis=-1)  # (B, N, k_total) collider vertex ids
        extra_ids = dynamic_region_ids if dynamic_region_ids is not None else np.zeros(0, np.int64)
        # across a gap in the reference pose: opposing normal, point outside its plane, ahead
        cj = np.stack([collider_rest[b][cand[b]] for b in range(B)])  # (B, N, k, 3)
        nj = np.stack([n_rest[b][cand[b]] for b in range(B)])
        rel = points_rest[:, :, None] - cj  # p - c_j
        across = (
            (np.einsum("bnc,bnkc->bnk", n0, nj) < _OPPOSING_COS)
            & (np.einsum("bnkc,bnkc->bnk", rel, nj) > 0)
            & (np.einsum("bnkc,bnc->bnk", rel, n0) < 0)
        )
        used = np.zeros(M, bool)  # the sorted ids of a mask, not np.unique's sort of ~70,000 candidates
        used[cand.ravel()] = True
        used[extra_ids] = True
        ring_faces = None
        if rings and not bnd.any():
            # closed collider: the candidates' one-ring triangles, so their corners join the plan
            ring_faces, _ = vertex_face_incidence(faces, M, np.flatnonzero(used))
            used[faces[ring_faces].ravel()] = True
        collider_ids = np.flatnonzero(used)
        position = np.full(M, -1, np.int64)  # collider vertex id -> index into collider_ids
        position[collider_ids] = np.arange(len(collider_ids))
        local = position[cand]
        face_ids, inc = vertex_face_incidence(faces, M, collider_ids)
        rings_table = None if ring_faces is None else _one_rings(position[faces[ring_faces]], len(collider_ids))
        reach = rest.reach
        has_dynamic = dynamic_points is not None and len(dynamic_points) > 0
        return cls(
            collider_ids=collider_ids,
            candidates=local.astype(np.int32),
            across=across,
            face_ids=face_ids,
            incidence=inc,
            faces=faces,
            orientation=orientation,
            boundary=bnd[collider_ids] if bnd.any() else None,
            reach_m=reach,
            dynamic_points=dynamic_points if has_dynamic else None,
            dynamic_region=position[dynamic_region_ids] if has_dynamic else None,
            ring=rings_table[0] if rings_table else None,
            ring_valence=rings_table[1] if rings_table else None,
        )

    def collider_planes(self, collider: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plan's collider vertices and unit outward normals as coordinate planes.

        collider : (B, T, M, 3) float32, metres
        returns  : points (3, B*T*S), normals (3, B*T*S) float32, frame-major
        """
        collider = _check_frames("collider", collider)
        B, T, M, _ = collider.shape
        if self.faces.max() >= M:
            raise InputShapeError("collider", f"(B, T, >{self.faces.max()}, 3)", collider.shape)
        BT, S = B * T, len(self.collider_ids)
        points, normals = np.empty((3, BT * S), np.float32), np.empty((3, BT * S), np.float32)
        # per frame: area-weighted face normals (v1 - v0) x (v2 - v0), summed over each vertex's
        # faces (the incidence), normalised and oriented outward (compiled, float32 as numpy's)
        inc = self.incidence
        push_kernels.collider_planes(np.ascontiguousarray(collider.reshape(BT, M, 3), np.float32), self.faces, self.face_ids, inc.indptr,
                                     inc.indices, inc.data, self.collider_ids, float(self.orientation), points, normals,
                                     np.empty((len(self.face_ids), 3), np.float32))
        return points, normals

    def collider_frames(self, collider: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plan's collider vertices and their area-weighted unit outward normals per frame.

        collider : (B, T, M, 3) float32, metres, posed collider vertices
        returns  : points (B, T, S, 3), normals (B, T, S, 3) float32
        """
        B, T = np.shape(collider)[:2]
        pts, nrm = self.collider_planes(collider)
        S = len(self.collider_ids)
        return (np.moveaxis(pts.reshape(3, B, T, S), 0, -1), np.moveaxis(nrm.reshape(3, B, T, S), 0, -1))
