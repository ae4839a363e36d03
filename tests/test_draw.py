"""Pose pictures: overlays against cv2.projectPoints and a brute-force ray-cast silhouette; skeleton clouds."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cameras import CameraRig
from torchtrack.checks import InputError, ShapeError
from torchtrack.conventions import LANDMARK_EDGES, LANDMARKS
from torchtrack.logging import RunLogger
from torchtrack.tracking.draw import (CENTRE_RGB, LEFT_RGB, RIGHT_RGB, VOXEL_RGB, _pixels, draw_pose_overlays,
                                      ellipsoid_rim_points, landmark_colours, skeleton_cloud)

W, H = 320, 240
DIST = [[0.0] * 5, [-0.25, 0.08, 0.001, -0.002, 0.0]]  # camera 0 pinhole, camera 1 with barrel distortion


def look_at(eye, target) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV extrinsics (R_cam_world, t_cam_world) of a camera at ``eye`` looking at ``target``, Z up."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ eye


def make_rig(eyes=((3.0, 0.5, 1.2), (-0.5, -3.0, 1.5)), target=(0.0, 0.0, 1.0), device="cpu") -> CameraRig:
    Rs, ts = zip(*[look_at(e, target) for e in eyes])
    C = len(eyes)
    K = torch.tensor([[[200.0, 0, 159.5], [0, 200.0, 119.5], [0, 0, 1]]] * C, dtype=torch.float64)
    return CameraRig([f"cam{c}" for c in range(C)], K, torch.tensor(np.stack(Rs)), torch.tensor(np.stack(ts)),
                     torch.tensor([[W, H]] * C), torch.tensor(DIST[:C], dtype=torch.float64)).to(device)


def cv2_project(rig: CameraRig, c: int, pts: np.ndarray) -> np.ndarray:
    """Reference: cv2.projectPoints of (N, 3) world points into camera c -> (N, 2)."""
    R, t = rig.R_cam_world[c].cpu().numpy(), rig.t_cam_world[c].cpu().numpy()
    return cv2.projectPoints(pts.astype(np.float64), cv2.Rodrigues(R)[0], t, rig.K[c].cpu().numpy(),
                             rig.dist[c].cpu().numpy())[0][:, 0]


def standing_pose() -> torch.Tensor:
    """(16, 3) a plausible upright pose facing +X at the origin, metres."""
    return torch.tensor([
        [0, 0, 1.0], [0, 0, 1.3], [0, 0, 1.5], [0, 0, 1.65],
        [0, 0.2, 1.45], [0.05, 0.25, 1.2], [0.15, 0.25, 1.0],
        [0, -0.2, 1.45], [0.05, -0.25, 1.2], [0.15, -0.25, 1.0],
        [0, 0.1, 0.95], [0.05, 0.12, 0.5], [0, 0.12, 0.08],
        [0, -0.1, 0.95], [0.05, -0.12, 0.5], [0, -0.12, 0.08],
    ], dtype=torch.float64)


def random_rotation(seed: int) -> torch.Tensor:
    rotvec = np.random.default_rng(seed).normal(size=3)
    return torch.tensor(cv2.Rodrigues(rotvec)[0])


def ray_cast_mask(rig: CameraRig, c: int, centre, R, semi_axes) -> np.ndarray:
    """Reference silhouette: (H, W) bool, pixels whose ray (cv2.undistortPoints) hits the ellipsoid in front."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    uv = np.stack([u.ravel(), v.ravel()], -1)[:, None]  # (H W, 1, 2)
    K, dist = rig.K[c].cpu().numpy(), rig.dist[c].cpu().numpy()
    xy = cv2.undistortPoints(uv, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    xy = xy[:, 0]  # (H W, 2) normalized, undistorted
    R_cw, t_cw = rig.R_cam_world[c].cpu().numpy(), rig.t_cam_world[c].cpu().numpy()
    d_world = np.concatenate([xy, np.ones_like(xy[:, :1])], 1) @ R_cw  # R^T d for every ray
    eye = -R_cw.T @ t_cw
    R, a, centre = np.asarray(R), np.asarray(semi_axes), np.asarray(centre)
    o = (R.T @ (eye - centre)) / a  # unit-sphere frame
    d = (d_world @ R) / a
    A, B, Cq = (d * d).sum(1), 2 * d @ o, o @ o - 1  # |o + s d|^2 = 1
    disc = B * B - 4 * A * Cq
    far = (-B + np.sqrt(np.maximum(disc, 0))) / (2 * A)  # the farther root: > 0 when any hit is in front
    return ((disc >= 0) & (far > 0)).reshape(H, W)


def polygon_mask(uv: np.ndarray) -> np.ndarray:
    """Reference fill: (H, W) bool, pixel centres inside the closed polygon ``uv (S, 2)`` (even-odd rule)."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    p = np.stack([u.ravel(), v.ravel()], -1)[:, None]  # (H W, 1, 2)
    a, b = uv[None], np.roll(uv, -1, 0)[None]  # (1, S, 2) edge ends
    straddles = (a[..., 1] > p[..., 1]) != (b[..., 1] > p[..., 1])  # (H W, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        u_cross = a[..., 0] + (p[..., 1] - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    return ((straddles & (u_cross > p[..., 0])).sum(1) % 2 == 1).reshape(H, W)


def drawn(images: torch.Tensor) -> np.ndarray:
    """(C, 3, H, W) -> (C, H, W) bool: pixels drawn on a black image."""
    return (images.cpu().sum(1) > 0).numpy()


# ------------------------------------------------------------------------------------------------ landmarks
def test_pixels_match_projectpoints(device):
    rig = make_rig(device=device)
    pts = torch.tensor(np.random.default_rng(0).uniform([-0.5, -0.5, 0.3], [0.5, 0.5, 1.7], (200, 3)))
    uv, drawable, inside = _pixels(rig, pts.to(device))
    assert uv.shape == (2, 200, 2) and inside.shape == drawable.shape == (2, 200)
    _, valid = rig.project(pts.to(device))
    assert torch.equal(inside, valid) and bool(inside.all())
    for c in range(2):
        np.testing.assert_allclose(uv[c].cpu().numpy(), cv2_project(rig, c, pts.numpy()), atol=1e-6)


@pytest.mark.parametrize("seed", range(4))
def test_joint_dot_centred_on_projectpoints(seed, device):
    rig = make_rig(device=device)
    p = np.random.default_rng(seed).uniform([-0.4, -0.4, 0.5], [0.4, 0.4, 1.5])
    landmarks = torch.full((16, 3), float("nan"), dtype=torch.float64)
    landmarks[0] = torch.from_numpy(p)  # only the pelvis: no bone has two finite ends
    out = draw_pose_overlays(torch.zeros(2, 3, H, W, device=device), rig, landmarks.to(device), joint_radius_px=4)
    for c, mask in enumerate(drawn(out)):
        ys, xs = np.nonzero(mask)
        assert 40 < len(xs) < 80  # one disc of radius 4
        np.testing.assert_allclose([xs.mean(), ys.mean()], cv2_project(rig, c, p[None])[0], atol=0.25)
        np.testing.assert_allclose(out[c, :, ys[0], xs[0]].cpu().numpy(), CENTRE_RGB, atol=1e-6)


def test_skeleton_colours_by_side():
    rig = make_rig()
    landmarks = standing_pose()
    out = draw_pose_overlays(torch.zeros(2, 3, H, W), rig, landmarks, joint_radius_px=2).numpy()
    joint_rgb, bone_rgb = landmark_colours()
    assert bone_rgb[LANDMARK_EDGES.index((2, 4))] == LEFT_RGB and bone_rgb[LANDMARK_EDGES.index((0, 13))] == RIGHT_RGB
    for c in range(2):
        uv = np.rint(cv2_project(rig, c, landmarks.numpy())).astype(int)
        for j, name in enumerate(LANDMARKS):  # joints are drawn last: each joint's pixel has its side's colour
            np.testing.assert_allclose(out[c, :, uv[j, 1], uv[j, 0]], joint_rgb[j], atol=1e-6, err_msg=name)
        mid = np.rint(cv2_project(rig, c, landmarks[[11, 12]].mean(0, keepdim=True).numpy())[0]).astype(int)
        np.testing.assert_allclose(out[c, :, mid[1], mid[0]], LEFT_RGB, atol=1e-6)  # middle of the left shin


def test_behind_camera_and_non_finite_not_drawn(device):
    rig = make_rig(device=device)
    images = torch.rand(2, 3, H, W, generator=torch.Generator().manual_seed(0)).to(device)
    eye = rig.centers()[0].cpu()
    forward = rig.R_cam_world[0, 2].cpu()  # camera 0's optical axis in the world
    jitter = 0.03 * torch.randn(16, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    behind = eye - 0.5 * forward + jitter  # (16, 3) half a metre behind camera 0
    rig0 = rig.subset([0])
    out = draw_pose_overlays(images[:1], rig0, behind.to(device))
    assert torch.equal(out, images[:1])
    out = draw_pose_overlays(images, rig, torch.full((16, 3), float("nan"), device=device))
    assert torch.equal(out, images)
    # Half the skeleton behind camera 0: only bones with both ends in front are drawn, and nothing crashes.
    half = standing_pose()
    half[4:] = behind[4:]
    out = draw_pose_overlays(torch.zeros(1, 3, H, W, device=device), rig0, half.to(device), joint_radius_px=0)
    mask = drawn(out)[0]
    ref = np.zeros((H, W), np.uint8)
    uv = cv2_project(rig, 0, half[:4].numpy())
    cv2.polylines(ref, [np.rint(uv).astype(np.int32)], False, 1, 5)  # pelvis-spine-neck-head, widened
    assert mask.any() and not (mask & ~ref.astype(bool)).any()


def test_landmarks_outside_image_are_clipped_lines():
    rig = make_rig()
    landmarks = standing_pose()
    landmarks[3] = torch.tensor([0.0, 0.0, 4.0])  # head far above: out of both images, in front
    out = draw_pose_overlays(torch.zeros(2, 3, H, W), rig, landmarks)
    for c in range(2):
        uv = cv2_project(rig, c, landmarks[[2, 3]].numpy())
        assert not (-0.5 <= uv[1, 1] < H - 0.5)
        top = np.nonzero(drawn(out)[c].any(1))[0].min()
        assert top <= 1  # the neck-head bone runs to the image edge


# ------------------------------------------------------------------------------------------------ blob outlines
ELLIPSOID = dict(centre=(0.1, -0.05, 1.0), semi_axes=(0.35, 0.2, 0.12))


def test_rim_points_tangent_and_on_surface():
    rig = make_rig()
    centres = torch.tensor([ELLIPSOID["centre"], (0.0, 0.2, 0.6)], dtype=torch.float64)
    R = torch.stack([random_rotation(0), random_rotation(1)])
    a = torch.tensor([ELLIPSOID["semi_axes"], (0.1, 0.1, 0.1)], dtype=torch.float64)
    rim, outside = ellipsoid_rim_points(rig.centers(), centres, R, a, num_samples=50)
    assert rim.shape == (2, 2, 50, 3) and bool(outside.all())
    for c in range(2):
        o = rig.centers()[c]
        for k in range(2):
            to_unit = lambda x: (x - centres[k]) @ R[k] / a[k]  # noqa: E731  world -> unit-sphere frame
            q, e = to_unit(rim[c, k]), to_unit(o)
            torch.testing.assert_close(q.norm(dim=-1), torch.ones(50, dtype=torch.float64))  # on the surface
            d = q - e  # viewing rays; |e + s d|^2 = 1 has a double root where the ray is tangent
            disc = (d @ e) ** 2 - (d * d).sum(-1) * (e @ e - 1)
            assert float(disc.abs().max()) < 1e-9 * float((d * d).sum(-1).max() * (e @ e))


@pytest.mark.parametrize("seed", range(3))
def test_outline_matches_ray_cast_silhouette(seed):
    rig = make_rig(eyes=((1.5, 0.3, 1.1), (-0.3, -1.6, 1.3)))  # close: silhouettes of 1700 to 3400 pixels
    centre, a, R = torch.tensor([ELLIPSOID["centre"]]), torch.tensor([ELLIPSOID["semi_axes"]]), random_rotation(seed)
    rim, _ = ellipsoid_rim_points(rig.centers(), centre, R[None], a, num_samples=128)
    uv, _ = rig.project(rim)  # (C, C, 1, S, 2)
    out = draw_pose_overlays(torch.zeros(2, 3, H, W), rig, None, centre, R[None], a, outline_width_px=1)
    for c, outline in enumerate(drawn(out)):
        ref = ray_cast_mask(rig, c, centre[0].numpy(), R.numpy(), a[0].numpy())
        poly = polygon_mask(uv[c, c, 0].numpy())
        iou = (poly & ref).sum() / (poly | ref).sum()
        assert ref.sum() > 1500 and iou > 0.99, f"camera {c}: IoU {iou:.4f}"
        # The drawn outline runs along the silhouette's boundary.
        ring = np.ones((3, 3), np.uint8)
        band = cv2.dilate(ref.astype(np.uint8), ring, iterations=2) & ~cv2.erode(ref.astype(np.uint8), ring,
                                                                                 iterations=2).astype(bool)
        assert outline.any() and not (outline & ~band.astype(bool)).any()
        boundary = ref & ~cv2.erode(ref.astype(np.uint8), ring).astype(bool)
        near = cv2.dilate(outline.astype(np.uint8), ring).astype(bool)
        assert (boundary & near).sum() > 0.95 * boundary.sum()


def test_blob_through_camera_plane_and_around_camera():
    rig = make_rig().subset([0])
    eye = rig.centers()[0].float()
    images = torch.zeros(1, 3, H, W)
    # An ellipsoid around the camera: no rim, nothing drawn.
    out = draw_pose_overlays(images, rig, None, eye[None], torch.eye(3)[None], torch.tensor([[0.5, 0.5, 0.5]]))
    assert torch.equal(out, images)
    # A long ellipsoid crossing the image plane beside the camera: part of its rim is behind the camera.
    R = torch.tensor(look_at([0, 0, 0], rig.R_cam_world[0, 2].numpy())[0].T, dtype=torch.float32)  # z: optical axis
    R = R[:, [2, 0, 1]]  # first axis along the optical axis
    centre = eye + 0.3 * rig.R_cam_world[0, 0].float()  # 0.3 m to the camera's right
    a = torch.tensor([[2.0, 0.1, 0.1]])
    rim, outside = ellipsoid_rim_points(eye[None], centre[None], R[None], a)
    z = (rig.world_to_camera(rim[0, 0].double())[0, :, 2])
    assert bool(outside.all()) and bool((z < 0).any()) and bool((z > 0).any())
    out = draw_pose_overlays(images, rig, None, centre[None], R[None], a, outline_width_px=1)
    ref = ray_cast_mask(rig, 0, centre.numpy(), R.numpy(), a[0].numpy()).astype(np.uint8)
    band = cv2.dilate(ref, np.ones((3, 3), np.uint8), iterations=2) & ~cv2.erode(ref, np.ones((3, 3), np.uint8),
                                                                                  iterations=2).astype(bool)
    outline = drawn(out)[0]
    assert torch.isfinite(out).all() and outline.any() and not (outline & ~band.astype(bool)).any()


def test_device_and_dtype_follow_images(device):
    rig = make_rig(device=device)
    images = torch.rand(2, 3, H, W, dtype=torch.float64, generator=torch.Generator().manual_seed(3)).to(device)
    centre, a = torch.tensor([ELLIPSOID["centre"]]), torch.tensor([ELLIPSOID["semi_axes"]])
    args = (standing_pose(), centre, random_rotation(0)[None].float(), a, torch.tensor([[0.0, 1.0, 0.0]]))
    out = draw_pose_overlays(images, rig, *(x.to(device) for x in args))
    assert out.shape == images.shape and out.dtype == torch.float64 and out.device == images.device
    cpu = draw_pose_overlays(images.cpu(), make_rig(), *args)
    assert (out.cpu() != cpu).float().mean() < 1e-3  # the same picture up to float rounding at pixel borders
    assert (out != images).any()


def test_bad_input():
    rig = make_rig()
    images = torch.zeros(2, 3, H, W)
    with pytest.raises(ShapeError, match="images"):
        draw_pose_overlays(torch.zeros(3, 3, H, W), rig)
    with pytest.raises(InputError, match="resized"):
        draw_pose_overlays(torch.zeros(2, 3, H // 2, W // 2), rig)
    with pytest.raises(InputError, match="float"):
        draw_pose_overlays(images.to(torch.uint8), rig)
    with pytest.raises(ShapeError, match="landmarks"):
        draw_pose_overlays(images, rig, torch.zeros(15, 3))
    with pytest.raises(InputError, match="all or none"):
        draw_pose_overlays(images, rig, None, torch.zeros(1, 3))
    with pytest.raises(ShapeError, match="blob_colours"):
        draw_pose_overlays(images, rig, None, torch.zeros(1, 3), torch.eye(3)[None], torch.ones(1, 3),
                           torch.ones(2, 3))
    with pytest.raises(InputError, match="semi_axes"):
        ellipsoid_rim_points(rig.centers(), torch.zeros(1, 3), torch.eye(3)[None], torch.zeros(1, 3))
    with pytest.raises(ShapeError, match="R_world_blob"):
        ellipsoid_rim_points(rig.centers(), torch.zeros(1, 3), torch.eye(3), torch.ones(1, 3))
    with pytest.raises(InputError, match="points_per_bone"):
        skeleton_cloud(standing_pose(), points_per_bone=1)


# ------------------------------------------------------------------------------------------------ 3D view
def test_skeleton_cloud_points_on_bones(device):
    landmarks = standing_pose().to(device)
    points, colours = skeleton_cloud(landmarks, points_per_bone=5)
    E = len(LANDMARK_EDGES)
    assert points.shape == colours.shape == (E * 5, 3) and points.device == landmarks.device
    for e, (i, j) in enumerate(LANDMARK_EDGES):
        ref = torch.stack([landmarks[i] + t * (landmarks[j] - landmarks[i]) for t in (0, 0.25, 0.5, 0.75, 1)])
        torch.testing.assert_close(points[5 * e:5 * e + 5], ref)
        assert colours[5 * e].tolist() == pytest.approx(landmark_colours()[1][e])


def test_pose_cloud_event(tmp_path, device):
    from tensorboard.backend.event_processing import event_accumulator as ea
    from tensorboard.util import tensor_util

    voxels = torch.rand(300, 3, generator=torch.Generator().manual_seed(4)).to(device)
    landmarks = standing_pose().to(device)
    landmarks[6] = float("nan")  # a lost wrist: its bone is left out
    with RunLogger(tmp_path) as run:
        run.pose_cloud(5, "pose/cloud", voxels, landmarks, points_per_bone=4, max_voxels=100)
    acc = ea.EventAccumulator(str(tmp_path), size_guidance={ea.TENSORS: 0})
    acc.Reload()
    assert sorted(acc.Tags()["tensors"]) == ["pose/cloud_COLOR", "pose/cloud_VERTEX"]
    event = acc.Tensors("pose/cloud_VERTEX")[0]
    vertices = tensor_util.make_ndarray(event.tensor_proto)[0]
    rgb = tensor_util.make_ndarray(acc.Tensors("pose/cloud_COLOR")[0].tensor_proto)[0]
    n_bones = (len(LANDMARK_EDGES) - 1) * 4
    assert event.step == 5 and vertices.shape == rgb.shape == (100 + n_bones, 3)
    points, _ = skeleton_cloud(landmarks.cpu(), 4)
    np.testing.assert_allclose(vertices[100:], points[torch.isfinite(points).all(-1)].float().numpy())
    np.testing.assert_array_equal(rgb[:100], np.full((100, 3), round(VOXEL_RGB[0] * 255)))
    assert (rgb[100:].max(1) == 255).all()  # bright skeleton
