"""The Part 7 evaluation (training.evaluate): one garment, one body, a few collision frames."""
import numpy as np
import pytest

from training.evaluate import BEGIN, END, BODIES, evaluate, markdown, per_frame_energies, settle_check, write_section
from training.physics import ClothGeometry


@pytest.fixture(scope="module")
def rows():
    return evaluate("walk", every=29, garments=["trousers"], bodies={"neutral": BODIES["neutral"]})  # 86 frames: the smoke of the 01_01 report


def test_rows_cover_every_method_with_finite_numbers(rows):
    assert [r.method for r in rows] == ["learned", "retarget", "lbs"]
    for r in rows:
        assert r.frames == 86 and r.collision_frames == 3
        assert 0.0 <= r.after["inside_pct"] <= 100.0 and 0.0 <= r.before["inside_pct"] <= 100.0
        assert all(np.isfinite(v) for v in r.energies_j.values())
    retarget = next(r for r in rows if r.method == "retarget")
    assert retarget.energies_j["gravity"] == 0.0  # the gravity column is relative to the retarget


def test_neutral_template_is_the_retarget_on_the_neutral_body(rows):
    by = {r.method: r for r in rows}
    assert by["lbs"].energies_j["strain"] == pytest.approx(by["retarget"].energies_j["strain"], rel=1e-4)


def test_energies_of_a_still_rest_garment():
    from inference.garment import GarmentCatalog

    asset = GarmentCatalog.load().get("trousers")
    cloth = ClothGeometry.from_asset(asset)
    still = np.repeat(asset.rest_vertices[None], 4, 0)
    e = per_frame_energies(cloth, still, 30.0)
    assert e["strain"] == pytest.approx(0.0, abs=1e-6) and e["inertia"] == pytest.approx(0.0, abs=1e-9)
    moved = still + np.array([0.0, 0.0, 0.01], np.float32) * np.arange(4)[:, None, None] ** 2  # constant acceleration
    assert per_frame_energies(cloth, moved, 30.0)["inertia"] > 0.0


def test_report_section_is_replaced_in_place(tmp_path, rows):
    doc = tmp_path / "evaluation.md"
    doc.write_text("# Evaluation\n\nhand-written text\n")
    write_section(doc, markdown(rows, [], None, "cmd one", 29))
    write_section(doc, markdown(rows, [], None, "cmd two", 29))
    text = doc.read_text()
    assert text.count(BEGIN) == 1 and text.count(END) == 1
    assert "hand-written text" in text and "cmd two" in text and "cmd one" not in text


def test_settle_check_reports_hem_speed_after_the_stop():
    r = settle_check(move_frames=20, hold_frames=12)
    assert r.stop_frame == 20 and len(r.hem_speed_mm_per_frame) == 12  # one per held frame
    assert all(np.isfinite(r.hem_speed_mm_per_frame))


def test_reference_error_is_zero_for_the_method_that_made_the_reference(tmp_path, monkeypatch):
    import json

    import training.evaluate as ev
    from inference.body import NEUTRAL_PHENOTYPES, BodyModel
    from inference.garment import GarmentCatalog
    from inference.motion.clips import ClipLibrary, adapt_clip
    from inference.pipeline import PoseSequence, drape

    body = BodyModel.load()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    clip = ClipLibrary().load("01_01")
    rot, trans = adapt_clip(clip, body, shape)
    motion = PoseSequence(rot[0, :8], trans[0, :8], clip.fps)
    frames = drape(body, shape, motion, [GarmentCatalog.load().get("trousers")], ev.METHODS["retarget"]).garments[0].vertices[3:8]
    monkeypatch.setattr(ev, "REFERENCE_DIR", tmp_path)
    meta = {"start": 3, "dynamic_solves": {"max_force_n_median": 0.001}}
    np.savez(tmp_path / "trousers_01_01.npz", vertices=frames, metadata=np.str_(json.dumps(meta)))
    (row,) = ev.reference_errors("01_01", ["trousers", "tshirt"])
    assert row.garment == "trousers" and row.frames == 5 and row.start == 3
    assert row.error_cm["retarget"] < 1e-4
    assert row.error_cm["learned"] > 0.05
    assert "| trousers | 3-7 |" in markdown([], [], None, "cmd", 8, [row])
