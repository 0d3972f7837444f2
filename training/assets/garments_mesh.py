"""Garment mesh surgery for the catalog build: MakeHuman sources -> clean triangle meshes.

Every operation here keeps a *linear source map*: ``GarmentMesh.source`` is a sparse
(V, V_src) matrix whose row v says how vertex v is a weighted average of the vertices of the
source ``.obj`` (rows sum to 1). Welding averages two rows, a midpoint of an edge is half of
each end's row, a bridge adds faces only. Because a MakeHuman ``.mhclo`` binding is linear in
the bound vertices (same per-garment axis scales for all of them), the binding of every new
vertex is exactly ``source @ binding_of_source``: subdivided garments still fit any body.

Sources: ``NAME.obj`` (quads, MakeHuman decimetres, Y-up, UVs) and ``NAME.mhclo``
(``verts`` lines ``i0 i1 i2 w0 w1 w2 d0 d1 d2`` into hm08; ``x_scale``/``y_scale``/``z_scale``
lines ``a b s``; see ``inference.garment.bind_garment`` for the formula).
"""
from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

HM08_VERTEX_COUNT = 19158


# ---------------------------------------------------------------------------- sources
@dataclass(frozen=True)
class OutfitSource:
    """One MakeHuman outfit as read from disk.

    vertices      : (Vs, 3) float64, MakeHuman units (decimetres), Y-up
    uvs           : (Vt, 2) float64
    quads         : (Fq, 4) int64 into vertices
    quad_uvs      : (Fq, 4) int64 into uvs
    binding       : (Vs, 19158) scipy CSR, the ``.mhclo`` weights w0..w2 over hm08 vertices
    offsets       : (Vs, 3) float64, ``.mhclo`` offsets (d0, d1, d2), hm08 axes, offset units
    scale_refs    : (3, 3) float64, rows x, y, z (hm08 axes): (a, b, s)
    """

    name: str
    vertices: np.ndarray
    uvs: np.ndarray
    quads: np.ndarray
    quad_uvs: np.ndarray
    binding: sp.csr_matrix
    offsets: np.ndarray
    scale_refs: np.ndarray


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """MakeHuman ``.obj``: positions (V,3), uvs (Vt,2), quads (F,4), quad uv indices (F,4); 0-based."""
    v, vt, f, ft = [], [], [], []
    for line in Path(path).read_text().splitlines():
        s = line.split()
        if not s:
            continue
        if s[0] == "v":
            v.append([float(x) for x in s[1:4]])
        elif s[0] == "vt":
            vt.append([float(x) for x in s[1:3]])
        elif s[0] == "f":
            corners = [c.split("/") for c in s[1:]]
            if len(corners) != 4:
                raise ValueError(f"{path}: expected quads, got a face with {len(corners)} corners")
            f.append([int(c[0]) - 1 for c in corners])
            ft.append([int(c[1]) - 1 for c in corners])
    return np.array(v), np.array(vt), np.array(f, np.int64), np.array(ft, np.int64)


def read_mhclo(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``.mhclo``: ref indices (V,3) int64, weights (V,3), offsets (V,3), scale_refs (3,3) (a, b, s per hm08 axis)."""
    refs: dict[str, tuple[float, float, float]] = {}
    rows: list[list[float]] = []
    section = None
    for line in Path(path).read_text().splitlines():
        s = line.split()
        if not s or s[0].startswith("#"):
            continue
        if s[0] in ("x_scale", "y_scale", "z_scale"):
            refs[s[0]] = (float(s[1]), float(s[2]), float(s[3]))
        elif s[0] in ("verts", "delete_verts", "weights"):
            section = s[0]
        elif section == "verts" and s[0][0].isdigit():
            if len(s) == 1:  # exact fit: one reference vertex
                rows.append([float(s[0]), 0, 0, 1, 0, 0, 0, 0, 0])
            elif len(s) == 9:
                rows.append([float(x) for x in s])
            else:
                raise ValueError(f"{path}: unexpected verts line {line!r}")
    a = np.array(rows)
    scale_refs = np.array([refs["x_scale"], refs["y_scale"], refs["z_scale"]])
    return a[:, :3].astype(np.int64), a[:, 3:6], a[:, 6:9], scale_refs


def load_outfit(folder: Path) -> OutfitSource:
    """Read ``folder/NAME.obj`` + ``folder/NAME.mhclo`` (NAME = folder name)."""
    folder = Path(folder)
    name = folder.name
    v, vt, quads, quad_uvs = read_obj(folder / f"{name}.obj")
    idx, w, d, scale_refs = read_mhclo(folder / f"{name}.mhclo")
    if len(idx) != len(v):
        raise ValueError(f"{name}: {len(idx)} binding lines for {len(v)} vertices")
    rows = np.repeat(np.arange(len(v)), 3)
    binding = sp.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(len(v), HM08_VERTEX_COUNT))
    binding.sum_duplicates()
    return OutfitSource(name, v, vt, quads, quad_uvs, binding, d, scale_refs)


def quad_components(quads: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected component label (V,) of each vertex of a polygon mesh (labels in first-vertex order)."""
    e = np.concatenate([quads[:, [i, (i + 1) % quads.shape[1]]] for i in range(quads.shape[1])])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(A, directed=False)[1]


# ---------------------------------------------------------------------------- mesh
@dataclass(frozen=True)
class GarmentMesh:
    """A triangle mesh with UV corners and its linear map to the source ``.obj`` vertices.

    faces    : (F, 3) int64 into vertices (welded positions)
    uvs      : (Vt, 2) float64 ; face_uvs : (F, 3) int64 into uvs (UV seams keep their corners)
    source   : (V, Vs) scipy CSR, rows sum to 1: vertex = source @ source_vertices
    piece    : (V,) int64, which selected outfit component each vertex came from (0, 1, ...)
    """

    faces: np.ndarray
    uvs: np.ndarray
    face_uvs: np.ndarray
    source: sp.csr_matrix
    piece: np.ndarray

    @property
    def n_vertices(self) -> int:
        return self.source.shape[0]

    def positions(self, source_positions: np.ndarray) -> np.ndarray:
        """(V, 3) vertices from (Vs, 3) source positions."""
        return np.asarray(self.source @ source_positions)


def triangulate_quads(quads: np.ndarray, quad_uvs: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split each quad (a, b, c, d) along its shorter diagonal; returns faces (2F, 3), face_uvs (2F, 3)."""
    p = positions[quads]
    d02 = np.linalg.norm(p[:, 0] - p[:, 2], axis=1)
    d13 = np.linalg.norm(p[:, 1] - p[:, 3], axis=1)
    use02 = (d02 <= d13)[:, None]
    a = np.where(use02, quads[:, [0, 1, 2]], quads[:, [0, 1, 3]])
    b = np.where(use02, quads[:, [0, 2, 3]], quads[:, [1, 2, 3]])
    ta = np.where(use02, quad_uvs[:, [0, 1, 2]], quad_uvs[:, [0, 1, 3]])
    tb = np.where(use02, quad_uvs[:, [0, 2, 3]], quad_uvs[:, [1, 2, 3]])
    return np.concatenate([a, b]), np.concatenate([ta, tb])


def select_components(outfit: OutfitSource, components: tuple[int, ...], expected_vertices: tuple[int, ...]) -> GarmentMesh:
    """Cut the chosen connected components out of an outfit and triangulate them.

    components        : component labels (``quad_components`` order)
    expected_vertices : their vertex counts, checked so that a changed source fails loudly
    """
    label = quad_components(outfit.quads, len(outfit.vertices))
    faces_l, uvs_l, piece_of_face = [], [], []
    for k, (c, n) in enumerate(zip(components, expected_vertices)):
        if int(np.sum(label == c)) != n:
            raise ValueError(f"{outfit.name}: component {c} has {np.sum(label == c)} vertices, expected {n}")
        keep = label[outfit.quads[:, 0]] == c
        f, ft = triangulate_quads(outfit.quads[keep], outfit.quad_uvs[keep], outfit.vertices)
        faces_l.append(f)
        uvs_l.append(ft)
        piece_of_face.append(np.full(len(f), k))
    faces, face_uvs = np.concatenate(faces_l), np.concatenate(uvs_l)
    vids, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    tids, face_uvs = np.unique(face_uvs, return_inverse=True)
    piece = np.zeros(len(vids), np.int64)
    piece[faces.ravel()] = np.repeat(np.concatenate(piece_of_face), 3)
    source = sp.csr_matrix((np.ones(len(vids)), (np.arange(len(vids)), vids)), shape=(len(vids), len(outfit.vertices)))
    return GarmentMesh(faces, outfit.uvs[tids], face_uvs.reshape(-1, 3), source, piece)


def merge_vertices(mesh: GarmentMesh, groups: np.ndarray) -> GarmentMesh:
    """Merge vertices with equal ``groups`` label (V,) into one, the average of their sources.

    Faces that become degenerate or duplicate are removed. Vertices keep their relative order.
    """
    _, first, new_id = np.unique(groups, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # keep the original vertex order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    new_id = rank[new_id]
    n = len(order)
    counts = np.bincount(new_id, minlength=n)
    M = sp.csr_matrix((1.0 / counts[new_id], (new_id, np.arange(len(new_id)))), shape=(n, len(new_id)))
    faces = new_id[mesh.faces]
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    _, first_face = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    unique_face = np.zeros(len(faces), bool)
    unique_face[first_face] = True
    ok &= unique_face  # two faces over the same 3 vertices: keep the first
    piece = np.zeros(n, np.int64)
    piece[new_id] = mesh.piece
    return GarmentMesh(faces[ok], mesh.uvs, mesh.face_uvs[ok], sp.csr_matrix(M @ mesh.source), piece)


def weld_duplicates(mesh: GarmentMesh, positions: np.ndarray, tol: float) -> GarmentMesh:
    """Weld vertices closer than ``tol`` (positions' units) by grid rounding."""
    key = np.round(positions / tol).astype(np.int64)
    _, groups = np.unique(key, axis=0, return_inverse=True)
    return merge_vertices(mesh, groups.ravel())


def collapse_short_edges(mesh: GarmentMesh, positions: np.ndarray, min_length: float) -> GarmentMesh:
    """Merge the ends of every edge shorter than ``min_length`` (clusters joined transitively) into
    their average, and drop the faces that degenerate: removes sliver strips (narrow hem and
    pocket-flap bands) that would be near-singular elements for the cloth model."""
    e = unique_edges(mesh.faces)
    short = e[np.linalg.norm(positions[e[:, 0]] - positions[e[:, 1]], axis=1) < min_length]
    n = mesh.n_vertices
    A = sp.coo_matrix((np.ones(len(short)), (short[:, 0], short[:, 1])), shape=(n, n))
    return merge_vertices(mesh, connected_components(A, directed=False)[1])


def remove_faces(mesh: GarmentMesh, keep: np.ndarray) -> GarmentMesh:
    """Keep faces where ``keep`` (F,) is true; drop vertices and UVs no face uses."""
    faces, face_uvs = mesh.faces[keep], mesh.face_uvs[keep]
    vids, faces = np.unique(faces, return_inverse=True)
    tids, face_uvs = np.unique(face_uvs, return_inverse=True)
    return GarmentMesh(faces.reshape(-1, 3), mesh.uvs[tids], face_uvs.reshape(-1, 3), mesh.source[vids], mesh.piece[vids])


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Sorted unique undirected edges (E, 2) of a triangle mesh, lexicographic order."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def subdivide(mesh: GarmentMesh, face_mask: np.ndarray | None = None) -> GarmentMesh:
    """Midpoint 1-to-4 split of the masked faces (all by default); no smoothing (positions stay on the surface).

    The masked faces must not share an edge with unmasked ones (no T-junctions): subdivide a
    whole connected piece. A new vertex is the mean of its edge's ends, in position, in UV and
    in source (hence in binding).
    """
    F = len(mesh.faces)
    mask = np.ones(F, bool) if face_mask is None else np.asarray(face_mask, bool)
    sub, sub_t = mesh.faces[mask], mesh.face_uvs[mask]
    if face_mask is not None:
        inside = {tuple(e) for e in unique_edges(sub)}
        outside = {tuple(e) for e in unique_edges(mesh.faces[~mask])}
        if inside & outside:
            raise ValueError("subdivide: masked faces share edges with unmasked faces (T-junctions)")

    def split(f: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        # midpoint id of each of the 3 edges (ab, bc, ca) per face, numbered after the n old ids
        e = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1), axis=2)  # (F, 3, 2)
        uniq, inv = np.unique(e.reshape(-1, 2), axis=0, return_inverse=True)
        return uniq, n + inv.reshape(-1, 3)

    V, Vt = mesh.n_vertices, len(mesh.uvs)
    edges, mid = split(sub, V)
    tedges, tmid = split(sub_t, Vt)
    a, b, c = sub.T
    ab, bc, ca = mid.T
    new_faces = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    ta, tb, tc = sub_t.T
    tab, tbc, tca = tmid.T
    new_tfaces = np.concatenate([np.stack(x, 1) for x in ((ta, tab, tca), (tab, tb, tbc), (tca, tbc, tc), (tab, tbc, tca))])
    # midpoint = (end0 + end1) / 2
    E = len(edges)
    rows = np.concatenate([np.arange(V), V + np.repeat(np.arange(E), 2)])
    cols = np.concatenate([np.arange(V), edges.ravel()])
    vals = np.concatenate([np.ones(V), np.full(2 * E, 0.5)])
    S = sp.csr_matrix((vals, (rows, cols)), shape=(V + E, V))
    uvs = np.concatenate([mesh.uvs, 0.5 * (mesh.uvs[tedges[:, 0]] + mesh.uvs[tedges[:, 1]])])
    piece = np.concatenate([mesh.piece, mesh.piece[edges[:, 0]]])
    out = GarmentMesh(
        np.concatenate([mesh.faces[~mask], new_faces]),
        uvs,
        np.concatenate([mesh.face_uvs[~mask], new_tfaces]),
        sp.csr_matrix(S @ mesh.source),
        piece,
    )
    # drop midpoints of UV edges that only unmasked faces use (none) and keep ids compact
    return remove_faces(out, np.ones(len(out.faces), bool))


# ---------------------------------------------------------------------------- topology
def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Boundary loops of a manifold triangle mesh, each an ordered vertex array.

    Each loop follows the faces' orientation (boundary edge a->b as it appears in its face).
    Loops are returned longest first, ties by smallest vertex id.
    """
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    und = np.sort(directed, axis=1)
    _, inv, cnt = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    bnd = directed[cnt[inv.ravel()] == 1]
    nxt = {}
    for a, b in bnd:
        if a in nxt:
            raise ValueError("boundary_loops: non-manifold boundary vertex")
        nxt[int(a)] = int(b)
    loops, seen = [], set()
    for s in sorted(nxt):
        if s in seen:
            continue
        loop, cur = [], s
        while cur not in seen:
            seen.add(cur)
            loop.append(cur)
            cur = nxt[cur]
        loops.append(np.array(loop))
    loops.sort(key=lambda l: (-len(l), int(l.min())))
    return loops


def orient_consistently(mesh: GarmentMesh) -> GarmentMesh:
    """Flip faces so that every shared edge is traversed in opposite directions (BFS per component).

    Starts each component from its lowest-numbered face; raises on a non-orientable mesh.
    """
    faces = mesh.faces.copy()
    face_uvs = mesh.face_uvs.copy()
    F = len(faces)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    face_of = np.tile(np.arange(F), 3)
    und = np.sort(directed, axis=1)
    _, inv = np.unique(und, axis=0, return_inverse=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    pairs = order.reshape(-1)  # group half-edges per undirected edge
    groups = np.split(pairs, np.flatnonzero(np.diff(inv[order])) + 1)
    adj = defaultdict(list)  # face -> (neighbour, same_direction)
    for g in groups:
        if len(g) == 2:
            h0, h1 = g
            same = bool(np.all(directed[h0] == directed[h1]))
            f0, f1 = face_of[h0], face_of[h1]
            adj[f0].append((f1, same))
            adj[f1].append((f0, same))
        elif len(g) > 2:
            raise ValueError("orient_consistently: non-manifold edge")
    flip = np.full(F, -1)
    for start in range(F):
        if flip[start] >= 0:
            continue
        flip[start] = 0
        stack = [start]
        while stack:
            f = stack.pop()
            for g, same in adj[f]:
                want = flip[f] ^ int(same)
                if flip[g] < 0:
                    flip[g] = want
                    stack.append(g)
                elif flip[g] != want:
                    raise ValueError("orient_consistently: mesh is not orientable")
    flipped = flip == 1
    faces[flipped] = faces[flipped][:, ::-1]
    face_uvs[flipped] = face_uvs[flipped][:, ::-1]
    return replace(mesh, faces=faces, face_uvs=face_uvs)


def orientation_patches(faces: np.ndarray) -> np.ndarray:
    """Label (F,) of the patches of consistently wound faces: faces joined across an edge only
    when they traverse it in opposite directions (a folded-over collar modelled with reversed
    winding is its own patch). Labels in order of the patch's first face."""
    F = len(faces)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    face_of = np.tile(np.arange(F), 3)
    # opposite half-edges a->b / b->a join their faces; equal ones (a->b twice) do not
    fwd = {(int(a), int(b)): int(f) for (a, b), f in zip(directed, face_of)}
    rows, cols = [], []
    for (a, b), f in fwd.items():
        g = fwd.get((b, a))
        if g is not None:
            rows.append(f)
            cols.append(g)
    A = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(F, F))
    return connected_components(A, directed=False)[1]


def face_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected component label (F,) of each face."""
    lab = quad_components(faces, n_vertices)
    return lab[faces[:, 0]]


def orient_outward(mesh: GarmentMesh, positions: np.ndarray, outward: np.ndarray) -> GarmentMesh:
    """Flip whole components so that face normals agree with ``outward`` (V, 3) directions by area-weighted vote."""
    p = positions[mesh.faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 * area
    vote = np.einsum("fc,fc->f", n, outward[mesh.faces].mean(1))
    comp = face_components(mesh.faces, mesh.n_vertices)
    faces, face_uvs = mesh.faces.copy(), mesh.face_uvs.copy()
    for c in np.unique(comp):
        m = comp == c
        if vote[m].sum() < 0:
            faces[m] = faces[m][:, ::-1]
            face_uvs[m] = face_uvs[m][:, ::-1]
    return replace(mesh, faces=faces, face_uvs=face_uvs)


def bridge_loops(mesh: GarmentMesh, loop_a: np.ndarray, loop_b: np.ndarray, positions: np.ndarray, centre: np.ndarray) -> GarmentMesh:
    """Stitch two closed boundary loops around a vertical axis with a strip of triangles.

    loop_a, loop_b : vertex ids of two loops (any start, any direction), each going once
                     around the vertical axis through ``centre`` (2,) (x, y), metres
    positions      : (V, 3) vertex positions, Z-up
    The strip is zipped by azimuth (advance the loop whose next vertex comes first); its faces
    are oriented to match the faces of loop_a and take each vertex's UV from a face using it.
    """
    def by_azimuth(loop):
        az = np.arctan2(positions[loop, 1] - centre[1], positions[loop, 0] - centre[0])
        # make the loop run counter-clockwise seen from above, start at the smallest azimuth
        turn = np.sum(np.angle(np.exp(1j * np.diff(np.append(az, az[0])))))
        if turn < 0:
            loop, az = loop[::-1], az[::-1]
        s = int(np.argmin(az))
        loop, az = np.roll(loop, -s), np.roll(az, -s)
        az = np.unwrap(az)
        if np.any(np.diff(az) <= 0):
            raise ValueError("bridge_loops: loop is not monotonic in azimuth")
        return loop, az

    A, aa = by_azimuth(np.asarray(loop_a))
    Bl, ab = by_azimuth(np.asarray(loop_b))
    A, aa = np.append(A, A[0]), np.append(aa, aa[0] + 2 * np.pi)
    Bl, ab = np.append(Bl, Bl[0]), np.append(ab, ab[0] + 2 * np.pi)
    # both loops start at their smallest azimuth (near -pi): zip them in one sweep
    tris = []
    i = j = 0
    while i < len(A) - 1 or j < len(Bl) - 1:
        adv_a = j == len(Bl) - 1 or (i < len(A) - 1 and aa[i + 1] <= ab[j + 1])
        if adv_a:
            tris.append((A[i], A[i + 1], Bl[j]))
            i += 1
        else:
            tris.append((A[i], Bl[j + 1], Bl[j]))
            j += 1
    tris = np.array(tris, np.int64)
    # orientation: loop_a's boundary edges must be traversed opposite to its own faces
    directed = {(int(f[k]), int(f[(k + 1) % 3])) for f in mesh.faces for k in range(3)}
    a0, a1 = int(A[0]), int(A[1])
    if (a0, a1) in directed:  # our strip uses a0->a1 too: reverse the strip
        tris = tris[:, ::-1]
    # a UV corner per vertex: the first face corner that uses it
    used, first = np.unique(mesh.faces.ravel(), return_index=True)
    corner_uv = np.full(mesh.n_vertices, -1)
    corner_uv[used] = mesh.face_uvs.ravel()[first]
    tuvs = corner_uv[tris]
    return replace(mesh, faces=np.concatenate([mesh.faces, tris]), face_uvs=np.concatenate([mesh.face_uvs, tuvs]))


def binding_arrays(mesh: GarmentMesh, outfit: OutfitSource) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Padded sparse binding of the mesh vertices: indices (V, K) int32, weights (V, K) float32, offsets (V, 3) float32.

    binding = source @ outfit.binding (exact), offsets = source @ outfit.offsets; padding
    entries have index 0 and weight 0; indices ascending per row.
    """
    Bm = sp.csr_matrix(mesh.source @ outfit.binding)
    Bm.sum_duplicates()
    Bm.sort_indices()
    Bm.eliminate_zeros()
    counts = np.diff(Bm.indptr)
    K = int(counts.max())
    V = Bm.shape[0]
    idx = np.zeros((V, K), np.int32)
    w = np.zeros((V, K), np.float32)
    rows = np.repeat(np.arange(V), counts)
    cols = np.arange(len(Bm.indices)) - np.repeat(Bm.indptr[:-1], counts)
    idx[rows, cols] = Bm.indices
    w[rows, cols] = Bm.data
    offsets = np.asarray(mesh.source @ outfit.offsets, np.float32)
    return idx, w, offsets


def vertex_adjacency(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Symmetric 0/1 vertex adjacency (V, V) of a triangle mesh."""
    e = unique_edges(faces)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]]))), shape=(n_vertices, n_vertices))
    return sp.csr_matrix(A)


def graph_distance_from(faces: np.ndarray, n_vertices: int, seeds: np.ndarray) -> np.ndarray:
    """Hop count (V,) from the nearest seed vertex over mesh edges (inf where unreachable)."""
    A = vertex_adjacency(faces, n_vertices)
    dist = np.full(n_vertices, np.inf)
    frontier = np.zeros(n_vertices, bool)
    frontier[seeds] = True
    dist[seeds] = 0
    d = 0
    while frontier.any():
        d += 1
        reach = (A @ frontier.astype(np.float64)) > 0
        frontier = reach & ~np.isfinite(dist)
        dist[frontier] = d
    return dist


__all__ = [
    "OutfitSource", "GarmentMesh", "load_outfit", "read_obj", "read_mhclo", "quad_components",
    "select_components", "merge_vertices", "weld_duplicates", "collapse_short_edges", "remove_faces", "unique_edges",
    "subdivide", "boundary_loops", "orient_consistently", "orientation_patches", "orient_outward", "face_components",
    "bridge_loops", "binding_arrays", "vertex_adjacency", "graph_distance_from",
]
