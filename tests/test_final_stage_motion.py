"""tools/final_stage_motion.py's numbers on made-up frames: a jump, a torn edge, a still garment."""
from __future__ import annotations

import importlib.util

import numpy as np

from tests.conftest import REPO_ROOT

_spec = importlib.util.spec_from_file_location("final_stage_motion", REPO_ROOT / "tools" / "final_stage_motion.py")
tool = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(tool)

FACES = np.array([[0, 1, 2], [0, 2, 3]])
SQUARE = np.array([[0, 0, 0], [0.01, 0, 0], [0.01, 0.01, 0], [0, 0.01, 0]], np.float32)
FAR_BODY = (np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [0, 0, 2]], np.float32), np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


def _row(after, before):
    body, faces = FAR_BODY
    return tool.row(after, before, FACES, np.repeat(body[None], len(after), 0), faces)


def test_a_vertex_that_jumps_and_comes_back_is_two_pops_and_tears_its_edges():
    before = np.repeat(SQUARE[None], 3, 0)
    after = before.copy()
    after[1, 2, 2] = 0.05  # frame 1: vertex 2 out 5 cm, back in frame 2
    r = _row(after, before)
    assert r["pops"] == 2 and abs(r["pop_max_cm"] - 5.0) < 1e-4
    assert r["edges_2cm"] == 3 and r["edges_3cm"] == 3 and abs(r["move_max_mm"] - 50.0) < 1e-3  # its three edges
    assert r["skin"] == 0.0


def test_a_garment_the_stages_leave_alone_has_nothing():
    before = np.repeat(SQUARE[None], 3, 0) + np.arange(3, dtype=np.float32)[:, None, None] * 0.1  # moving 10 cm a frame
    r = _row(before.copy(), before)
    assert r["pops"] == 0 and r["edges_2cm"] == 0 and r["move_max_mm"] == 0.0
