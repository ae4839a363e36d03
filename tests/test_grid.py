"""Voxel grid specs and the rig's common field of view."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from torchtrack.occupancy import GridSpec, grid_from_rig
from torchtrack.synth.sequence import RigConfig, make_ring_rig


def _seen_by_all(rig, points: np.ndarray) -> np.ndarray:
    """(N,) bool: every camera projects the point inside its image (cv2.projectPoints, independent of the rig)."""
    ok = np.ones(len(points), dtype=bool)
    for c in range(rig.num_cameras):
        R = rig.R_cam_world[c].double().numpy()
        t = rig.t_cam_world[c].double().numpy()
        uv, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, rig.K[c].double().numpy(),
                                  rig.dist[c].double().numpy())
        w, h = rig.image_size_wh[c].tolist()
        z = points @ R.T + t
        ok &= (z[:, 2] > 0) & (uv[:, 0, 0] >= -0.5) & (uv[:, 0, 0] < w - 0.5) & (uv[:, 0, 1] >= -0.5) \
            & (uv[:, 0, 1] < h - 0.5)
    return ok


def test_common_view_box():
    rig = make_ring_rig(RigConfig(num_cameras=6, width=320, height=240)).float()
    spec = grid_from_rig(rig, 0.05, top_z_m=1.8)
    lo, hi = np.array(spec.lower_m), np.array(spec.upper_m)
    mid = (lo + hi) / 2
    # edge midpoints of the box's floor and top, 5 cm inside: seen by all; 30 cm outside: not
    for z in (0.0, 1.8):
        for axis in (0, 1):
            for side, sign in ((lo, 1), (hi, -1)):
                p = mid.copy()
                p[2] = z
                p[axis] = side[axis] + sign * 0.05
                q = p.copy()
                q[axis] = side[axis] - sign * 0.30
                assert _seen_by_all(rig, p[None])[0], (z, axis, p)
                assert not (_seen_by_all(rig, q[None])[0] and _seen_by_all(rig, np.r_[q[:2], 1.8 - z][None])[0])


def test_grid_from_rig_leaves_the_callers_rig_alone():
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120)).float()
    grid_from_rig(rig, 0.1)
    assert rig.K.dtype == torch.float32  # nn.Module.double() would have converted it in place


def test_centres_and_index_of_round_trip():
    spec = GridSpec((-0.3, -0.2, 0.0), (0.3, 0.2, 0.5), 0.1)
    assert spec.shape == (6, 4, 5) and spec.num_voxels == 120
    c = spec.centres(torch.float64)
    idx, inside = spec.index_of(c)
    assert bool(inside.all()) and torch.equal(idx, torch.arange(120))
    # the flat index is (ix * ny + iy) * nz + iz
    torch.testing.assert_close(c[(2 * 4 + 3) * 5 + 1], torch.tensor([-0.05, 0.15, 0.15], dtype=torch.float64))
    _, out = spec.index_of(torch.tensor([[0.31, 0.0, 0.1]], dtype=torch.float64))
    assert not bool(out[0])


def test_points_in_messages_are_rounded():
    from torchtrack.occupancy.grid import format_point

    assert format_point((-1.1999999999999997, 0.0, 2.1000000000000005)) == "(-1.2, 0, 2.1)"
    assert format_point((0.12345, -3.0, 10.0)) == "(0.123, -3, 10)"


def test_capture_views_half_at_least_three_and_all_for_the_hull():
    from torchtrack.occupancy import capture_views

    assert [capture_views(c) for c in (1, 2, 3, 4, 5, 6, 7, 8, 12, 13)] == [1, 2, 3, 3, 3, 3, 4, 4, 6, 7]
    assert [capture_views(c, "hull") for c in (4, 8)] == [4, 8]


def test_fewer_views_cover_more_floor():
    """The box that all but two of 8 ring cameras see holds the one all 8 see."""
    rig = make_ring_rig(RigConfig(num_cameras=8))
    every, most = grid_from_rig(rig, 0.05), grid_from_rig(rig, 0.05, min_views=6)
    assert all(m <= e for m, e in zip(most.lower_m, every.lower_m))
    assert all(m >= e for m, e in zip(most.upper_m, every.upper_m))
    assert most.num_voxels > 1.5 * every.num_voxels
