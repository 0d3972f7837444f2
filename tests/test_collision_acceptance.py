"""Issue acceptance, measured with the exact inside test: garments on CMU 01_01 (the spec's test
sequence) for the neutral body and the two extreme adult corners, before and after the guard.

CI runs a subsample of the frames (every 24th, ~29 frames) of two garments; the full table over
every garment and every 8th frame is `python -m training.evaluate_collisions --every 8`
(docs/evaluation.md). Bounds are regression guards above the measured values (every 24th frame,
arms lifted as the service does (shoulder-lift-v2), guard plane-push-v4: after the guard, all /
clean %, T-shirt and trousers: neutral 0.090 / 0.009 and 0.007 / 0.001, lightest 0.003 / 0.000
and 0.007 / 0.001, heaviest 0.184 / 0.095 and 0.000 / 0.000).
"""
import pytest

from training.evaluate_collisions import BODIES, evaluate

# inside_pct_clean and inside_pct after the guard must stay below these (percent of garment vertices)
BOUND_AFTER = {"neutral": 0.025, "min corner [0,.77,0,0,0,0]": 0.01, "max corner [1,1,1,1,1,1]": 0.2}
BOUND_AFTER_ALL = {"neutral": 0.15, "min corner [0,.77,0,0,0,0]": 0.02, "max corner [1,1,1,1,1,1]": 0.3}


@pytest.fixture(scope="module")
def rows():
    return evaluate("01_01", "retarget", every=24, garments=["tshirt", "trousers"], bodies=BODIES)


def test_guard_reduces_collisions_on_01_01(rows):
    assert len(rows) == 6
    for r in rows:
        assert r.frames >= 25
        assert r.after["inside_pct"] <= r.before["inside_pct"], r
        assert r.after["inside_pct_clean"] <= r.before["inside_pct_clean"], r
        assert r.after["inside_pct_clean"] < BOUND_AFTER[r.body], (r.body, r.garment, r.after)
        assert r.after["inside_pct"] < BOUND_AFTER_ALL[r.body], (r.body, r.garment, r.after)


def test_guard_clears_the_light_body(rows):
    # the lightest adult body has almost no LBS self-intersection: (near) zero after the guard
    for r in rows:
        if r.body.startswith("min corner"):
            assert r.after["inside_pct_clean"] < 0.05, (r.garment, r.after)
