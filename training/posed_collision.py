"""A posed-space collision term for the canonical regressor (thesis ch. 5 eq. 5.6 on ch. 6's model), torch.

The canonical VAE keeps its decoded garments outside the *canonical* body (eq. 6.16), and the
runtime pushes every decoded point out to the garment's margin there. Posed by the diffused
body (eq. 6.7), such a garment still ends up inside the *posed* body where the body's skinning
squeezes space: the armpit and the inner thigh as the limbs close, the sides of a heavy torso.
This module measures that on the training frames and lets the regressor (eq. 6.18) learn to
pick latents whose posed garment stays out, with SNUG's collision energy against the posed body
of each training frame (its nearest vertex and that vertex's normal):

    d_v   = (x_v - b_nn(v)) . n_nn(v)                     (m, signed distance along the body normal)
    E_col = mean_v max(eps - d_v, 0)                       (m; eq. 5.6's hinge, linear as eq. 6.12)

x = M_G(D(z), beta, theta) (eq. 6.7, ``training.projection.CanonicalBody``), z the regressor's
latent, D the VAE's decoder (frozen); nn(v) is found with a KD-tree per frame (constant inside a
step, as in SNUG). The body frames are the newton simulation's own colliders, so the term sees
exactly the bodies of the supervised targets.

Units: metres. Arrays: torch float32, batch axis first.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.spatial
import torch

from inference.mesh import vertex_normals
from training.projection import CanonicalBody


@dataclass
class PosedFrames:
    """One training sequence's posed bodies: vertices and unit normals (T, Vb, 3), a KD-tree per
    frame, the skinning transforms (T, J, 4, 4) and the diffused fields of its body shape."""

    vertices: np.ndarray
    normals: np.ndarray
    trees: list
    transforms: torch.Tensor
    body: CanonicalBody

    @classmethod
    def build(cls, body_vertices: np.ndarray, body_faces: np.ndarray, transforms: np.ndarray, body: CanonicalBody) -> "PosedFrames":
        v = np.asarray(body_vertices, np.float32)
        return cls(v, vertex_normals(v, body_faces), [scipy.spatial.cKDTree(f) for f in v],
                   torch.as_tensor(np.asarray(transforms), dtype=torch.float32), body)


def pose_frames(body: CanonicalBody, X: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """eq. 6.7 on a batch: X (n, V, 3) canonical, transforms (n, J, 4, 4) -> posed (n, V, 3)."""
    n, V, _ = X.shape
    w, _, offsets = body.fields(X.reshape(-1, 3))
    shaped = X + offsets.reshape(n, V, 3)
    A = torch.einsum("nvj,njab->nvab", w.reshape(n, V, -1), transforms[:, body.bone_index, :3, :])
    return torch.einsum("nvab,nvb->nva", A[..., :3], shaped) + A[..., 3]


def posed_distance(posed: torch.Tensor, frames: PosedFrames, index: np.ndarray) -> torch.Tensor:
    """d_v (n, V) of posed garments (n, V, 3) against the body frames ``index`` (n,) (module
    docstring); the nearest vertices are looked up without gradient."""
    x = posed.detach().numpy()
    nn = np.stack([frames.trees[t].query(p)[1] for t, p in zip(index, x)])  # (n, V)
    b = torch.as_tensor(frames.vertices[index[:, None], nn])
    n = torch.as_tensor(frames.normals[index[:, None], nn])
    return ((posed - b) * n).sum(-1)


def collision_energy(d: torch.Tensor, eps_m: float) -> torch.Tensor:
    """E_col (m) of signed distances d (n, V)."""
    return torch.clamp(eps_m - d, min=0.0).mean()
