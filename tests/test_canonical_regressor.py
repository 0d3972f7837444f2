"""The canonical-space regressor (thesis eq. 6.17-6.18) learns a latent that follows the motion."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training.canonical_regressor import CanonicalRegressor, RegressorConfig, regressor_loss, train_regressor  # noqa: E402


def _sequences(n=6, T=24, F=12, latent=5, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(F, latent)).astype(np.float32) * 0.3
    out = []
    for _ in range(n):
        g = np.cumsum(rng.normal(size=(T, F)), 0).astype(np.float32) * 0.2
        z = np.tanh(g @ A)  # the latent a function of the descriptor: learnable from gamma alone
        out.append({"phenotypes": rng.uniform(0.0, 1.0, 6).astype(np.float32), "gamma": g, "z": z})
    return out


def test_loss_is_zero_only_on_the_target_and_counts_velocity_and_acceleration():
    z = torch.randn(2, 10, 4)
    cfg = RegressorConfig()
    assert float(regressor_loss(z, z, cfg)) == 0.0
    shifted = z + 0.1  # same velocity and acceleration: only the position term
    assert float(regressor_loss(shifted, z, cfg)) == pytest.approx(0.1, rel=1e-5)
    ramp = z + 0.1 * torch.arange(10.0)[None, :, None]  # velocity off by 0.1 everywhere
    assert float(regressor_loss(ramp, z, cfg)) > float((ramp - z).abs().mean()) + 0.5 * 0.1 - 1e-4


def test_regressor_fits_sequences_and_runs_in_chunks():
    seqs = _sequences()
    cfg = RegressorConfig(hidden=32, layers=2, steps=400, window=24, batch=4)
    model, record = train_regressor(seqs, 5, cfg)
    losses = [h["loss"] for h in record["history"]]
    assert losses[-1] < 0.5 * losses[0], losses
    # a whole sequence in one call equals two chunks with the state carried
    s = seqs[0]
    ph, g = torch.as_tensor(s["phenotypes"][None]), torch.as_tensor(s["gamma"][None])
    with torch.no_grad():
        whole, _ = model(ph, g, model.initial_state(1))
        a, h = model(ph, g[:, :10], model.initial_state(1))
        b, _ = model(ph, g[:, 10:], h)
    np.testing.assert_allclose(torch.cat([a, b], 1).numpy(), whole.numpy(), atol=1e-5)
    assert isinstance(model, CanonicalRegressor)


def test_regressor_exports_with_parity(tmp_path):
    pytest.importorskip("onnxruntime")
    from training.canonical_regressor import HALF_TOLERANCE, export_regressor

    model, _ = train_regressor(_sequences(n=2, F=378), 5, RegressorConfig(hidden=16, layers=2, steps=2, window=8, batch=2))
    full = export_regressor(model, tmp_path / "regressor32.onnx", half=False)
    assert full["parity_max_abs"] <= 1e-4 and full["outputs"]["z"] == ["B", "T", 5] and full["weights"] == "float32"
    # the shipped form: weights stored as float16, cast back to float32 when the model loads
    out = export_regressor(model, tmp_path / "regressor.onnx")
    assert out["weights"] == "float16" and out["parity_max_abs"] <= HALF_TOLERANCE
    assert out["bytes"] < 0.65 * full["bytes"]  # biases and small tensors stay float32
