"""CI smoke training: a few steps of train_fit and train_wrinkle on the smallest garment and a
short clip, then the ONNX export and the onnxruntime wrapper (keeps the training code from
rotting; < 60 s on 2 cores). Full training: ``python -m training.train_fit --garment <id>``."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")

GARMENT = "trousers"  # the smallest catalog garment (3,485 vertices)


@pytest.mark.timeout(180)
def test_smoke_train_export_run(tmp_path):
    from inference.learned import LearnedGarment
    from training.export_onnx import PARITY_TOLERANCE_M, export_garment
    from training.train_fit import SMOKE as FIT_SMOKE, FitConfig, train_fit
    from training.train_wrinkle import SMOKE as WRINKLE_SMOKE, WrinkleConfig, train_wrinkle

    ckpt = tmp_path / "checkpoints"
    fit_record = train_fit(FitConfig(garment=GARMENT, **FIT_SMOKE), smoke=True, out_dir=ckpt)
    assert fit_record["steps"] == FIT_SMOKE["max_steps"]
    for key in ("static_j", "strain_j", "collision_j", "distance_to_retarget_cm_mean"):
        assert np.isfinite(fit_record["metrics"]["held_out_learned"][key])

    wrinkle_record = train_wrinkle(WrinkleConfig(garment=GARMENT, **WRINKLE_SMOKE), smoke=True, out_dir=ckpt)
    assert wrinkle_record["steps"] == WRINKLE_SMOKE["max_steps"]
    assert "01_01" not in wrinkle_record["config"]["clips"]
    val = wrinkle_record["metrics"]["validation"]
    assert np.isfinite(val["learned"]["static_j_per_frame"]) and np.isfinite(val["learned"]["inertia_j_per_frame"])
    assert all(np.isfinite(h["loss_j"]) for h in wrinkle_record["history"])

    entry = export_garment(GARMENT, ckpt, tmp_path / "models", smoke=True)
    assert entry["fit"]["parity_max_abs_m"] <= PARITY_TOLERANCE_M
    assert entry["wrinkle"]["parity_max_abs"] <= PARITY_TOLERANCE_M

    lg = LearnedGarment.load(tmp_path / "models" / GARMENT)
    p = np.array([[0.5, 0.8, 0.5, 0.5, 0.5, 0.5]], np.float32)
    assert lg.fit(p).shape == (1, lg.num_vertices, 3)
    delta, h = lg.wrinkles(p, np.zeros((1, 4, lg.descriptor_size), np.float32))
    assert delta.shape == (1, 4, lg.num_vertices, 3) and h.shape == (WRINKLE_SMOKE["layers"], 1, WRINKLE_SMOKE["hidden"])


def test_training_cli_parses_into_the_config(tmp_path):
    import torch

    from training.train_fit import main

    main(["--garment", GARMENT, "--smoke", "--lr", "2e-4", "--k-collision", "5000", "--out", str(tmp_path)])
    record = torch.load(tmp_path / GARMENT / "fit_smoke.pt", weights_only=False)["record"]
    assert record["smoke"] and record["config"]["lr"] == 2e-4 and record["config"]["k_collision"] == 5000.0
    assert record["config"]["max_steps"] == 5  # the smoke overrides
