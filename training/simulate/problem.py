"""The objective of one implicit step and its sparse Hessian.

``StepProblem`` is eq. 5.4, the minimisation form of backward Euler (eq. 5.3):

    x^{t+1} = argmin_x  L_inertia(x; x^t, v^t, dt) + L_static(x; posed body at t+1)

with exactly the energies the learned models are trained on (``training.physics``: eq. 5.6-5.12),
the collision term against a ``Collider``. Its Hessian is the sum of the per-element blocks of
``training.physics`` (exact StVK or its PSD projection, bending Gauss-Newton, collision and mass
blocks), which ``HessianAssembly`` sums into one sparse (3V x 3V) matrix.

Units: metres (positions), joules (energies), J/m^2 (Hessians).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from training.physics import ClothGeometry, bending_hessian, inertia_energy, static_energy, strain_hessian
from training.simulate.contacts import Collider, Contacts


class HessianAssembly:
    """Sparse (3V x 3V) CSR assembly of per-element Hessian blocks of one garment.

    The sparsity pattern (triangles: 9 x 9 blocks, hinges: 12 x 12, vertices: 3 x 3) is built
    once; ``matrix`` then sums block entries into it with one ``np.bincount``.
    """

    def __init__(self, cloth: ClothGeometry):
        V = cloth.num_vertices
        self.size = 3 * V

        def dofs(elements):  # (n, k) vertex ids -> (n, 3k) dof ids, ordered (corner, coordinate)
            return (3 * elements[:, :, None] + np.arange(3)).reshape(len(elements), -1)

        blocks = [dofs(cloth.faces.numpy()), dofs(cloth.hinges.numpy()), dofs(np.arange(V)[:, None])]
        keys = np.concatenate([(d[:, :, None] * self.size + d[:, None, :]).ravel() for d in blocks])
        unique, self._position = np.unique(keys, return_inverse=True)
        self._indices = (unique % self.size).astype(np.int32)
        self._indptr = np.searchsorted(unique // self.size, np.arange(self.size + 1)).astype(np.int32)

    def matrix(self, triangle_blocks: np.ndarray, hinge_blocks: np.ndarray, vertex_blocks: np.ndarray) -> sp.csr_matrix:
        """triangle_blocks (F, 9, 9), hinge_blocks (H, 12, 12), vertex_blocks (V, 3, 3) -> (3V, 3V) CSR."""
        values = np.concatenate([triangle_blocks.ravel(), hinge_blocks.ravel(), vertex_blocks.ravel()])
        data = np.bincount(self._position, weights=values, minlength=len(self._indices))
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(self.size, self.size))


class StepProblem:
    """The objective of one implicit step, eq. 5.4: inertia (optional) + strain + bending + gravity
    + collision against one posed body (optional), with its gradient and PSD Hessian.

    inertia : (x_prev, x_prev2, dt_s) of eq. 5.6, or None ; body : Collider or None
    """

    def __init__(self, cloth: ClothGeometry, assembly: HessianAssembly | None, inertia: tuple[torch.Tensor, torch.Tensor, float] | None, body: Collider | None):
        self.cloth, self.assembly, self.inertia, self.body = cloth, assembly, inertia, body

    def energy(self, x: torch.Tensor, contacts: Contacts | None) -> torch.Tensor:
        e = static_energy(self.cloth, x)  # strain + bending + gravity (eq. 5.7 without collision)
        if self.inertia is not None:
            e = e + inertia_energy(self.cloth, x, *self.inertia)
        if self.body is not None:
            e = e + self.body.collision(self.cloth, x, contacts)
        return e

    def static(self, x: torch.Tensor, contacts: Contacts | None) -> torch.Tensor:
        """L_static only (eq. 5.7): the residual of static equilibrium is its gradient."""
        e = static_energy(self.cloth, x)
        return e + self.body.collision(self.cloth, x, contacts) if self.body is not None else e

    def hessian(self, x: torch.Tensor, contacts: Contacts | None, project: bool = True) -> sp.csr_matrix:
        """Hessian of ``energy`` (physics.*_hessian), (3V, 3V) CSR, J/m^2: PSD approximation, or
        with project=False the exact strain Hessian (indefinite where compression outweighs the
        mass and bending terms)."""
        cloth = self.cloth
        with torch.no_grad():
            tri = strain_hessian(cloth, x, project)[0].numpy()
            hinge = bending_hessian(cloth, x)[0].numpy()
            vert = np.zeros((cloth.num_vertices, 3, 3))
            if self.inertia is not None:  # M / dt^2 (eq. 5.6)
                vert += (cloth.vertex_mass_kg.numpy() / self.inertia[2] ** 2)[:, None, None] * np.eye(3)
            if self.body is not None:
                vert += self.body.hessian(cloth, x, contacts)[0].numpy()
        return self.assembly.matrix(tri, hinge, vert)
