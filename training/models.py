"""The learned garment model of thesis eq. 4.2 (SNUG eq. 5.2): nn.Modules only.

T_c(beta, gamma_1..t) = T_bar_c + R_G(beta) + R_L(beta, gamma_1..t)           (eq. 4.2)

- ``FitRegressor`` is R_G (thesis ch. 4.2.2): an MLP from the 6 anny phenotypes to per-vertex
  displacements. Ours is a *residual on top of the .mhclo retarget fit*: the unposed garment is
  ``retarget_fit(hm08(beta)) + R_G(beta)``, so the network learns the drape, not the body
  (in the spirit of the diffused shape blendshapes of eq. 6.8).
- ``WrinkleGRU`` is R_L (ch. 4.2.3, SNUG §5.2.5): 4 GRU layers of 256 (tanh), then a linear
  layer to per-vertex displacements, over the motion descriptor gamma (eq. 6.17) and the shape.

Both end in a fixed low-rank output basis (``OutputBasis``): displacements
D[v, c] = sum_k Phi[v, k] C[k, c], with Phi the first K manifold harmonics of the garment mesh
(eigenvectors of its graph Laplacian, ``training.datasets.harmonic_basis``), so that the
outputs are smooth, the linear layer is K x 3 wide instead of V x 3 and the ONNX files stay a
few MB. Inputs are normalised inside the modules (phenotype box -> [-1, 1], gamma by the
training set's mean/std, clipped), so the exported ONNX takes raw phenotypes and raw gamma.

Shapes: B batch, T frames, V vertices, K basis size, F descriptor size (378), L GRU layers,
H hidden size. Units: displacements in metres.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from inference.body import PHENOTYPE_LABELS, PHENOTYPE_RANGES

# Normalised descriptor entries are clipped to +- this many standard deviations (mocap noise
# gives rare, huge finite-difference accelerations).
GAMMA_CLIP_STD = 5.0


def phenotype_box() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds (6,) float32 of the supported adult phenotype box (inference.body)."""
    lo = np.array([PHENOTYPE_RANGES[k][0] for k in PHENOTYPE_LABELS], np.float32)
    hi = np.array([PHENOTYPE_RANGES[k][1] for k in PHENOTYPE_LABELS], np.float32)
    return lo, hi


class PhenotypeNormaliser(nn.Module):
    """Phenotypes (B, 6) in the adult box -> (B, 6) in [-1, 1] (2 (p - lo) / (hi - lo) - 1)."""

    def __init__(self):
        super().__init__()
        lo, hi = phenotype_box()
        self.register_buffer("lo", torch.as_tensor(lo))
        self.register_buffer("span", torch.as_tensor(hi - lo))

    def forward(self, phenotypes: torch.Tensor) -> torch.Tensor:
        return 2.0 * (phenotypes - self.lo) / self.span - 1.0


class OutputBasis(nn.Module):
    """Fixed low-rank basis: coefficients (..., K * 3) -> displacements (..., V, 3), metres.

    basis       : (V, K) float32, columns scaled to unit RMS over the vertices
    coeff_unit_m: metres per unit of coefficient (the basis is stored pre-multiplied by it). With
                  unit-RMS modes a coefficient is then the RMS displacement of its mode in these
                  units (1 cm by default), which keeps Adam's first steps (~lr per weight) at
                  millimetres instead of decimetres.
    """

    def __init__(self, basis: np.ndarray, coeff_unit_m: float = 0.01):
        super().__init__()
        basis = np.asarray(basis, np.float32)
        if basis.ndim != 2:
            raise ValueError(f"basis: expected shape (V, K), got {basis.shape}")
        self.coeff_unit_m = float(coeff_unit_m)
        self.register_buffer("basis", torch.as_tensor(basis * np.float32(coeff_unit_m)))

    @property
    def num_vertices(self) -> int:
        return int(self.basis.shape[0])

    @property
    def size(self) -> int:
        return int(self.basis.shape[1])

    def forward(self, coeffs: torch.Tensor) -> torch.Tensor:
        lead = coeffs.shape[:-1]
        c = coeffs.reshape(-1, self.size, 3)  # (N, K, 3)
        # D[n, v, c] = sum_k Phi[v, k] C[n, k, c] as one GEMM (V, K) @ (K, 3N): the basis is read
        # once for all N frames (a broadcast (V, K) @ (N, K, 3) reads it per frame; measured 6x slower)
        n = c.shape[0]
        d = torch.matmul(self.basis, c.permute(1, 0, 2).reshape(self.size, 3 * n))  # (V, 3N)
        return d.reshape(self.num_vertices, n, 3).permute(1, 0, 2).reshape(*lead, self.num_vertices, 3)


class FitRegressor(nn.Module):
    """R_G (thesis ch. 4.2.2): phenotypes (B, 6) -> fit displacements (B, V, 3), metres.

    A residual on the .mhclo retarget fit (see the module docstring). MLP: normalised
    phenotypes -> ``layers`` x [Linear(hidden), tanh] -> Linear(3K) (zero-initialised, so an
    untrained model is exactly the retarget baseline) -> OutputBasis.
    """

    def __init__(self, basis: np.ndarray, hidden: int = 128, layers: int = 2):
        super().__init__()
        self.normalise = PhenotypeNormaliser()
        self.output = OutputBasis(basis)
        blocks: list[nn.Module] = []
        width = len(PHENOTYPE_LABELS)
        for _ in range(layers):
            blocks += [nn.Linear(width, hidden), nn.Tanh()]
            width = hidden
        self.mlp = nn.Sequential(*blocks)
        self.head = nn.Linear(width, 3 * self.output.size)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, phenotypes: torch.Tensor) -> torch.Tensor:
        """phenotypes : (B, 6) raw, in the adult box ; returns (B, V, 3) metres."""
        return self.output(self.head(self.mlp(self.normalise(phenotypes))))

    def coefficients(self, phenotypes: torch.Tensor) -> torch.Tensor:
        """The output basis' coefficients in metres, (B, K, 3): forward = basis (V, K) @ these."""
        return self.head(self.mlp(self.normalise(phenotypes))).reshape(-1, self.output.size, 3) * self.output.coeff_unit_m


class WrinkleGRU(nn.Module):
    """R_L (thesis ch. 4.2.3; SNUG §5.2.5): (phenotypes, gamma_1..T, h0) -> (B, T, V, 3), hT.

    Input per frame: [normalised phenotypes (6), normalised gamma (F)] -> ``layers`` GRU
    layers of ``hidden`` units (tanh candidate activation, nn.GRU) -> Linear(3K) -> OutputBasis.

    gamma_mean, gamma_std : (F,) descriptor statistics of the training frames (std floored)
    """

    def __init__(self, basis: np.ndarray, gamma_mean: np.ndarray, gamma_std: np.ndarray, hidden: int = 256, layers: int = 4, head_init_std: float = 1e-4):
        super().__init__()
        gamma_mean = np.asarray(gamma_mean, np.float32)
        gamma_std = np.asarray(gamma_std, np.float32)
        if gamma_mean.ndim != 1 or gamma_mean.shape != gamma_std.shape:
            raise ValueError(f"gamma_mean/gamma_std: expected matching (F,), got {gamma_mean.shape}, {gamma_std.shape}")
        self.hidden = hidden
        self.layers = layers
        self.normalise = PhenotypeNormaliser()
        self.register_buffer("gamma_mean", torch.as_tensor(gamma_mean))
        self.register_buffer("gamma_std", torch.as_tensor(gamma_std))
        self.gru = nn.GRU(len(PHENOTYPE_LABELS) + len(gamma_mean), hidden, num_layers=layers, batch_first=True)
        self.output = OutputBasis(basis)
        self.head = nn.Linear(hidden, 3 * self.output.size)
        nn.init.normal_(self.head.weight, std=head_init_std)
        nn.init.zeros_(self.head.bias)

    @property
    def descriptor_size(self) -> int:
        return int(self.gamma_mean.shape[0])

    def initial_state(self, batch: int, std: float = 0.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """h0 (L, B, H): zeros at runtime; N(0, std) in training (SNUG §5.2.5: std 0.1)."""
        h = torch.zeros(self.layers, batch, self.hidden)
        return h if std == 0 else h.normal_(0.0, std, generator=generator)

    def forward(self, phenotypes: torch.Tensor, gamma: torch.Tensor, h0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """phenotypes : (B, 6) raw ; gamma : (B, T, F) raw (inference.motion.descriptor) ;
        h0 : (L, B, H) ; returns displacements (B, T, V, 3) metres and hT (L, B, H)."""
        g = torch.clamp((gamma - self.gamma_mean) / self.gamma_std, -GAMMA_CLIP_STD, GAMMA_CLIP_STD)
        p = self.normalise(phenotypes)[:, None, :].expand(-1, gamma.shape[1], -1)
        y, h_t = self.gru(torch.cat([p, g], dim=-1), h0)
        return self.output(self.head(y)), h_t
