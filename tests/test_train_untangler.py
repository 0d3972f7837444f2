"""The learned untangling operator (thesis eq. 7.7; training/train_untangler.py): it learns, it
exports to ONNX with parity, and its report compares it with the exact operator."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training.train_untangler import UntanglerMLP, evaluate, export, train  # noqa: E402
from training.untangle import MAX_LAYERS, sample_untangling  # noqa: E402


def test_a_zero_correction_leaves_the_input_and_training_lowers_the_loss(tmp_path):
    torch.manual_seed(0)
    model = UntanglerMLP(hidden=128, depth=3)
    f_star, h_star, f_gt = sample_untangling(256, np.random.default_rng(0))
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias.zero_()
        np.testing.assert_array_equal(model(torch.as_tensor(f_star), torch.as_tensor(h_star)).numpy(), f_star)
    history = train(model, samples=8192, epochs=6, batch=128, lr=2e-3, seed=1)
    # below the identity's squared error on the same samples: it untangles, a little, already
    f_star, _, f_gt = sample_untangling(8192, np.random.default_rng(1))
    assert history[-1] < 0.9 * float(((f_star - f_gt) ** 2).sum(1).mean())
    path = tmp_path / "untangler.onnx"
    assert export(model, path) <= 1e-5
    report = evaluate(path, samples=2000)
    for n, row in report["layers"].items():
        assert row["tangled_input_share"] > 0.0
        assert np.isfinite([row["mean_abs"], row["max_abs"], row["ms_5000_onnx"], row["ms_5000_exact_numpy"]]).all()
        assert row["tangled_past_1mm_input_share"] > 0.0 and row["identity_mean_abs_where_tangled"] > 0.0
    assert set(report["layers"]) == {2, 3, 7} and MAX_LAYERS == 7


def test_tangle_depth_is_the_deepest_crossing_of_an_active_pair():
    from inference.untangle import tangled, untangle_exact
    from training.train_untangler import tangle_depth

    f = np.array([[-0.01, 0.03], [0.02, 0.03], [-0.05, 0.01], [-0.05, 0.01]], np.float32)
    h = np.array([[-1, -1], [-1, -1], [-1, -1], [-1, 0.5]], np.float32)
    np.testing.assert_allclose(tangle_depth(f, h), [0.01, -0.02, 0.01, -np.inf])
    g, hh, _ = sample_untangling(3000, np.random.default_rng(4))
    np.testing.assert_array_equal(tangle_depth(g, hh) > 0, tangled(g, hh))
    assert (tangle_depth(untangle_exact(g, hh), hh) <= 0).all()
