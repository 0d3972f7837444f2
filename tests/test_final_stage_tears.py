"""tools/final_stage_tears.py's counts on a hand-made strip: a torn edge, a jump, an untouched edge."""
from __future__ import annotations

import importlib.util

import numpy as np

from tests.conftest import REPO_ROOT

_spec = importlib.util.spec_from_file_location("final_stage_tears", REPO_ROOT / "tools" / "final_stage_tears.py")
tool = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(tool)


def test_torn_edges_and_pops_of_a_strip():
    # a strip of two triangles, vertices 1 cm apart, in two frames
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    came = np.repeat(np.array([[[0.0, 0, 0], [0.01, 0, 0], [0.0, 0.01, 0], [0.01, 0.01, 0]]]), 2, axis=0)
    left = came.copy()
    left[1, 0, 2] += 0.03  # frame 1: vertex 0 out 3 cm one way ...
    left[1, 1, 2] -= 0.03  # ... and vertex 1 the other way: edge 0-1 torn, and both jump 3 cm
    left[0, 3, 2] += 0.001  # frame 0: vertex 3 a millimetre out, nothing torn
    r = tool.tears(faces, came, left)
    assert r["torn"] == 1 and r["frames_torn"] == 1 and r["frames"] == 2
    assert r["pops"] == 2
    assert abs(r["longest_cm"] - (np.hypot(1.0, 6.0) - 1.0)) < 1e-6
    assert abs(r["move_max_cm"] - 3.0) < 1e-9
