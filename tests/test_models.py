"""training.models and training.datasets: hand-computed cases, batch consistency, GRU chunking,
ONNX export parity on small random models."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training.datasets import graph_laplacian, harmonic_basis, sample_adult_phenotypes, scale_motion  # noqa: E402
from training.models import FitRegressor, OutputBasis, PhenotypeNormaliser, WrinkleGRU, phenotype_box  # noqa: E402

# A 2 x 2 quad grid: 9 vertices, 8 triangles.
GRID_V = np.array([[x, y, 0.0] for y in range(3) for x in range(3)], np.float32) * 0.1
GRID_F = np.array([f for i in (0, 1, 3, 4) for f in ([i, i + 1, i + 4], [i, i + 4, i + 3])], np.int64)
GRID_E = np.unique(np.sort(GRID_F[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1), axis=0)
F_DESC = 378


def small_gru(K: int = 4, hidden: int = 8, layers: int = 2, seed: int = 0) -> WrinkleGRU:
    torch.manual_seed(seed)
    basis = harmonic_basis(len(GRID_V), GRID_E, K)
    m = WrinkleGRU(basis, np.zeros(F_DESC, np.float32), np.ones(F_DESC, np.float32), hidden, layers, head_init_std=0.1)
    return m.eval()


def test_phenotype_normaliser_maps_box_to_unit_cube():
    lo, hi = phenotype_box()
    assert lo[1] == pytest.approx(0.77) and hi[1] == 1.0  # adults only (inference.body)
    out = PhenotypeNormaliser()(torch.as_tensor(np.stack([lo, hi, (lo + hi) / 2])))
    np.testing.assert_allclose(out.numpy(), [[-1] * 6, [1] * 6, [0] * 6], atol=1e-6)


def test_harmonic_basis_constant_mode_and_unit_rms():
    U = harmonic_basis(len(GRID_V), GRID_E, 5)
    assert U.shape == (9, 5) and U.dtype == np.float32
    np.testing.assert_allclose(np.sqrt((U**2).mean(0)), 1.0, rtol=1e-5)  # unit RMS columns
    np.testing.assert_allclose(np.abs(U[:, 0]), 1.0, rtol=1e-5)  # the constant mode (eigenvalue 0) first
    L = graph_laplacian(9, GRID_E).toarray()
    assert np.allclose(L.sum(1), 0) and L[4, 4] == 6  # the centre vertex has 6 neighbours


def test_output_basis_hand_computed():
    basis = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]], np.float32)  # (V=3, K=2)
    ob = OutputBasis(basis, coeff_unit_m=0.5)
    c = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])  # C[k, c]: k=0 -> (1, 2, 3), k=1 -> (4, 5, 6)
    d = ob(c)[0].numpy()
    # D[v] = 0.5 * sum_k basis[v, k] C[k]
    np.testing.assert_allclose(d, 0.5 * np.array([[1, 2, 3], [8, 10, 12], [5, 7, 9]]), rtol=1e-6)


def test_fit_regressor_starts_at_the_retarget_and_is_batch_consistent():
    m = FitRegressor(harmonic_basis(9, GRID_E, 4), hidden=8, layers=2)
    p = torch.as_tensor(sample_adult_phenotypes(4, np.random.default_rng(0)))
    with torch.no_grad():
        assert m(p).shape == (4, 9, 3)
        assert float(m(p).abs().max()) == 0.0  # zero-initialised head: untrained = retarget baseline
    torch.nn.init.normal_(m.head.weight, std=0.1)
    with torch.no_grad():
        full = m(p)
        one = torch.cat([m(p[i : i + 1]) for i in range(4)])
    torch.testing.assert_close(full, one, atol=1e-7, rtol=0)
    assert float((full[0] - full[1]).abs().max()) > 0  # depends on the shape


def test_wrinkle_gru_chunked_state_equals_one_call():
    m = small_gru()
    p = torch.as_tensor(sample_adult_phenotypes(3, np.random.default_rng(1)))
    g = torch.randn(3, 7, F_DESC)
    h0 = m.initial_state(3, 0.1, torch.Generator().manual_seed(0))
    with torch.no_grad():
        y, h = m(p, g, h0)
        y1, h1 = m(p, g[:, :3], h0)
        y2, h2 = m(p, g[:, 3:], h1)
    assert y.shape == (3, 7, 9, 3) and h.shape == (2, 3, 8)
    torch.testing.assert_close(torch.cat([y1, y2], 1), y, atol=1e-6, rtol=0)
    torch.testing.assert_close(h2, h, atol=1e-6, rtol=0)
    with torch.no_grad():  # batch consistency
        yb = torch.cat([m(p[i : i + 1], g[i : i + 1], h0[:, i : i + 1])[0] for i in range(3)])
    torch.testing.assert_close(yb, y, atol=1e-6, rtol=0)


def test_wrinkle_gru_normalises_and_clips_gamma():
    m = small_gru()
    p = torch.as_tensor(sample_adult_phenotypes(1, np.random.default_rng(2)))
    h0 = m.initial_state(1)
    g = torch.zeros(1, 2, F_DESC)
    g_big, g_huger = g.clone(), g.clone()
    g_big[..., 0], g_huger[..., 0] = 50.0, 5000.0  # both beyond the 5-sigma clip
    with torch.no_grad():
        torch.testing.assert_close(m(p, g_big, h0)[0], m(p, g_huger, h0)[0])


def test_scale_motion_scales_root_linear_terms_only():
    from inference.motion.descriptor import DESCRIPTOR_LAYOUT

    t = np.ones((2, 3, 3), np.float32)
    g = np.ones((2, 3, F_DESC), np.float32)
    t2, g2 = scale_motion(t, g, np.array([1.0, 2.0]))
    assert np.allclose(t2[1], 2.0) and np.allclose(t2[0], 1.0)
    assert np.allclose(g2[1, :, DESCRIPTOR_LAYOUT["root_linear_velocity"]], 2.0)
    assert np.allclose(g2[1, :, DESCRIPTOR_LAYOUT["pose"]], 1.0) and np.allclose(g, 1.0)


def test_sample_adult_phenotypes_corners_first():
    p = sample_adult_phenotypes(70, np.random.default_rng(0))
    lo, hi = phenotype_box()
    assert p.shape == (70, 6)
    corners = p[:64]
    assert np.all((np.isclose(corners, lo) | np.isclose(corners, hi)))
    assert len(np.unique(corners, axis=0)) == 64
    assert np.all(p >= lo) and np.all(p <= hi)


def test_onnx_export_parity(tmp_path):
    pytest.importorskip("onnx")
    import onnxruntime as ort

    from training.export_onnx import PARITY_TOLERANCE_M, export_fit, export_wrinkle

    record = {"config": {"test": True}, "train_wall_s": 0.0, "steps": 0, "metrics": {}, "git_commit": "test"}
    fit = FitRegressor(harmonic_basis(9, GRID_E, 4), hidden=8)
    torch.nn.init.normal_(fit.head.weight, std=0.1)
    e_fit = export_fit(fit, tmp_path / "fit.onnx", record)
    e_gru = export_wrinkle(small_gru(), tmp_path / "wrinkle.onnx", record)
    assert e_fit["parity_max_abs_m"] <= PARITY_TOLERANCE_M and e_gru["parity_max_abs"] <= PARITY_TOLERANCE_M
    import onnx

    model = onnx.load(str(tmp_path / "wrinkle.onnx"))
    assert model.opset_import[0].version >= 17
    assert "GRU" in {n.op_type for n in model.graph.node}  # one ONNX GRU op per layer, no Python loop
    meta = {p.key: p.value for p in model.metadata_props}
    assert {"config", "git_commit", "train_wall_s", "metrics"} <= set(meta)
    sess = ort.InferenceSession(str(tmp_path / "wrinkle.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["phenotypes", "gamma", "h0"]


def test_import_onnx_rebuilds_the_exported_checkpoints(tmp_path):
    """training.import_onnx: fit.onnx / wrinkle.onnx read back into torch give the exported
    weights exactly (GRU gate blocks reordered (z, r, h) -> (r, z, n), head transposed), the
    record of model.json, and a basis that rebuilds the same buffer."""
    pytest.importorskip("onnx")
    import json

    from training.export_onnx import export_fit, export_wrinkle
    from training.import_onnx import fit_checkpoint, wrinkle_checkpoint

    record = {"config": {"lr": 1e-4}, "train_wall_s": 12.5, "steps": 7, "metrics": {"x": 1.0}, "git_commit": "abc"}
    torch.manual_seed(1)
    fit = FitRegressor(harmonic_basis(9, GRID_E, 4), hidden=8, layers=3)
    torch.nn.init.normal_(fit.head.weight, std=0.1)
    gru = small_gru(layers=3)
    for name, p in gru.gru.named_parameters():  # distinct gate blocks, so a wrong order is caught
        p.data.copy_(torch.randn_like(p))
    entry = {"fit": export_fit(fit, tmp_path / "fit.onnx", record), "wrinkle": export_wrinkle(gru, tmp_path / "wrinkle.onnx", record)}
    (tmp_path / "model.json").write_text(json.dumps(entry))

    for original, ck, build in ((fit, fit_checkpoint(tmp_path), lambda c: FitRegressor(c["basis"], c["hidden"], c["layers"])),
                                (gru, wrinkle_checkpoint(tmp_path), lambda c: WrinkleGRU(c["basis"], c["gamma_mean"], c["gamma_std"], c["hidden"], c["layers"]))):
        want = original.state_dict()
        assert set(ck["state_dict"]) == set(want)
        for k, v in want.items():
            assert torch.equal(ck["state_dict"][k], v), k
        rebuilt = build(ck)
        torch.testing.assert_close(rebuilt.output.basis, original.output.basis, rtol=1e-6, atol=0)
        rebuilt.load_state_dict(ck["state_dict"])
        assert ck["record"]["steps"] == 7 and ck["record"]["config"] == {"lr": 1e-4} and ck["record"]["git_commit"] == "abc"
    assert ck["hidden"] == 8 and ck["layers"] == 3


def test_import_onnx_rejects_a_wrong_gate_order(tmp_path, monkeypatch):
    """The parity check against onnxruntime catches a mis-read GRU (here: gates left in ONNX order)."""
    pytest.importorskip("onnx")
    import json

    import training.import_onnx as imp
    from training.export_onnx import export_wrinkle

    gru = small_gru()
    for p in gru.gru.parameters():
        p.data.copy_(torch.randn_like(p))
    record = {"config": {}, "train_wall_s": 0.0, "steps": 0, "metrics": {}}
    (tmp_path / "model.json").write_text(json.dumps({"wrinkle": export_wrinkle(gru, tmp_path / "wrinkle.onnx", record)}))
    monkeypatch.setattr(imp, "_gru_blocks", lambda a, H: a[:3 * H])
    with pytest.raises(RuntimeError, match="differs from onnxruntime"):
        imp.wrinkle_checkpoint(tmp_path)
