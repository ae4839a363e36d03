"""Body masks, clearance and the clearest frames (torchtrack.tracking.clearance) against plain loops: OpenCV's
undistortion and an analytic ray - ellipsoid test per pixel, brute-force distances."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError, ShapeError
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.clearance import PixelTiles, body_masks, clear_frame_masks, clearance_px, stays_near

from conftest import facing_pair_rig as _rig
from conftest import pose_at as _pose

W, H = 64, 64


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


@pytest.mark.parametrize("W, H, bones", [(64, 64, None), (61, 45, None), (160, 120, ("l_foot", "r_foot"))])
def test_body_masks_match_a_plain_loop_over_pixels_and_ellipsoids(skel, W, H, bones):
    """Whole 8 x 8 tiles, an image that is not, and the feet's blobs alone (``bones``)."""
    import cv2

    rig = _rig(k1=-0.6, W=W, H=H)
    if bones is not None:  # the feet magnified
        rig.K[:, :2, :2] *= 3.0
    nan = torch.full_like(_pose(skel, 0.0), float("nan"))
    angles = torch.stack([_pose(skel, 0.0), _pose(skel, 0.3, -1.0), nan])  # the second off-centre in view b
    got = body_masks(rig, skel, angles, blob_scale=1.2, bones=bones)
    assert got.shape == (3, 2, H, W) and got.dtype == torch.bool
    assert got[2].all()  # an untracked frame: the body may be anywhere
    assert torch.equal(body_masks(rig, skel, angles, 1.2, tiles=PixelTiles(rig), bones=bones), got)  # rays reused
    with pytest.raises(InputError, match="pixel tiles"):  # another rig's rays are refused, not misread
        body_masks(rig, skel, angles, 1.2, tiles=PixelTiles(_rig(k1=-0.6, W=W + 8, H=H)))
    blobs = BlobModel.from_config(skel)
    centres, R = blobs.ellipsoids(skel.forward(angles[:2]).bone_frames)
    axes = (blobs.semi_axes * 1.2).double().numpy()
    v, u = np.mgrid[0:H, 0:W]
    pix = np.stack([u.ravel(), v.ravel()]).astype(np.float64)  # (2, HW)
    for t in range(2):
        for c in range(2):
            Rc, tc = rig.R_cam_world[c].double().numpy(), rig.t_cam_world[c].double().numpy()
            eye = -Rc.T @ tc
            xy = cv2.undistortPoints(pix[:2].T[:, None], rig.K[c].double().numpy(),
                                     rig.dist[c].double().numpy())[:, 0]  # (HW, 2) OpenCV's undistortion
            d = Rc.T @ np.concatenate([xy.T, np.ones((1, H * W))])  # (3, HW) ray directions
            want = np.zeros(H * W, bool)
            for k in range(len(axes)):  # |A (eye + s d - c)|^2 = 1 in the ellipsoid's unit frame, some s > 0
                if bones is not None and skel.bone_names[int(blobs.bone_of_blob[k])] not in bones:
                    continue
                A = R[t, k].double().numpy().T / axes[k][:, None]
                o, dd = A @ (eye - centres[t, k].double().numpy()), A @ d  # (3,), (3, HW)
                a, b, cc = (dd * dd).sum(0), 2 * o @ dd, o @ o - 1
                disc = b * b - 4 * a * cc
                want |= (disc >= 0) & ((-b + np.sqrt(np.maximum(disc, 0))) / (2 * a) > 0)
            want = want.reshape(H, W)
            mismatch = got[t, c].numpy() != want
            assert want.sum() > (50 if bones is None else 20), want.sum()  # the body is in view
            assert mismatch.sum() <= 2, (t, c, mismatch.sum())  # only rays grazing a rim may differ


def test_clearance_is_the_distance_to_the_nearest_set_pixel():
    gen = torch.Generator().manual_seed(0)
    masks = torch.rand(3, 2, 9, 11, generator=gen) > 0.93
    masks[1, 1] = False
    got = clearance_px(masks)
    v, u = np.mgrid[0:9, 0:11]
    for i in range(3):
        for c in range(2):
            m = masks[i, c].numpy()
            if not m.any():
                assert torch.isinf(got[i, c]).all()
                continue
            d = np.sqrt((v[..., None] - v[m]) ** 2 + (u[..., None] - u[m]) ** 2).min(-1)
            np.testing.assert_allclose(got[i, c].numpy(), d, atol=1e-5)


def test_clearance_within_a_radius_gives_the_same_clear_frames():
    """Distances up to ``within_px`` as the plain loop's, the others no nearer; clear_frame_masks, which compares
    them with thresholds up to that, keeps the same frames from either."""
    gen = torch.Generator().manual_seed(1)
    masks = torch.zeros(12, 40, 60, dtype=torch.bool)
    for i in range(12):  # a blob that moves across the image, one frame without it
        y, x = 5 + 2 * i, 4 + 4 * i
        masks[i, y:y + 6, x:x + 5] = torch.rand(6, 5, generator=gen) > 0.3
    masks[7] = False
    full, bounded = clearance_px(masks), clearance_px(masks, within_px=6.0)
    v, u = np.mgrid[0:40, 0:60]
    for i in range(12):
        m = masks[i].numpy()
        if m.any():
            d = np.sqrt((v[..., None] - v[m]) ** 2 + (u[..., None] - u[m]) ** 2).min(-1)
            np.testing.assert_allclose(full[i].numpy(), d, atol=1e-5)
    near = full <= 6.0
    assert torch.equal(bounded[near], full[near]) and (bounded[~near] > 6.0).all() and torch.isinf(bounded).any()
    for k, clear_px, near_px in ((4, 6.0, 0.0), (4, 3.0, 6.0), (20, 6.0, 5.0)):
        assert torch.equal(clear_frame_masks(bounded, k, clear_px, near_px),
                           clear_frame_masks(full, k, clear_px, near_px))
    with pytest.raises(InputError, match="within_px"):
        clearance_px(masks, within_px=0.0)


def test_clear_frame_masks_keep_the_clearest_frames_and_never_the_body():
    k, big = 5, 20.0
    cases = {  # clearance over 12 frames -> the frames kept
        "many frames far": ([25, 30, 40, 21, 22, 23, 20, 0, 0, 3, 1, 2], [0, 1, 2, 3, 4, 5, 6]),
        "few far: the 5 clearest": ([0, 0, 0, 4, 9, 25, 30, 1, 2, 0, 0, 0], [3, 4, 5, 6, 8]),
        "ties at the 5th": ([7, 7, 7, 9, 9, 9, 0, 0, 0, 0, 1, 1], [0, 1, 2, 3, 4, 5]),
        "only 3 off the body": ([0, 0, 0, 0, 0, 0, 0, 0, 0, 4, 6, 8], [9, 10, 11]),
        "never clear": ([0] * 12, []),
    }
    clearance = torch.tensor([c for c, _ in cases.values()], dtype=torch.float32).T[:, :, None]  # (12, 5, 1)
    used = ~clear_frame_masks(clearance, k, big)
    for j, (name, (_, keep)) in enumerate(cases.items()):
        assert torch.nonzero(used[:, j, 0])[:, 0].tolist() == keep, name
    with pytest.raises(ShapeError):
        clear_frame_masks(torch.zeros(4, 5), k, big)


def test_clear_frame_masks_leave_pixels_that_stay_near_the_body_to_the_fallback():
    """near_px: a pixel with fewer than k frames at least near_px clear of the body keeps no frame; the others
    keep what they keep without it (against a plain loop over pixels)."""
    k, big, near = 5, 20.0, 6.0
    gen = torch.Generator().manual_seed(3)
    clearance = (torch.rand(12, 40, 7, generator=gen) * 14).floor()  # (12 frames, 40 x 7 pixels), 0-13 px
    clearance[:, 0, 0] = torch.tensor([2.0, 3, 2, 3, 4, 5, 2, 3, 1, 0, 0, 5])  # just outside a body that stays
    without = clear_frame_masks(clearance, k, big)
    got = clear_frame_masks(clearance, k, big, near)
    assert bool(got[:, 0, 0].all()) and not bool(without[:, 0, 0].all())
    alone = stays_near(clearance, k, near)  # (40, 7): the rule on its own
    for i in range(40):
        for j in range(7):
            far = sum(float(c) >= near for c in clearance[:, i, j])
            expect = [True] * 12 if far < k else without[:, i, j].tolist()
            assert got[:, i, j].tolist() == expect, (i, j)
            assert bool(alone[i, j]) == (far < k), (i, j)
    assert torch.equal(clear_frame_masks(clearance, k, big, 0.0), without)
