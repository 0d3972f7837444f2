"""training.correction_modes: widening and truncating the wrinkle GRU's output basis."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")


def _checkpoint(V=40, K=6, F=5, seed=0):
    from training.models import WrinkleGRU

    rng = np.random.default_rng(seed)
    basis = np.linalg.qr(rng.standard_normal((V, K)))[0].astype(np.float32) * np.sqrt(V)
    model = WrinkleGRU(basis, np.zeros(F, np.float32), np.ones(F, np.float32), hidden=8, layers=2)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(seed))
    return {"basis": basis, "state_dict": model.state_dict(), "gamma_mean": np.zeros(F, np.float32), "gamma_std": np.ones(F, np.float32),
            "hidden": 8, "layers": 2, "record": {}}


def _run(ck, T=7):
    from training.train_wrinkle import wrinkle_from_checkpoint

    model, _ = wrinkle_from_checkpoint(ck)
    g = torch.as_tensor(np.random.default_rng(1).standard_normal((2, T, 5)).astype(np.float32))
    p = torch.tensor([[0.5, 0.8, 0.5, 0.5, 0.5, 0.5], [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]])
    with torch.no_grad():
        return model(p, g, model.initial_state(2))[0].numpy()


def test_extend_keeps_the_output_then_truncate_to_full_rank_too():
    from training.correction_modes import extend_checkpoint, truncate_checkpoint

    ck = _checkpoint()
    modes = np.random.default_rng(2).standard_normal((3, 40 * 3)).astype(np.float32)
    wide = extend_checkpoint(ck, modes)
    assert wide["basis"].shape == (40, 6 + 9)  # x, y, z parts of 3 modes
    b = wide["basis"].astype(np.float64)
    np.testing.assert_allclose(b[:, 6:].T @ b[:, :6], 0.0, atol=1e-3)  # orthogonal to the harmonics
    np.testing.assert_allclose(np.sqrt((b[:, 6:] ** 2).mean(0)), 1.0, rtol=1e-5)  # unit RMS
    np.testing.assert_array_equal(_run(wide), _run(ck))  # new head rows start at 0
    # trained: the new rows do something; truncating to full rank keeps the output
    with torch.no_grad():
        wide["state_dict"]["head.weight"][18:] = torch.randn(27, 8, generator=torch.Generator().manual_seed(3)) * 0.1
    full, kept = truncate_checkpoint(wide, keep=6, rank=9)
    assert kept == pytest.approx(1.0)
    np.testing.assert_allclose(_run(full), _run(wide), atol=1e-6)
    low, kept = truncate_checkpoint(wide, keep=6, rank=4)
    assert low["basis"].shape == (40, 10) and 0.0 < kept < 1.0
    np.testing.assert_array_equal(low["basis"][:, :6], wide["basis"][:, :6])
    assert np.abs(_run(low) - _run(wide)).max() > 0.0


def test_modes_never_come_from_the_test_clip():
    from training.correction_modes import correction_modes

    with pytest.raises(ValueError, match="01_01"):
        correction_modes("tshirt", clips=("walk", "01_01"))
