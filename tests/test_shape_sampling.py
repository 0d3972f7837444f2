"""Shapes of the training windows (training.train_wrinkle.draw_shapes): uniform over the bank, or
a set share of box corners."""
import numpy as np
import pytest

pytest.importorskip("torch")  # training.train_wrinkle imports torch


def test_the_bank_starts_with_the_box_corners():
    from training.datasets import N_CORNERS, sample_adult_phenotypes
    from training.models import phenotype_box

    lo, hi = phenotype_box()
    bank = sample_adult_phenotypes(N_CORNERS + 10, np.random.default_rng(0))
    corners = bank[:N_CORNERS]
    assert np.all(np.isclose(corners, lo) | np.isclose(corners, hi))
    assert len(np.unique(corners, axis=0)) == N_CORNERS
    # the uniform samples after them are not all corners
    assert not np.all(np.isclose(bank[N_CORNERS:], lo) | np.isclose(bank[N_CORNERS:], hi))


@pytest.mark.parametrize("fraction", [0.0, 0.5, 1.0])
def test_corner_fraction_sets_the_share_of_corner_windows(fraction):
    from training.datasets import N_CORNERS
    from training.train_wrinkle import draw_shapes

    idx = draw_shapes(np.random.default_rng(1), 256, 4000, fraction)
    assert idx.min() >= 0 and idx.max() < 256
    share = float((idx < N_CORNERS).mean())
    assert abs(share - fraction) < 0.03
    if fraction == 0.5:  # both parts are spread over their ranges
        assert len(np.unique(idx[idx < N_CORNERS])) == N_CORNERS
        assert len(np.unique(idx[idx >= N_CORNERS])) > 150


def test_default_draw_is_uniform_over_the_bank():
    from training.datasets import N_CORNERS
    from training.train_wrinkle import draw_shapes

    idx = draw_shapes(np.random.default_rng(2), 256, 8000)
    assert abs(float((idx < N_CORNERS).mean()) - N_CORNERS / 256) < 0.03
    # the same stream as before the option existed: runs stay reproducible
    assert np.array_equal(draw_shapes(np.random.default_rng(3), 256, 16), np.random.default_rng(3).integers(0, 256, 16))


@pytest.mark.parametrize("fraction, bank", [(1.5, 256), (-0.1, 256), (0.5, 64)])
def test_bad_corner_fraction_is_refused(fraction, bank):
    from training.train_wrinkle import draw_shapes

    with pytest.raises(ValueError):
        draw_shapes(np.random.default_rng(0), bank, 4, fraction)


def test_corner_fraction_option():
    import training.cli as cli
    from training.train_wrinkle import WrinkleConfig

    seen = []

    def train(config, smoke, out_dir):
        seen.append(config)
        return {"metrics": {}}

    cli.run(["--garment", "tshirt", "--corner-fraction", "0.5"], "train", WrinkleConfig, train, {}, "", None)
    cli.run(["--garment", "tshirt"], "train", WrinkleConfig, train, {}, "", None)
    assert [c.corner_fraction for c in seen] == [0.5, None]
