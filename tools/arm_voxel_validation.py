"""Measure the arm lift's thinning of the arm points (``inference.motion.self_contact.ARM_VOXEL_M``)
on the validation clip CMU 02_02 (first chosen on 01_01, a test clip): the abduction angles with
1, 2 and 3 cm cells against 1 cm (mean and largest difference over frames and both arms), the
number of arm points and the lift's ms per frame, neutral and heaviest adult.

    python tools/arm_voxel_validation.py
"""
from __future__ import annotations

import time

import numpy as np

import inference.motion.self_contact as sc
from inference.body import BodyModel
from training.protocol import validation_motions

VOXELS_M = (0.01, 0.02, 0.03)


def main() -> None:
    body = BodyModel.load()
    print("| body | arm cell cm | arm points | abduction mean deg | |angle - 1 cm| mean / max deg | lift ms per frame |")
    print("|---|---|---|---|---|---|")
    for name, shape, motion in validation_motions(body, lift=False):
        angles = {}
        for voxel in VOXELS_M:
            sc.ARM_VOXEL_M = voxel
            lifter = sc.ArmLifter(body, shape)
            t0 = time.perf_counter()
            _, angle = lifter.lift(motion.rotations, motion.translation)
            ms = (time.perf_counter() - t0) * 1e3 / motion.num_frames
            angles[voxel] = np.degrees(np.asarray(angle))
            diff = np.abs(angles[voxel] - angles[VOXELS_M[0]])
            points = sum(len(ids) for _, ids in lifter.arms)
            print(f"| {name} | {voxel * 100:g} | {points} | {angles[voxel].mean():.2f} | {diff.mean():.3f} / {diff.max():.3f} | {ms:.2f} |", flush=True)


if __name__ == "__main__":
    main()
