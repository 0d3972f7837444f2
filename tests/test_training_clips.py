"""Training clips: AMC and BVH sources load alike; held-out clips are refused (training.datasets)."""
import numpy as np
import pytest

from inference.body import NEUTRAL_PHENOTYPES, BodyModel

pytest.importorskip("torch")  # training.datasets imports training.physics (torch)


@pytest.fixture(scope="module")
def body():
    model = BodyModel.load()
    return model, model.shape(NEUTRAL_PHENOTYPES[None])


@pytest.mark.parametrize("clip_id", ["01_01", "131_03"])
def test_held_out_clips_are_never_training_clips(body, clip_id):
    from training.datasets import load_training_clip

    with pytest.raises(ValueError, match="held out"):
        load_training_clip(clip_id, *body, max_frames=4)


def test_bvh_clip_is_retargeted_like_an_amc_clip(body):
    from training.datasets import load_training_clip

    rot_b, trans_b = load_training_clip("131_01", *body, max_frames=30)
    rot_a, trans_a = load_training_clip("02_01", *body, max_frames=30)
    assert rot_b.shape == rot_a.shape == (30, 31, 3) and trans_b.shape == trans_a.shape == (30, 3)
    assert np.isfinite(rot_b).all() and np.isfinite(trans_b).all()
    # both on the neutral body, grounded the same way: the roots' heights (metres, BVH units
    # converted) agree within 15 cm while both subjects stand and walk
    assert np.abs(trans_b[:, 2] - trans_a[:, 2]).max() < 0.15


def test_clips_option_parses_a_comma_separated_list():
    from training.cli import _clips

    assert _clips("02_01, 131_01") == ("02_01", "131_01")
    with pytest.raises(Exception):
        _clips(" , ")
