"""Pose2Sim's BODY_25B keypoints mapped onto our skeleton's output points (torchtrack.io.pose2sim.LANDMARK_MAP).

The reference for the mapping is the template skeleton's own geometry, scaled by the subject's limbs: a mapped
point must sit where the template puts the point of that name. BODY_25B's ``Head`` is the top of the head.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data

from torchtrack.io.pose2sim import LANDMARK_MAP, reference_landmarks
from torchtrack.skeleton import Skeleton


@pytest.fixture(scope="module")
def mapped():
    demo = shared_data("pose2sim_demo")
    names, points = reference_landmarks(demo)
    return names, points


def test_every_mapped_point_is_a_skeleton_output(mapped):
    names, points = mapped
    outputs = Skeleton.from_urdf().output_names
    assert names == list(LANDMARK_MAP)
    assert set(names) <= set(outputs), sorted(set(names) - set(outputs))
    assert points.shape == (100, len(names), 3) and np.isfinite(points).all()


def test_the_reference_head_point_is_the_head_top(mapped):
    """Neck to BODY_25B Head, median over the clip, against the template scaled by the subject's thighs and
    shanks (pose-independent lengths): within 15 % of neck -> head_top, and far from neck -> head centre."""
    names, points = mapped
    skel = Skeleton.from_urdf()
    rest = dict(zip(skel.output_names, skel.forward(skel.rest_angles()[None]).output_points[0].numpy()))
    ref = {n: points[:, i] for i, n in enumerate(names)}  # (T, 3) each

    def ref_length(a: str, b: str) -> float:
        return float(np.median(np.linalg.norm(ref[a] - ref[b], axis=-1)))

    def model_length(a: str, b: str) -> float:
        return float(np.linalg.norm(rest[a] - rest[b]))

    legs = [("l_hip", "l_knee"), ("l_knee", "l_ankle"), ("r_hip", "r_knee"), ("r_knee", "r_ankle")]
    scale = float(np.median([ref_length(a, b) / model_length(a, b) for a, b in legs]))
    neck_head = ref_length("neck", "head_top")
    to_top, to_centre = scale * model_length("neck", "head_top"), scale * model_length("neck", "head")
    assert abs(neck_head - to_top) < 0.15 * to_top, (neck_head, to_top)
    assert neck_head > 1.5 * to_centre, (neck_head, to_centre)


def test_the_filtered_reference_is_the_raw_one_smoothed():
    """Pose2Sim's filtered keypoints: the same points in the same frames (within a few cm of the raw ones on
    average), with far less frame-to-frame jitter (the RMS of the second difference over frames)."""
    from torchtrack.io.pose2sim import REFERENCE_FILTERED, reference_keypoints

    shared_data("pose2sim_demo", REFERENCE_FILTERED)
    demo = shared_data("pose2sim_demo")
    names, raw = reference_keypoints(demo)
    names_f, filt = reference_keypoints(demo, filtered=True)
    assert names_f == names and filt.shape == raw.shape and np.isfinite(filt).all()
    apart = np.linalg.norm(filt - raw, axis=-1)
    assert np.median(apart) < 0.02 and apart.mean() < 0.03, (np.median(apart), apart.mean())

    def jitter(x):
        return float(np.sqrt((np.diff(x, 2, axis=0) ** 2).sum(-1).mean()))

    assert jitter(filt) < 0.2 * jitter(raw), (jitter(filt), jitter(raw))
    _, lm = reference_landmarks(demo, filtered=True)
    assert lm.shape == (100, len(LANDMARK_MAP), 3)
    np.testing.assert_allclose(lm[:, list(LANDMARK_MAP).index("pelvis")],
                               filt[:, [names.index("RHip"), names.index("LHip")]].mean(1))
