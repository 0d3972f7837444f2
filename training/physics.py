"""Cloth physics energies (thesis ch. 5.2.2-5.2.4, SNUG), batched torch, one function per energy.

The backward-Euler step of eq. 5.3 is the minimiser of eq. 5.4,

    x^{t+1} = argmin_x  1/(2 dt^2) (x - x_hat)^T M (x - x_hat) + Phi(x),   x_hat = x^t + dt v^t,

and SNUG's loss (eq. 5.5) is that objective: L = L_inertia (eq. 5.6) + L_static (eq. 5.7), with
L_static = L_strain (eq. 5.8-5.9) + L_bending (eq. 5.10) + L_gravity (eq. 5.11) + L_collision
(eq. 5.12). The same functions serve the physics reference (``training.simulate``) and the
self-supervised training losses.

Discretisation (``ClothGeometry``, precomputed once per garment from its rest geometry):
- strain: linear triangles; each rest triangle is flattened into its own plane, X in R^2
  (eq. 5.8's undeformed X), Dm = [X1 - X0, X2 - X0] (2 x 2); F = Ds Dm^-1 (3 x 2) with
  Ds = [x1 - x0, x2 - x0]; G = (F^T F - I) / 2; triangle volume = rest area x thickness.
- bending: per interior edge (shared by exactly two triangles) the dihedral angle theta,
  k_scale = l^2 / (4 (a1 + a2)) from the rest edge length and rest areas (eq. 5.10). The
  garments' rest shape is curved (a template on a body), so the energy is taken relative to the
  rest dihedral angle, (theta - theta_rest)^2 / 2: zero at rest, eq. 5.10 exactly for a flat rest.
- masses: lumped, density x thickness x area / 3 to each corner of every triangle.
- collision: d(x) is SNUG's approximation of the signed distance to the posed body, the
  distance to the tangent plane of the closest body vertex, (x - b_c) . n_c, with c the closest
  body vertex among KD-tree candidates (or all body vertices for small meshes). Options for
  solvers: a soft-min blend of the candidates' planes (``smoothing_m``: smooth in x, where the
  closest-vertex d jumps between neighbouring planes) and a per-vertex ``active`` mask.

Hessians (``*_hessian``): per-element positive semi-definite approximations for Newton solvers
(StVK Gauss-Newton + clamped geometric stiffness or the exact one, bending Gauss-Newton,
exact collision blocks); the mass term of eq. 5.6 is M / dt^2.

Units: SI throughout (metres, kg, seconds, Pa, J, radians); gravity is -Z, 9.81 m/s^2.
Arrays: positions (B, V, 3), batch axis first; every energy returns (B,) joules. The dtype of
the positions must match the geometry's (float32 or float64, chosen in ``ClothGeometry``).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

log = logging.getLogger(__name__)

GRAVITY_M_S2 = 9.81
# Gravitational acceleration g of eq. 5.11, m/s^2, Z-up world (anny body, DESIGN.md §2).
GRAVITY_VECTOR = (0.0, 0.0, -GRAVITY_M_S2)
# Squared-length floor under the square roots of the dihedral angle (m^4 for face normals,
# m^2 for the edge): keeps gradients finite for collapsed triangles and zero-length edges.
_LENGTH2_FLOOR = 1e-30
# A hinge whose (sin, cos) pair is shorter than this is degenerate (a collapsed triangle):
# its angle is taken as 0 with a zero gradient instead of atan2(0, 0).
_DEGENERATE_HINGE = 0.25
# Rest triangles with less area than this (m^2) cannot be flattened (rank-deficient Dm).
_MIN_REST_AREA_M2 = 1e-14

# Collision stiffness of the *training* loss (J/m^3), 400x SNUG's k_collision = 250. With 250 the
# equilibrium of eq. 5.7 lies inside the body wherever the cloth is under tension: a 13 % strain
# around a 4 cm limb presses a vertex with ~0.05 N, which the cubic penalty 3 k (eps - d)^2 only
# balances at eps - d ~ 8 mm, i.e. 6 mm inside; tight garments on the heaviest bodies press with
# ~1 N. Measured on the T-shirt fit (3 min, 20 held-out shapes): inside fraction 9.8 % with 250,
# 0.31 % with 1e4, 0.004 % with 1e5 (static energy still 23 % below the retarget's). The metrics
# keep the physical value (the garment's material).
TRAIN_K_COLLISION = 1.0e5


@dataclass(frozen=True)
class ClothMaterial:
    """Material of eq. 5.8-5.12 (SNUG values, thesis ch. 5.3.1).

    density_kg_m3      : fabric density, kg/m^3 (cotton: 426)
    thickness_m        : fabric thickness, m (0.47 mm)
    lame_lambda_pa     : Lame lambda of the StVK membrane, Pa
    lame_mu_pa         : Lame mu of the StVK membrane, Pa
    k_bend             : bending stiffness of eq. 5.10, J (N m per rad^2; k_scale is unitless)
    k_collision        : collision stiffness of eq. 5.12, J/m^3
    collision_margin_m : safety margin epsilon of eq. 5.12, m
    """

    density_kg_m3: float = 426.0
    thickness_m: float = 0.47e-3
    lame_lambda_pa: float = 4.44e4
    lame_mu_pa: float = 2.36e4
    k_bend: float = 3.96e-5
    k_collision: float = 250.0
    collision_margin_m: float = 0.002

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f"material.{f.name}: expected a finite value >= 0, got {value}")
        if self.density_kg_m3 <= 0 or self.thickness_m <= 0:
            raise ValueError("material: density and thickness must be > 0 (vertex masses)")

    @classmethod
    def from_dict(cls, material: dict) -> "ClothMaterial":
        """From a garment's ``garment.json`` ``material`` (same key names); unknown keys are an error."""
        names = {f.name for f in fields(cls)}
        unknown = set(material) - names
        if unknown:
            raise ValueError(f"material: unknown keys {sorted(unknown)}; expected a subset of {sorted(names)}")
        return cls(**{k: float(v) for k, v in material.items()})


# ------------------------------------------------------------------------------ precompute
def rest_triangle_frames(rest_vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each rest triangle flattened into its own plane (eq. 5.8's X in R^2): Dm^-1 and area.

    In the frame u = e1/|e1|, w = (n x e1)/|n x e1| of triangle (X0, X1, X2), e1 = X1 - X0,
    e2 = X2 - X0: Dm = [[|e1|, e2.u], [0, e2.w]] (columns X1 - X0, X2 - X0 in R^2).

    rest_vertices : (V, 3) float, metres ; faces : (F, 3) int
    returns       : dm_inv (F, 2, 2) float64 (1/m), rest_area (F,) float64 (m^2)
    """
    X = np.asarray(rest_vertices, np.float64)
    f = np.asarray(faces, np.int64)
    e1 = X[f[:, 1]] - X[f[:, 0]]
    e2 = X[f[:, 2]] - X[f[:, 0]]
    n = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(n, axis=1)
    if (area < _MIN_REST_AREA_M2).any():
        bad = np.flatnonzero(area < _MIN_REST_AREA_M2)
        raise ValueError(f"faces {bad[:10].tolist()}: rest area below {_MIN_REST_AREA_M2} m^2 (degenerate triangles)")
    l1 = np.linalg.norm(e1, axis=1)
    u = e1 / l1[:, None]
    w = np.cross(n, e1)
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    dm = np.zeros((len(f), 2, 2))
    dm[:, 0, 0] = l1
    dm[:, 0, 1] = np.einsum("fc,fc->f", e2, u)
    dm[:, 1, 1] = np.einsum("fc,fc->f", e2, w)
    return np.linalg.inv(dm), area


def interior_hinges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interior edges (shared by exactly two triangles) with their two opposite vertices.

    faces   : (F, 3) int
    returns : hinges (H, 4) int64 rows (i, j, k, l): edge i-j (i < j), k opposite in one
              triangle, l in the other; hinge_faces (H, 2) int64, the two triangles.
    Border edges (one triangle) have no hinge; non-manifold edges (> 2) are skipped with a warning.
    """
    f = np.asarray(faces, np.int64)
    F = len(f)
    edges = f[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)  # (3F, 2), edge c of face f at 3 f + c
    opposite = f[:, [2, 0, 1]].reshape(-1)
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    if (counts > 2).any():
        log.warning("interior_hinges: %d non-manifold edges skipped", int((counts > 2).sum()))
    rows = np.flatnonzero(counts[inverse] == 2)
    rows = rows[np.argsort(inverse[rows], kind="stable")]  # the two rows of a hinge are adjacent
    a, b = rows[0::2], rows[1::2]
    hinges = np.stack([key[a, 0], key[a, 1], opposite[a], opposite[b]], axis=1)
    hinge_faces = np.stack([a // 3, b // 3], axis=1)
    assert hinge_faces.max(initial=-1) < F
    return hinges, hinge_faces


def lumped_vertex_masses(faces: np.ndarray, rest_area_m2: np.ndarray, num_vertices: int, density_kg_m3: float, thickness_m: float) -> np.ndarray:
    """Lumped mass matrix diagonal of eq. 5.4/5.6: m_v = sum_{f ∋ v} density thickness area_f / 3.

    faces : (F, 3) int ; rest_area_m2 : (F,) ; returns (V,) float64, kg
    """
    m = np.zeros(num_vertices)
    np.add.at(m, np.asarray(faces, np.int64).ravel(), np.repeat(density_kg_m3 * thickness_m * rest_area_m2 / 3.0, 3))
    return m


@dataclass(frozen=True)
class ClothGeometry:
    """Per-garment constants of the energies, as torch tensors of one dtype.

    faces              : (F, 3) int64
    dm_inv             : (F, 2, 2) 1/m, inverse rest matrices of the flattened rest triangles
    rest_area_m2       : (F,) m^2
    vertex_mass_kg     : (V,) kg, lumped
    hinges             : (H, 4) int64 (i, j, k, l): interior edge i-j, opposite vertices k, l
    k_scale            : (H,) unitless, l^2 / (4 (a1 + a2)) (eq. 5.10)
    rest_dihedral_rad  : (H,) rad, dihedral angle of the rest geometry
    material           : ClothMaterial
    """

    faces: torch.Tensor
    dm_inv: torch.Tensor
    rest_area_m2: torch.Tensor
    vertex_mass_kg: torch.Tensor
    hinges: torch.Tensor
    k_scale: torch.Tensor
    rest_dihedral_rad: torch.Tensor
    material: ClothMaterial
    collision_depth_cap_m: float | None = None  # training only: eq. 5.12 continued linearly beyond this depth

    @classmethod
    def from_mesh(cls, rest_vertices: np.ndarray, faces: np.ndarray, material: ClothMaterial | dict, dtype: torch.dtype = torch.float64) -> "ClothGeometry":
        """Precompute from the rest geometry (V, 3) metres and faces (F, 3) (computed in float64)."""
        if isinstance(material, dict):
            material = ClothMaterial.from_dict(material)
        X = np.asarray(rest_vertices, np.float64)
        f = np.asarray(faces, np.int64)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError(f"rest_vertices: expected shape (V, 3), got {X.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"faces: expected shape (F, 3) with F > 0, got {f.shape}")
        if f.min() < 0 or f.max() >= len(X):
            raise ValueError(f"faces: indices must lie in [0, {len(X)}), got [{f.min()}, {f.max()}]")
        dm_inv, area = rest_triangle_frames(X, f)
        hinges, hinge_faces = interior_hinges(f)
        edge_len2 = np.sum((X[hinges[:, 1]] - X[hinges[:, 0]]) ** 2, axis=1)
        k_scale = edge_len2 / (4.0 * area[hinge_faces].sum(axis=1))  # eq. 5.10: l^2 / (4 (a1 + a2))
        rest_angle = dihedral_angles(torch.as_tensor(X[None]), torch.as_tensor(hinges))[0].numpy()
        mass = lumped_vertex_masses(f, area, len(X), material.density_kg_m3, material.thickness_m)

        def t(a):
            return torch.as_tensor(a, dtype=dtype)

        return cls(
            faces=torch.as_tensor(f),
            dm_inv=t(dm_inv),
            rest_area_m2=t(area),
            vertex_mass_kg=t(mass),
            hinges=torch.as_tensor(hinges),
            k_scale=t(k_scale),
            rest_dihedral_rad=t(rest_angle),
            material=material,
        )

    @classmethod
    def from_asset(cls, asset, dtype: torch.dtype = torch.float64) -> "ClothGeometry":
        """From an ``inference.garment.GarmentAsset``: its ``rest_vertices``, ``faces`` and ``material``."""
        return cls.from_mesh(asset.rest_vertices, asset.faces, ClothMaterial.from_dict(asset.material), dtype)

    @property
    def dtype(self) -> torch.dtype:
        return self.dm_inv.dtype

    def with_collision_stiffness(self, k_collision: float | None, depth_cap_m: float | None = None, margin_m: float | None = None) -> "ClothGeometry":
        """The same cloth with k_collision of eq. 5.12 replaced (J/m^3; None keeps the material's)
        and, with ``depth_cap_m``, the penalty continued linearly (force capped at 3 k cap^2)
        beyond that depth below the margin: LBS squeezes (an arm sunk into the torso) leave
        vertices that no displacement can free, and the cubic's unbounded force there swamps the
        other terms. ``margin_m`` replaces eps of eq. 5.12 (metres; None keeps the material's):
        a wider training margin keeps a network's prediction error outside the body (training
        only; the physical energy keeps the material's k, eps and no cap)."""
        material = self.material
        if k_collision is not None:
            material = replace(material, k_collision=float(k_collision))
        if margin_m is not None:
            material = replace(material, collision_margin_m=float(margin_m))
        cloth = replace(self, material=material) if material is not self.material else self
        return cloth if depth_cap_m is None else replace(cloth, collision_depth_cap_m=float(depth_cap_m))

    def to(self, device: torch.device | str) -> "ClothGeometry":
        """The same cloth with its tensors on ``device`` (training on a GPU)."""
        moved = {f.name: getattr(self, f.name).to(device) for f in fields(self) if isinstance(getattr(self, f.name), torch.Tensor)}
        return replace(self, **moved)

    @property
    def num_vertices(self) -> int:
        return int(self.vertex_mass_kg.shape[0])

    @property
    def total_mass_kg(self) -> float:
        return float(self.vertex_mass_kg.sum())


def _check_positions(cloth: ClothGeometry, x: torch.Tensor, name: str = "x") -> None:
    if x.ndim != 3 or x.shape[1:] != (cloth.num_vertices, 3):
        raise ValueError(f"{name}: expected shape (B, {cloth.num_vertices}, 3), got {tuple(x.shape)}")
    if x.dtype != cloth.dtype:
        raise ValueError(f"{name}: dtype {x.dtype} differs from the geometry's {cloth.dtype}")


# ------------------------------------------------------------------------------ kinematics
def deformation_gradients(x: torch.Tensor, faces: torch.Tensor, dm_inv: torch.Tensor) -> torch.Tensor:
    """F = Ds Dm^-1 per triangle, Ds = [x1 - x0, x2 - x0] (eq. 5.8's F = dx/dX).

    x : (B, V, 3) metres ; faces : (F, 3) ; dm_inv : (F, 2, 2) 1/m
    returns (B, F, 3, 2) unitless
    """
    x0, x1, x2 = x[:, faces[:, 0]], x[:, faces[:, 1]], x[:, faces[:, 2]]
    ds = torch.stack([x1 - x0, x2 - x0], dim=-1)  # (B, F, 3, 2)
    # F[b, f, c, j] = sum_i ds[b, f, c, i] dm_inv[f, i, j]
    return torch.einsum("bfci,fij->bfcj", ds, dm_inv)


def hinge_angles(hx: torch.Tensor) -> torch.Tensor:
    """Signed dihedral angle theta of hinges given by their corners (eq. 5.10), robust: no NaN value or gradient.

    For edge e = x_j - x_i with opposite vertices k, l: n1 = e x (x_k - x_i),
    n2 = (x_l - x_i) x e (both = the common normal when the two triangles are coplanar and k, l
    lie on opposite sides, whatever the faces' winding), normalised; then
    theta = atan2((n1 x n2) . e/|e|, n1 . n2) in (-pi, pi], 0 when flat. A collapsed triangle
    gives theta = 0 with a zero gradient.

    hx : (..., 4, 3) metres, corners (x_i, x_j, x_k, x_l) ; returns (...) radians
    """
    xi, xj, xk, xl = hx.unbind(-2)
    e = xj - xi
    n1 = torch.linalg.cross(e, xk - xi)
    n2 = torch.linalg.cross(xl - xi, e)
    # n / sqrt(|n|^2 + floor): unit for real triangles, 0 (finite gradient) for collapsed ones
    n1 = n1 / torch.sqrt((n1 * n1).sum(-1, keepdim=True) + _LENGTH2_FLOOR)
    n2 = n2 / torch.sqrt((n2 * n2).sum(-1, keepdim=True) + _LENGTH2_FLOOR)
    e_hat = e / torch.sqrt((e * e).sum(-1, keepdim=True) + _LENGTH2_FLOOR)
    cos = (n1 * n2).sum(-1)
    sin = (torch.linalg.cross(n1, n2) * e_hat).sum(-1)
    degenerate = cos * cos + sin * sin < _DEGENERATE_HINGE
    return torch.atan2(torch.where(degenerate, torch.zeros_like(sin), sin), torch.where(degenerate, torch.ones_like(cos), cos))


def dihedral_angles(x: torch.Tensor, hinges: torch.Tensor) -> torch.Tensor:
    """Dihedral angle per hinge (``hinge_angles``). x : (B, V, 3) metres ; hinges : (H, 4) ; returns (B, H) radians."""
    return hinge_angles(x[:, hinges])


def _wrapped_bend(theta: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """theta - theta_rest wrapped into (-pi, pi]."""
    delta = theta - rest
    return delta - (2.0 * torch.pi) * torch.round(delta / (2.0 * torch.pi))


def closest_body_vertices(x: torch.Tensor, body_points: torch.Tensor, candidates: torch.Tensor | None = None) -> torch.Tensor:
    """Index of the closest body vertex of every garment vertex, (B, V) int64 (not differentiable).

    x : (B, V, 3) ; body_points : (B, M, 3) ; candidates : (B, V, k) or (V, k) int64 indices
    into the body to choose among (KD-tree, ``training.candidates.body_candidates``), or None: all M body vertices
    (a (B, V, M) distance matrix: small meshes only)
    """
    B, V = x.shape[:2]
    if body_points.ndim != 3 or body_points.shape[0] != B or body_points.shape[-1] != 3:
        raise ValueError(f"body_points: expected shape (B={B}, M, 3), got {tuple(body_points.shape)}")
    with torch.no_grad():
        if candidates is None:
            return torch.cdist(x, body_points).argmin(dim=-1)
        cand = candidates if candidates.ndim == 3 else candidates.expand(B, -1, -1)
        if cand.shape[:2] != (B, V):
            raise ValueError(f"candidates: expected shape (B, {V}, k) or ({V}, k), got {tuple(candidates.shape)}")
        batch = torch.arange(B, device=x.device)[:, None, None]
        d2 = ((body_points[batch, cand] - x[:, :, None]) ** 2).sum(-1)  # (B, V, k)
        return torch.gather(cand, 2, d2.argmin(dim=-1, keepdim=True))[..., 0]


def body_signed_distances(x: torch.Tensor, body_points: torch.Tensor, body_normals: torch.Tensor, candidates: torch.Tensor | None = None, smoothing_m: float | None = None) -> torch.Tensor:
    """SNUG's approximate signed distance to the posed body (eq. 5.12's d(x)), metres.

    d(x_v) = (x_v - b_c) . n_c with c the closest body vertex to x_v (``closest_body_vertices``:
    among its candidates, or among all body vertices when candidates is None). The choice of c
    is not differentiated; d is, with respect to x and the body. A (B, V, 1) candidate list fixes
    c (a contact plane per vertex).

    smoothing_m: instead of the closest candidate's plane, a soft-min blend of the candidates'
    planes, d = sum_j w_j (x - b_j) . n_j with w = softmax(-|x - b_j|^2 / smoothing_m^2): smooth
    in x (the closest-vertex d jumps where the closest vertex changes, as neighbouring tangent
    planes differ), and the closest-vertex d as smoothing_m -> 0.

    x            : (B, V, 3) metres
    body_points  : (B, M, 3) metres, posed body vertices
    body_normals : (B, M, 3) unit outward vertex normals
    candidates   : (B, V, k) or (V, k) int64, or None (all M body vertices: small meshes only)
    returns      : (B, V)
    """
    if body_points.shape != body_normals.shape:
        raise ValueError(f"body_points/body_normals: shapes differ, {tuple(body_points.shape)} vs {tuple(body_normals.shape)}")
    if smoothing_m is not None:
        return _blended_planes(x, body_points, body_normals, candidates, smoothing_m)[0]
    closest = closest_body_vertices(x, body_points, candidates)
    batch = torch.arange(x.shape[0], device=x.device)[:, None]
    return ((x - body_points[batch, closest]) * body_normals[batch, closest]).sum(-1)


def _blended_planes(x, body_points, body_normals, candidates, smoothing_m):
    """Soft-min blend of candidate tangent planes: d (B, V) and the blended normal (B, V, 3)."""
    B, V = x.shape[:2]
    if candidates is None:
        cand = torch.arange(body_points.shape[1], device=x.device).expand(B, V, -1)
    else:
        cand = candidates if candidates.ndim == 3 else candidates.expand(B, -1, -1)
        if cand.shape[:2] != (B, V):
            raise ValueError(f"candidates: expected shape (B, {V}, k) or ({V}, k), got {tuple(candidates.shape)}")
    batch = torch.arange(B, device=x.device)[:, None, None]
    p, n = body_points[batch, cand], body_normals[batch, cand]  # (B, V, k, 3)
    r = x[:, :, None] - p
    w = torch.softmax(-(r * r).sum(-1) / (smoothing_m * smoothing_m), dim=-1)  # (B, V, k)
    d = (w * (r * n).sum(-1)).sum(-1)
    return d, (w[..., None] * n).sum(-2)


# ------------------------------------------------------------------------------ energies
def strain_energy(cloth: ClothGeometry, x: torch.Tensor) -> torch.Tensor:
    """Membrane strain energy, StVK (eq. 5.8-5.9): sum_f V_f Psi_S(G_f), joules.

    Psi_S = lambda/2 tr(G)^2 + mu tr(G^2) (J/m^3), G = (F^T F - I)/2, V_f = rest area x thickness.
    x : (B, V, 3) metres ; returns (B,)
    """
    _check_positions(cloth, x)
    F = deformation_gradients(x, cloth.faces, cloth.dm_inv)
    # C[b, f, i, j] = sum_c F[b, f, c, i] F[b, f, c, j]   (right Cauchy-Green F^T F)
    C = torch.einsum("bfci,bfcj->bfij", F, F)
    g00, g11, g01 = 0.5 * (C[..., 0, 0] - 1.0), 0.5 * (C[..., 1, 1] - 1.0), 0.5 * C[..., 0, 1]
    tr_g = g00 + g11
    tr_g2 = g00 * g00 + g11 * g11 + 2.0 * g01 * g01  # tr(G^2), G symmetric
    m = cloth.material
    psi = 0.5 * m.lame_lambda_pa * tr_g * tr_g + m.lame_mu_pa * tr_g2  # eq. 5.8
    return (psi * (cloth.rest_area_m2 * m.thickness_m)).sum(-1)  # eq. 5.9


def bending_energy(cloth: ClothGeometry, x: torch.Tensor) -> torch.Tensor:
    """Bending energy (eq. 5.10), relative to the rest shape: sum_e k_bend k_scale (theta - theta_rest)^2 / 2, joules.

    theta - theta_rest is wrapped into (-pi, pi]. x : (B, V, 3) metres ; returns (B,)
    """
    _check_positions(cloth, x)
    delta = _wrapped_bend(dihedral_angles(x, cloth.hinges), cloth.rest_dihedral_rad)
    return (cloth.material.k_bend * cloth.k_scale * 0.5 * delta * delta).sum(-1)  # eq. 5.10


def gravity_energy(cloth: ClothGeometry, x: torch.Tensor) -> torch.Tensor:
    """Gravitational potential (eq. 5.11): sum_v -m_v g^T x_v = sum_v m_v 9.81 z_v, joules (Z-up).

    x : (B, V, 3) metres ; returns (B,)
    """
    _check_positions(cloth, x)
    g = torch.tensor(GRAVITY_VECTOR, dtype=x.dtype, device=x.device)
    return -(cloth.vertex_mass_kg * (x @ g)).sum(-1)  # eq. 5.11


def collision_energy(cloth: ClothGeometry, x: torch.Tensor, body_points: torch.Tensor, body_normals: torch.Tensor, candidates: torch.Tensor | None = None, active: torch.Tensor | None = None, smoothing_m: float | None = None,
                     inside: torch.Tensor | None = None) -> torch.Tensor:
    """Body collision penalty (eq. 5.12): sum_v k_collision max(eps - d(x_v), 0)^3, joules.

    d from ``body_signed_distances`` (arguments as there); eps, k_collision from the material.
    active : optional (B, V) bool, vertices that collide (others are left out: e.g. garment
             vertices in the posed body's self-intersections, where the skin is no surface)
    inside : optional (B, V) bool, vertices an exact test found inside the body (the winding
             number of the closed posed skin, ``inference.winding``; not differentiated). The
             closest vertex's tangent plane misjudges a vertex pushed into an arm whose closest
             skin is the torso beside it (d > 0); for these d = min(d, -|x_v - b_c|), so the
             penalty pulls them toward their closest skin vertex b_c, out of the part they are in.
    returns (B,)
    """
    _check_positions(cloth, x)
    if inside is None:
        d = body_signed_distances(x, body_points, body_normals, candidates, smoothing_m)
    else:
        if inside.shape != x.shape[:2]:
            raise ValueError(f"inside: expected {tuple(x.shape[:2])}, got {tuple(inside.shape)}")
        if smoothing_m is not None:
            raise ValueError("inside: the exact test needs the closest vertex's plane (smoothing_m None)")
        closest = closest_body_vertices(x, body_points, candidates)
        batch = torch.arange(x.shape[0], device=x.device)[:, None]
        offset = x - body_points[batch, closest]
        d = (offset * body_normals[batch, closest]).sum(-1)
        d = torch.where(inside, torch.minimum(d, -torch.sqrt((offset * offset).sum(-1) + 1e-18)), d)
    m = cloth.material
    depth = torch.clamp(m.collision_margin_m - d, min=0.0)
    if active is not None:
        depth = depth * active.to(depth.dtype)
    cap = cloth.collision_depth_cap_m
    if cap is not None:  # k (c^3 + 3 c^2 (depth - c)) beyond the cap c: C1, force 3 k c^2
        capped = torch.clamp(depth, max=cap)
        return m.k_collision * (capped**3 + 3.0 * cap * cap * (depth - capped)).sum(-1)
    return m.k_collision * (depth * depth * depth).sum(-1)  # eq. 5.12


def inertia_energy(cloth: ClothGeometry, x: torch.Tensor, x_prev: torch.Tensor, x_prev2: torch.Tensor, dt_s: float) -> torch.Tensor:
    """Inertia term (eq. 5.6): 1/(2 dt^2) (x - x_hat)^T M (x - x_hat), joules.

    x_hat = x_prev + dt v_prev, v_prev = (x_prev - x_prev2)/dt (eq. 5.4), i.e. 2 x_prev - x_prev2.
    x, x_prev, x_prev2 : (B, V, 3) metres ; dt_s : seconds ; returns (B,)
    """
    for name, a in (("x", x), ("x_prev", x_prev), ("x_prev2", x_prev2)):
        _check_positions(cloth, a, name)
    if not dt_s > 0:
        raise ValueError(f"dt_s: expected > 0 seconds, got {dt_s}")
    r = x - (2.0 * x_prev - x_prev2)  # x - x_hat
    return (cloth.vertex_mass_kg * (r * r).sum(-1)).sum(-1) / (2.0 * dt_s * dt_s)  # eq. 5.6


def static_energy(cloth: ClothGeometry, x: torch.Tensor, body_points: torch.Tensor | None = None, body_normals: torch.Tensor | None = None, candidates: torch.Tensor | None = None) -> torch.Tensor:
    """L_static (eq. 5.7): strain + bending + gravity + collision (no collision without a body), (B,) J."""
    e = strain_energy(cloth, x) + bending_energy(cloth, x) + gravity_energy(cloth, x)
    if body_points is not None:
        e = e + collision_energy(cloth, x, body_points, body_normals, candidates)
    return e


def total_energy(cloth: ClothGeometry, x: torch.Tensor, x_prev: torch.Tensor, x_prev2: torch.Tensor, dt_s: float, body_points: torch.Tensor | None = None, body_normals: torch.Tensor | None = None, candidates: torch.Tensor | None = None) -> torch.Tensor:
    """L = L_inertia + L_static (eq. 5.5), the objective of the backward-Euler step (eq. 5.4), (B,) J."""
    return inertia_energy(cloth, x, x_prev, x_prev2, dt_s) + static_energy(cloth, x, body_points, body_normals, candidates)


def energy_terms(cloth: ClothGeometry, x: torch.Tensor, body_points: torch.Tensor | None = None, body_normals: torch.Tensor | None = None, candidates: torch.Tensor | None = None, x_prev: torch.Tensor | None = None, x_prev2: torch.Tensor | None = None, dt_s: float | None = None,
                 inside: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Every term separately, (B,) joules each: strain, bending, gravity, and collision (with a
    body; ``inside`` as in ``collision_energy``) and inertia (with x_prev, x_prev2, dt_s) — the
    per-frame metrics of DESIGN.md §5."""
    out = {
        "strain": strain_energy(cloth, x),
        "bending": bending_energy(cloth, x),
        "gravity": gravity_energy(cloth, x),
    }
    if body_points is not None:
        out["collision"] = collision_energy(cloth, x, body_points, body_normals, candidates, inside=inside)
    if x_prev is not None:
        out["inertia"] = inertia_energy(cloth, x, x_prev, x_prev2, dt_s)
    return out


# ------------------------------------------------------------------------------ Hessians
# Positive semi-definite approximations of each energy's Hessian, per element, for Newton-type
# solvers (``training.simulate``). Element blocks are ordered (corner a, coordinate i) -> 3 a + i.
def strain_hessian(cloth: ClothGeometry, x: torch.Tensor, project: bool = True) -> torch.Tensor:
    """Hessian of the StVK strain energy (eq. 5.8-5.9) per triangle, (B, F, 9, 9) J/m^2.

    With c_a = dF/dx_a (F = Ds Dm^-1 is linear in x: dF/dx_a = e_c c_a^T), f_j the columns of F:
        dG00/dx_a = c_a0 f0,  dG11/dx_a = c_a1 f1,  dG01/dx_a = (c_a0 f1 + c_a1 f0) / 2
        H = V [lambda dtrG dtrG^T + 2 mu (dG00 dG00^T + dG11 dG11^T + 2 dG01 dG01^T)]    (Gauss-Newton)
          + V (C S+ C^T) (x) I_3                                                       (geometric)
    with S = lambda tr(G) I + 2 mu G the second Piola-Kirchhoff stress and S+ its PSD part
    (eigenvalues clamped at 0). project=True: PSD always, exact when S is PSD (stretched, not
    compressed). project=False: S instead of S+, the exact Hessian (indefinite under compression).
    x : (B, V, 3) metres
    """
    _check_positions(cloth, x)
    Fg = deformation_gradients(x, cloth.faces, cloth.dm_inv)  # (B, F, 3, 2)
    f0, f1 = Fg[..., 0], Fg[..., 1]
    D = cloth.dm_inv
    c = torch.stack([-(D[:, 0] + D[:, 1]), D[:, 0], D[:, 1]], dim=1)  # (F, 3 corners, 2): dF[:, j]/dx_a
    c0, c1 = c[None, :, :, 0, None], c[None, :, :, 1, None]  # (1, F, 3, 1)
    j00 = (c0 * f0[:, :, None]).flatten(-2)  # (B, F, 9)
    j11 = (c1 * f1[:, :, None]).flatten(-2)
    j01 = (0.5 * (c0 * f1[:, :, None] + c1 * f0[:, :, None])).flatten(-2)
    jtr = j00 + j11
    m = cloth.material
    vol = (cloth.rest_area_m2 * m.thickness_m)[None, :, None, None]

    def outer(a, b):
        return a[..., :, None] * b[..., None, :]

    gn = m.lame_lambda_pa * outer(jtr, jtr) + 2.0 * m.lame_mu_pa * (outer(j00, j00) + outer(j11, j11) + 2.0 * outer(j01, j01))
    G = 0.5 * (torch.einsum("bfci,bfcj->bfij", Fg, Fg) - torch.eye(2, dtype=x.dtype, device=x.device))
    S = m.lame_lambda_pa * (G[..., 0, 0] + G[..., 1, 1])[..., None, None] * torch.eye(2, dtype=x.dtype, device=x.device) + 2.0 * m.lame_mu_pa * G
    if project:
        w, U = torch.linalg.eigh(S)
        S = (U * w.clamp(min=0.0)[..., None, :]) @ U.transpose(-1, -2)
    # K[b, f, a, a'] = sum_ij C[f, a, i] S+[b, f, i, j] C[f, a', j]   (geometric stiffness, per corner pair)
    K = torch.einsum("fai,bfij,fcj->bfac", c, S, c)
    geo = torch.einsum("bfac,ij->bfaicj", K, torch.eye(3, dtype=x.dtype, device=x.device)).reshape(K.shape[:2] + (9, 9))
    return vol * (gn + geo)


def bending_hessian(cloth: ClothGeometry, x: torch.Tensor) -> torch.Tensor:
    """Gauss-Newton Hessian of the bending energy (eq. 5.10) per hinge, (B, H, 12, 12) J/m^2:
    k_bend k_scale (dtheta/dx)(dtheta/dx)^T (drops (theta - theta_rest) d^2theta; exact at rest, PSD).

    x : (B, V, 3) metres ; corners ordered (i, j, k, l) as ``ClothGeometry.hinges``
    """
    _check_positions(cloth, x)
    with torch.enable_grad():
        hx = x.detach()[:, cloth.hinges].requires_grad_(True)  # (B, H, 4, 3), independent copies
        (dtheta,) = torch.autograd.grad(hinge_angles(hx).sum(), hx)
    j = dtheta.flatten(-2)  # (B, H, 12)
    k = (cloth.material.k_bend * cloth.k_scale)[None, :, None, None]
    return k * j[..., :, None] * j[..., None, :]


def collision_hessian(cloth: ClothGeometry, x: torch.Tensor, body_points: torch.Tensor, body_normals: torch.Tensor, candidates: torch.Tensor | None = None, active: torch.Tensor | None = None, smoothing_m: float | None = None) -> torch.Tensor:
    """Hessian of the collision energy (eq. 5.12) per vertex, (B, V, 3, 3) J/m^2:
    6 k_collision max(eps - d, 0) n n^T, PSD. Exact for a fixed closest body vertex; with
    smoothing_m, n is the blended normal and the weights' derivatives are left out (Gauss-Newton).
    Arguments as ``collision_energy``."""
    _check_positions(cloth, x)
    with torch.no_grad():
        if smoothing_m is not None:
            d, n = _blended_planes(x, body_points, body_normals, candidates, smoothing_m)
        else:
            closest = closest_body_vertices(x, body_points, candidates)
            batch = torch.arange(x.shape[0], device=x.device)[:, None]
            n = body_normals[batch, closest]
            d = ((x - body_points[batch, closest]) * n).sum(-1)
        depth = torch.clamp(cloth.material.collision_margin_m - d, min=0.0)
        if active is not None:
            depth = depth * active.to(depth.dtype)
        return (6.0 * cloth.material.k_collision * depth)[..., None, None] * n[..., :, None] * n[..., None, :]
