"""Training samples of the local untangling operator (thesis §7.5; the operator, eq. 7.6, is
``inference.untangle``): f* ~ U(-0.2, 1.5), h* ~ U(-1, 1) per layer, N = 7 slots; an outfit with
fewer layers sets h* = 1 (inactive) in the unused ones.
"""
from __future__ import annotations

import numpy as np

from inference.untangle import untangle_exact

# Layer slots of the learned operator (thesis: "more than enough for common outfits").
MAX_LAYERS = 7
F_RANGE = (-0.2, 1.5)
H_RANGE = (-1.0, 1.0)


def sample_untangling(n: int, rng: np.random.Generator, layers: int = MAX_LAYERS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n training samples (§7.5): f* (n, layers), h* (n, layers) and f = O(f*, h*), float32."""
    f_star = rng.uniform(*F_RANGE, (n, layers))
    h_star = rng.uniform(*H_RANGE, (n, layers))
    return f_star.astype(np.float32), h_star.astype(np.float32), untangle_exact(f_star, h_star).astype(np.float32)
