"""CameraRig: projection and rays against OpenCV (an independent implementation), masks by hand, batching."""

from __future__ import annotations

import math
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data

from torchtrack.cameras import CameraRig, load_calibration
from torchtrack.cameras.distortion import fold_radius_sq
from torchtrack.checks import InputError, ShapeError

# Real calibrations whose distortion values the accuracy tests use (strong barrel k1 = -0.34 webcam, positive
# k1 webcams, k1-only mouse rig cameras, the Qualisys rig with its k2).
REAL_FILES = [
    ("calibrations", "caliscope", "4_cam_recording_camera_array.toml"),
    ("calibrations", "caliscope", "post_optimization_camera_array.toml"),
    ("calibrations", "anipose", "7cam-allen-mouse_calibration.toml"),
    ("pose2sim_demo", "calibration", "Calib.qca.txt"),
]
#: Realistic fisheye coefficients (k1..k4 of a ~180 degree lens, as cv2.fisheye.calibrate returns them).
FISHEYE_K = [0.0265, -0.0052, 0.0011, -0.00021]


def _real_rig(parts, dtype=torch.float64) -> CameraRig:
    return load_calibration(shared_data(*parts), dtype=dtype)


def _points_in_view(rig: CameraRig, n: int, gen: torch.Generator, margin: float = 1.1) -> torch.Tensor:
    """World points ``(C * n, 3)``: for each camera, n points inside (about) its field of view, 2..6 length
    units of the rig's translation scale in front of it."""
    scale = float(rig.t_cam_world.norm(dim=-1).mean().clamp(min=1.0))
    pts = []
    for c in range(len(rig)):
        K, (w, h) = rig.K[c].double(), rig.image_size_wh[c].tolist()
        uv = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([w, h]) * margin
        uv -= torch.tensor([w, h]) * (margin - 1) / 2
        xy = (uv - K[:2, 2]) / torch.stack([K[0, 0], K[1, 1]])  # roughly the field of view (distortion aside)
        z = (0.5 + torch.rand(n, 1, generator=gen, dtype=torch.float64)) * scale
        cam = torch.cat([xy * z, z], -1)
        R, t = rig.R_cam_world[c].double(), rig.t_cam_world[c].double()
        pts.append((cam - t) @ R)  # R^T (x_cam - t)
    return torch.cat(pts)


def _cv2_project(rig: CameraRig, c: int, pts: np.ndarray) -> np.ndarray:
    R, t = rig.R_cam_world[c].double().numpy(), rig.t_cam_world[c].double().numpy()
    K, d = rig.K[c].double().numpy(), rig.dist[c].double().numpy()
    rvec = cv2.Rodrigues(R)[0]
    if rig.fisheye[c]:
        return cv2.fisheye.projectPoints(pts[:, None], rvec, t, K, d[:4])[0][:, 0]
    return cv2.projectPoints(pts, rvec, t, K, d)[0][:, 0]


def _fisheye_rig(dtype=torch.float64) -> CameraRig:
    """Two fisheye cameras and one pinhole camera looking at the origin from different sides."""
    K = torch.tensor([[[400.0, 0, 639.5], [0, 400.0, 479.5], [0, 0, 1]]] * 3, dtype=dtype)
    rotvecs = torch.tensor([[0.1, 0.2, 0.0], [0.0, 2.5, 0.3], [1.2, -0.4, 0.2]], dtype=dtype)
    R = torch.from_numpy(np.stack([cv2.Rodrigues(v.numpy().astype(np.float64))[0] for v in rotvecs])).to(dtype)
    t = torch.tensor([[0.1, -0.2, 3.0], [0.3, 0.1, 2.5], [-0.2, 0.0, 4.0]], dtype=dtype)
    dist = torch.tensor([FISHEYE_K + [0.0], FISHEYE_K + [0.0], [-0.3, 0.1, 0.001, -0.002, -0.01]], dtype=dtype)
    size = torch.tensor([[1280, 960]] * 3)
    return CameraRig(["f0", "f1", "p2"], K, R, t, size, dist, [True, True, False])


# ------------------------------------------------------------------------------------------------ projection
@pytest.mark.parametrize("parts", REAL_FILES, ids=lambda p: p[-1])
def test_project_matches_opencv_float64(parts):
    rig = _real_rig(parts)
    gen = torch.Generator().manual_seed(0)
    pts = _points_in_view(rig, 400, gen)
    uv, valid = rig.project(pts)
    assert uv.shape == (len(rig), pts.shape[0], 2) and valid.shape == (len(rig), pts.shape[0])
    assert uv.dtype == torch.float64
    for c in range(len(rig)):
        ref = _cv2_project(rig, c, pts.numpy())
        v = valid[c].numpy()
        assert v.sum() > 200, "most points of the camera's own sample must be valid"
        err = np.abs(uv[c].numpy()[v] - ref[v]).max()
        assert err < 1e-3, f"{rig.names[c]}: max error {err} px vs cv2.projectPoints"


@pytest.mark.parametrize("parts", REAL_FILES, ids=lambda p: p[-1])
def test_project_float32_tolerance(parts):
    """float32 rig and points: within 0.02 px of OpenCV's float64 answer (float32 epsilon is 6e-8 relative;
    1e3 px coordinates from 1e3 mm translations lose ~1e-3 px, well inside the stated 0.02 px)."""
    rig64 = _real_rig(parts)
    rig32 = _real_rig(parts, torch.float32)
    pts = _points_in_view(rig64, 400, torch.Generator().manual_seed(1)).float()
    uv, valid = rig32.project(pts)
    assert uv.dtype == torch.float32
    for c in range(len(rig32)):
        ref = _cv2_project(rig64, c, pts.double().numpy())
        v = valid[c].numpy()
        assert np.abs(uv[c].double().numpy()[v] - ref[v]).max() < 0.02


def test_fisheye_and_mixed_rig_match_opencv():
    rig = _fisheye_rig()
    pts = _points_in_view(rig, 500, torch.Generator().manual_seed(2), margin=1.3)
    uv, valid = rig.project(pts)
    for c in range(len(rig)):
        ref = _cv2_project(rig, c, pts.numpy())
        v = valid[c].numpy()
        assert v.sum() > 200
        assert np.abs(uv[c].numpy()[v] - ref[v]).max() < 1e-6
    # Mixed rig batched == each camera alone (the fisheye and pinhole paths selected per camera).
    for c in range(len(rig)):
        uv_c, valid_c = rig.subset([c]).project(pts)
        assert torch.equal(valid_c[0], valid[c])
        # Only valid projections are compared: behind the camera the coordinates may be astronomically large,
        # where the batched and single-camera paths differ by float rounding.
        torch.testing.assert_close(uv_c[0][valid[c]], uv[c][valid[c]], rtol=0, atol=1e-9)


def _simple_rig(dist=None) -> CameraRig:
    """One camera at the origin looking along +z: f = 100, 100x60 image, centre (49.5, 29.5)."""
    K = torch.tensor([[[100.0, 0.0, 49.5], [0.0, 100.0, 29.5], [0.0, 0.0, 1.0]]], dtype=torch.float64)
    return CameraRig(["c"], K, torch.eye(3, dtype=torch.float64)[None], torch.zeros(1, 3, dtype=torch.float64),
                     torch.tensor([[100, 60]]), dist)


def test_valid_mask_by_hand():
    rig = _simple_rig()
    # u = 100 x / z + 49.5, v = 100 y / z + 29.5; image: -0.5 <= u < 99.5, -0.5 <= v < 59.5.
    pts = torch.tensor([
        [0.0, 0.0, 1.0],     # centre                          -> valid
        [-0.5, -0.3, 1.0],   # (-0.5, -0.5): first pixel's corner -> valid
        [0.5, 0.0, 1.0],     # u = 99.5: right edge, excluded  -> invalid
        [0.0, 0.3, 1.0],     # v = 59.5: bottom edge, excluded -> invalid
        [0.499, 0.299, 1.0],  # just inside                     -> valid
        [-0.501, 0.0, 1.0],  # just left of the image          -> invalid
        [0.0, 0.0, -1.0],    # behind                          -> invalid
        [0.0, 0.0, 0.0],     # at the centre of projection     -> invalid
        [0.0, 0.0, 1e-7],    # closer than MIN_DEPTH           -> invalid
        [1.0, 0.5, 4.0],     # (74.5, 42): inside              -> valid
    ], dtype=torch.float64)
    uv, valid = rig.project(pts)
    assert valid[0].tolist() == [True, True, False, False, True, False, False, False, False, True]
    torch.testing.assert_close(uv[0, 9], torch.tensor([74.5, 42.0], dtype=torch.float64))
    assert torch.isfinite(uv).all(), "invalid points still get finite coordinates"


def test_valid_excludes_points_folded_back_by_the_distortion():
    """k1 = -0.313 (anipose cam091): rho(r) = r (1 + k1 r^2) turns at r = 1/sqrt(3 |k1|) and returns to 0 at
    r = 1/sqrt(|k1|) (61 degrees off axis): OpenCV projects such a point onto the principal point."""
    k1 = -0.31335387778001184
    rig = _simple_rig(torch.tensor([[k1, 0.0, 0.0, 0.0, 0.0]], dtype=torch.float64))
    r_zero = 1 / math.sqrt(-k1)
    pts = torch.tensor([[r_zero, 0.0, 1.0], [0.3, 0.1, 1.0]], dtype=torch.float64)
    uv, valid = rig.project(pts)
    ref = cv2.projectPoints(pts.numpy(), np.zeros(3), np.zeros(3), rig.K[0].numpy(), rig.dist[0].numpy())[0][:, 0]
    np.testing.assert_allclose(uv[0].numpy(), ref, atol=1e-9)
    assert -0.5 <= ref[0, 0] < 99.5 and -0.5 <= ref[0, 1] < 59.5, "OpenCV puts the far-off-axis point in the image"
    assert valid[0].tolist() == [False, True]
    np.testing.assert_allclose(fold_radius_sq(rig.dist, rig.fisheye_mask).item(), 1 / (3 * -k1), rtol=5e-3)


def test_batched_leading_dims_equal_looped():
    rig = _real_rig(REAL_FILES[0])
    pts = _points_in_view(rig, 30, torch.Generator().manual_seed(3)).reshape(2, 3, 20, 3)  # (B1, B2, N, 3)
    uv, valid = rig.project(pts)
    assert uv.shape == (4, 2, 3, 20, 2) and valid.shape == (4, 2, 3, 20)
    cam = rig.world_to_camera(pts)
    assert cam.shape == (4, 2, 3, 20, 3)
    for i in range(2):
        for j in range(3):
            uv_ij, valid_ij = rig.project(pts[i, j])
            torch.testing.assert_close(uv[:, i, j], uv_ij, rtol=1e-12, atol=1e-9)  # BLAS blocking may differ
            assert torch.equal(valid[:, i, j], valid_ij)
            for c in range(len(rig)):  # and every camera alone
                uv_c, _ = rig.subset([c]).project(pts[i, j])
                torch.testing.assert_close(uv_c[0], uv_ij[c], rtol=1e-12, atol=1e-9)


def test_device_and_dtype(device):
    rig64 = _real_rig(REAL_FILES[0])
    pts = _points_in_view(rig64, 50, torch.Generator().manual_seed(4))
    uv_ref, valid_ref = rig64.project(pts)
    rig = rig64.to(device)
    assert rig.K.device.type == device.type and rig.image_size_wh.dtype == torch.int64
    uv, valid = rig.project(pts.to(device))
    assert uv.device.type == device.type
    torch.testing.assert_close(uv.cpu(), uv_ref, rtol=0, atol=1e-6)
    assert torch.equal(valid.cpu(), valid_ref)
    o, d = rig.pixel_rays(uv)
    assert o.device.type == device.type and d.device.type == device.type
    # float32 rig with float64 points: computed in float64 (the promoted dtype).
    rig32 = rig.to(torch.float32)
    assert rig32.K.dtype == torch.float32 and rig32.fisheye_mask.dtype == torch.bool
    assert rig32.project(pts.to(device))[0].dtype == torch.float64


# ------------------------------------------------------------------------------------------------------ rays
@pytest.mark.parametrize("parts", REAL_FILES, ids=lambda p: p[-1])
def test_pixel_rays_pass_through_the_points(parts):
    rig = _real_rig(parts)
    pts = _points_in_view(rig, 300, torch.Generator().manual_seed(5))
    uv, valid = rig.project(pts)
    origins, dirs = rig.pixel_rays(uv)
    assert origins.shape == dirs.shape == (len(rig), pts.shape[0], 3)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones_like(dirs[..., 0]))
    to_point = pts[None] - origins  # (C, N, 3)
    along = (to_point * dirs).sum(-1)
    dist = (to_point - along[..., None] * dirs).norm(dim=-1)  # point-to-ray distance
    # Metres for caliscope / Qualisys, mm for the anipose mouse rig: 1e-4 of either is far above float64 noise.
    assert dist[valid].max() < 1e-4 and (along[valid] > 0).all()


@pytest.mark.parametrize("parts", REAL_FILES, ids=lambda p: p[-1])
def test_undistortion_matches_opencv(parts):
    rig = _real_rig(parts)
    for c in range(len(rig)):
        (w, h), K, d = rig.image_size_wh[c].tolist(), rig.K[c].numpy(), rig.dist[c].numpy()
        u, v = np.meshgrid(np.linspace(-0.5, w - 0.5, 41), np.linspace(-0.5, h - 0.5, 31))
        px = np.stack([u.ravel(), v.ravel()], -1)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
        ref = cv2.undistortPoints(px[:, None], K, d, P=K, criteria=crit)[:, 0]  # undistorted pixels
        uv = torch.zeros(len(rig), px.shape[0], 2, dtype=torch.float64)
        uv[c] = torch.from_numpy(px)
        _, dirs = rig.pixel_rays(uv)
        d_cam = dirs[c] @ rig.R_cam_world[c].T  # (N, 3) camera frame
        ours = (d_cam[:, :2] / d_cam[:, 2:]).numpy() * [K[0, 0], K[1, 1]] + K[:2, 2]
        assert np.abs(ours - ref).max() < 1e-3, f"{rig.names[c]}: undistortion differs from OpenCV"


def test_fisheye_rays_match_opencv():
    rig = _fisheye_rig()
    px = np.stack(np.meshgrid(np.linspace(0, 1279, 33), np.linspace(0, 959, 25)), -1).reshape(-1, 2)
    # theta_d < 1.5 rad (86 degrees): the image corners of this 1280x960, f = 400 px camera lie beyond 90 degrees,
    # outside the fisheye model's domain (a real circular fisheye image is black there).
    px = px[np.linalg.norm((px - [639.5, 479.5]) / 400.0, axis=1) < 1.5]
    uv = torch.from_numpy(px)[None].expand(len(rig), -1, -1).contiguous()
    _, dirs = rig.pixel_rays(uv)
    for c in (0, 1):
        K, d = rig.K[c].numpy(), rig.dist[c, :4].numpy()
        ref = cv2.fisheye.undistortPoints(px[:, None], K, d)[:, 0]  # normalized
        d_cam = dirs[c] @ rig.R_cam_world[c].T
        ours = (d_cam[:, :2] / d_cam[:, 2:]).numpy()
        assert np.abs(ours - ref).max() * K[0, 0] < 1e-3


# ------------------------------------------------------------------------------------------ other methods
def test_centers_subset_resized_pinhole():
    rig = _real_rig(REAL_FILES[0])
    C = rig.centers()
    torch.testing.assert_close((rig.R_cam_world @ C[..., None])[..., 0] + rig.t_cam_world,
                               torch.zeros_like(C), rtol=0, atol=1e-12)
    sub = rig.subset(["port_2", 0])
    assert sub.names == ["port_2", "port_0"] and len(sub) == sub.num_cameras == 2
    assert rig.subset("port_3").names == ["port_3"]
    torch.testing.assert_close(sub.K, rig.K[[2, 0]])
    with pytest.raises(InputError, match="nope"):
        rig.subset(["nope"])
    # Resized: u' = (u + 0.5) * s - 0.5 for every projected point.
    pts = _points_in_view(rig, 50, torch.Generator().manual_seed(6))
    small = rig.resized(320, 240)
    assert small.image_size_wh.tolist() == [[320, 240]] * 4
    uv, valid = rig.project(pts)
    uv_s, _ = small.project(pts)
    s = torch.tensor([320 / 1280, 240 / 720], dtype=torch.float64)
    torch.testing.assert_close(uv_s, (uv + 0.5) * s - 0.5, rtol=1e-12, atol=1e-9)
    # kornia's PinholeCamera has the same undistorted projection.
    nodist = CameraRig(rig.names, rig.K, rig.R_cam_world, rig.t_cam_world, rig.image_size_wh)
    cam = nodist.pinhole()
    assert cam.intrinsics.shape == (4, 4, 4) and cam.height.tolist() == [720.0] * 4
    uv_k = cam.project(pts[None].expand(4, -1, -1))
    torch.testing.assert_close(uv_k, nodist.project(pts)[0], rtol=0, atol=1e-6)


def test_package_import_does_not_load_opencv():
    code = "import sys, torchtrack.cameras, torchtrack.cameras.cli; sys.exit('cv2' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def _args(**over):
    K = torch.tensor([[[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]] * 2, dtype=torch.float64)
    args = dict(names=["a", "b"], K=K, R_cam_world=torch.eye(3, dtype=torch.float64).repeat(2, 1, 1),
                t_cam_world=torch.zeros(2, 3, dtype=torch.float64), image_size_wh=torch.tensor([[640, 480]] * 2))
    args.update(over)
    return args


@pytest.mark.parametrize("over, error, match", [
    (dict(K=torch.eye(3, dtype=torch.float64)[None]), ShapeError, "K: expected shape"),
    (dict(t_cam_world=torch.zeros(2, 4, dtype=torch.float64)), ShapeError, "t_cam_world"),
    (dict(dist=torch.zeros(2, 6, dtype=torch.float64)), ShapeError, "dist"),
    (dict(names=["a", "a"]), InputError, "unique"),
    (dict(R_cam_world=torch.diag(torch.tensor([1.0, 1.0, 1.1], dtype=torch.float64)).repeat(2, 1, 1)),
     InputError, "camera 'a': R_cam_world is not a rotation"),
    (dict(R_cam_world=torch.stack([torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, -1.0]))]).double()),
     InputError, "camera 'b'.*det <= 0"),
    (dict(t_cam_world=torch.tensor([[0.0, 0, 0], [0, float("nan"), 0]], dtype=torch.float64)),
     InputError, "t_cam_world: 1 of 6 values"),
    (dict(K=torch.tensor([[[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], [[-5.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]],
                         dtype=torch.float64)), InputError, "camera 'b': focal lengths"),
    (dict(K=torch.tensor([[[500.0, 2, 320], [0, 500.0, 240], [0, 0, 1]]] * 2, dtype=torch.float64)),
     InputError, "skew"),
    (dict(image_size_wh=torch.tensor([[640, 480], [0, 480]])), InputError, "camera 'b': image size"),
])
def test_constructor_rejects_bad_input(over, error, match):
    with pytest.raises(error, match=match):
        CameraRig(**_args(**over))


def test_constructor_defaults_and_buffers():
    rig = CameraRig(**_args(dist=torch.tensor([[0.1, 0.01, 0.0, 0.0]] * 2, dtype=torch.float64)))
    assert rig.dist.shape == (2, 5) and rig.dist[:, 4].eq(0).all()
    assert rig.fisheye == [False, False] and rig.names == ["a", "b"]
    assert set(dict(rig.named_buffers())) == {"K", "R_cam_world", "t_cam_world", "dist", "image_size_wh",
                                              "fisheye_mask"}
    with pytest.raises(ShapeError):
        rig.project(torch.zeros(5, 2))
    with pytest.raises(ShapeError):
        rig.pixel_rays(torch.zeros(3, 5, 2))
