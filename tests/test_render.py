"""Tests of the scene renderer (torchtrack.synth.scene) and its shading (torchtrack.synth.render); the ray casting
is tested in test_ellipsoids.py.

References are independent of the code under test: the projected conic of each ellipsoid (dual quadric) and, with
lens distortion, OpenCV's projectPoints of dense surface samples.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchtrack.cameras.rig import CameraRig
from torchtrack.checks import InputError, ShapeError
from torchtrack.ellipsoids import ray_ellipsoid_intersect
from torchtrack.synth.render import shade
from torchtrack.synth.scene import SceneConfig, SceneRenderer, illumination_gain

from conftest import quadric_matrix, small_body

# ----------------------------------------------------------------------------------------------- helpers


def look_at(center, target) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV R_cam_world, t_cam_world of a camera at ``center`` looking at ``target`` (world Z up)."""
    c, tgt = torch.tensor(center, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    z = (tgt - c) / (tgt - c).norm()
    x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    return R, -R @ c


def ring_rig(C=4, W=80, H=60, f=70.0, radius=3.0, height=1.8, dist=None, sizes=None, device="cpu") -> CameraRig:
    """C cameras on a circle looking at (0, 0, 1)."""
    Rs, ts = zip(*(look_at([radius * math.cos(2 * math.pi * i / C), radius * math.sin(2 * math.pi * i / C),
                            height], [0.0, 0.0, 1.0]) for i in range(C)))
    sizes = sizes or [(W, H)] * C
    K = torch.stack([torch.tensor([[f * w / W, 0, (w - 1) / 2], [0, f * w / W, (h - 1) / 2], [0, 0, 1]])
                     for w, h in sizes])
    return CameraRig([f"c{i}" for i in range(C)], K.double(), torch.stack(Rs), torch.stack(ts),
                     torch.tensor(sizes), dist).to(device)


def conic_inside_mask(rig: CameraRig, cam: int, c, R, a) -> np.ndarray:
    """(H, W) pixels whose centre lies inside the image conic of the ellipsoid (undistorted camera).

    The image of the quadric Q = [[A, -A c], [-c^T A, c^T A c - 1]] under P = K [R | t] is the conic
    C = (P Q^-1 P^T)^-1 (the dual quadric projects to the dual conic).
    """
    K, Rc, t = (x.detach().cpu().double().numpy() for x in (rig.K[cam], rig.R_cam_world[cam], rig.t_cam_world[cam]))
    W, H = (int(v) for v in rig.image_size_wh[cam])
    A = quadric_matrix(c, R, a)
    Q = np.block([[A, -(A @ c)[:, None]], [-(A @ c)[None, :], np.array([[c @ A @ c - 1.0]])]])
    P = K @ np.hstack([Rc, t[:, None]])
    conic = np.linalg.inv(P @ np.linalg.inv(Q) @ P.T)
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    x = np.stack([u, v, np.ones_like(u)], -1)
    val = np.einsum("hwi,ij,hwj->hw", x, conic, x)
    centre = P @ np.append(c, 1.0)
    centre_val = centre @ conic @ centre
    return np.sign(val) == np.sign(centre_val)


def inside_convex_hull(hull: np.ndarray, W: int, H: int) -> np.ndarray:
    """(H, W) pixel centres inside a convex polygon (V, 2) given in either orientation."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    p = np.stack([u, v], -1).reshape(-1, 1, 2)  # (P, 1, 2)
    a, b = hull.astype(np.float64), np.roll(hull.astype(np.float64), -1, axis=0)  # (V, 2) edges a -> b
    cross = (b - a)[None, :, 0] * (p - a[None])[..., 1] - (b - a)[None, :, 1] * (p - a[None])[..., 0]  # (P, V)
    return ((cross >= 0).all(1) | (cross <= 0).all(1)).reshape(H, W)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum()) / max(1, int((a | b).sum()))


def boundary_band(mask: np.ndarray, width: int = 1) -> np.ndarray:
    """Pixels within ``width`` of a change in ``mask``."""
    m = mask.astype(np.int8)
    band = np.zeros_like(mask)
    for dy in range(-width, width + 1):
        for dx in range(-width, width + 1):
            band |= np.roll(np.roll(m, dy, 0), dx, 1) != m
    return band


# ----------------------------------------------------------------------------------------------- ray casting


def test_shade():
    normal = torch.tensor([[0.0, 0, 1], [0, 0, -1], [1, 0, 0], [0, 0, 1]])
    part = torch.tensor([0, 1, 0, -1])
    colours = torch.tensor([[0.5, 0.4, 0.2], [0.8, 0.8, 0.8]])
    light = torch.tensor([0.0, 0.0, 2.0])  # not unit: normalized inside
    rgb = shade(normal, part, colours, light, ambient=0.25)
    torch.testing.assert_close(rgb[0], colours[0])  # facing the light
    torch.testing.assert_close(rgb[1], 0.25 * colours[1])  # facing away: ambient only
    torch.testing.assert_close(rgb[2], 0.25 * colours[0])  # grazing
    assert (rgb[3] == 0).all()
    var = shade(normal, part, colours, light, 0.25, torch.tensor([1.0, -1.0, 0.0, 0.0]), 0.1)
    torch.testing.assert_close(var[0], (colours[0] * 1.1).clamp(0, 1))
    torch.testing.assert_close(var[1], 0.25 * colours[1] * 0.9)
    with pytest.raises(ShapeError):
        shade(normal, part, colours[:, :2], light)


# ----------------------------------------------------------------------------------------------- scene

QUIET = SceneConfig(noise_std=0.0)


def render_body(sr: SceneRenderer, body=None, **kw):
    c, R, a, col = body or small_body(torch.float32)
    return sr.render(c, R, a, col, **kw)


def test_silhouettes_match_projected_conics(device):
    rig = ring_rig(C=3, W=160, H=120, f=140.0, device=device)
    sr = SceneRenderer(rig, QUIET)
    c, R, a, col = small_body()
    images, sil, part_ids = sr.render(c, R, a, col)
    assert images.shape == (3, 3, 120, 160) and sil.shape == (3, 120, 160) and part_ids.shape == sil.shape
    assert sil.dtype == torch.bool and part_ids.dtype == torch.int64
    assert images.min() >= 0 and images.max() <= 1
    assert torch.equal(sil, part_ids >= 0)
    for cam in range(3):
        per_part = [conic_inside_mask(rig, cam, *(x[k].numpy() for x in (c, R, a))) for k in range(len(c))]
        ref = np.any(per_part, axis=0)
        got = sil[cam].cpu().numpy()
        assert iou(got, ref) > 0.99
        assert not (got ^ ref)[~boundary_band(ref)].any()  # differences only at boundary pixels
        # Every visible part covers pixels inside its own conic.
        ids = part_ids[cam].cpu().numpy()
        for k, inside in enumerate(per_part):
            assert (~inside[ids == k]).sum() <= max(2, 0.01 * (ids == k).sum())


def test_silhouettes_with_lens_distortion():
    cv2 = pytest.importorskip("cv2")
    dist = torch.tensor([[-0.25, 0.08, 0.002, -0.001, -0.01]], dtype=torch.float64).expand(2, 5)
    rig = ring_rig(C=2, W=160, H=120, f=130.0, dist=dist)
    sr = SceneRenderer(rig, QUIET)
    c, R, a, col = small_body()
    c = c + torch.tensor([0.0, 0.8, 0.0], dtype=c.dtype)  # off the image centre, where distortion is large
    _, sil, _ = sr.render(c, R, a, col)
    # Dense surface samples (Fibonacci sphere mapped onto each ellipsoid), projected by OpenCV.
    n = 3000
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    sphere = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], -1)
    _, sil_pinhole, _ = SceneRenderer(ring_rig(C=2, W=160, H=120, f=130.0), QUIET).render(c, R, a, col)
    assert (sil_pinhole ^ sil).sum() > 200  # the distortion matters
    for cam in range(2):
        rvec, _ = cv2.Rodrigues(rig.R_cam_world[cam].numpy())
        ref = np.zeros((120, 160), bool)
        for k in range(len(c)):
            pts = c[k].numpy() + (sphere * a[k].numpy()) @ R[k].numpy().T
            uv, _ = cv2.projectPoints(pts, rvec, rig.t_cam_world[cam].numpy(), rig.K[cam].numpy(),
                                      rig.dist[cam].numpy())
            ref |= inside_convex_hull(cv2.convexHull(uv[:, 0].astype(np.float32))[:, 0], 160, 120)
        got = sil[cam].numpy()
        assert iou(got, ref) > 0.97
        assert not (got ^ ref)[~boundary_band(ref)].any()


def test_nearer_part_wins(device):
    """Two spheres on the line of sight of camera 0: whichever is nearer shows, whatever its index."""
    rig = ring_rig(C=2, device=device)
    sr = SceneRenderer(rig, QUIET)
    cam = rig.centers()[0].cpu().double()
    towards = (torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) - cam)
    towards = towards / towards.norm()
    near, far = cam + 1.5 * towards, cam + 3.0 * towards
    R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    semi = torch.tensor([[0.15] * 3, [0.5] * 3], dtype=torch.float64)
    col = torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64)
    for order in ([0, 1], [1, 0]):
        centers = torch.stack([near, far])[order]
        _, sil, ids = sr.render(centers, R, semi[order], col[order])
        centre_px = ids[0, 29:31, 39:41]  # the image centre sees the target point (0, 0, 1)
        assert (centre_px == order.index(0)).all()
        assert (ids[0] == order.index(1)).any()  # the far, larger sphere shows around the near one
        uv, valid = rig.project(torch.stack([near, far]).float().to(device))
        assert valid[0].all()


@pytest.mark.parametrize("distorted", [False, True])
def test_tiled_cast_equals_dense_cast(distorted):
    """The renderer's tile-culled body cast gives the same part per pixel as the plain dense intersection."""
    dist = torch.tensor([[-0.3, 0.1, 0.003, 0.002, -0.02]], dtype=torch.float64).expand(4, 5) if distorted else None
    rig = ring_rig(C=4, W=90, H=70, dist=dist)
    sr = SceneRenderer(rig, dataclasses.replace(QUIET, tile_px=16))  # 90 x 70 leaves partial tiles
    c, R, a, col = small_body()
    _, sil, ids = sr.render(c, R, a, col)
    v, u = torch.meshgrid(torch.arange(70), torch.arange(90), indexing="ij")
    uv = torch.stack([u, v], -1).reshape(1, -1, 2).expand(4, -1, -1).double()
    o, d = rig.pixel_rays(uv)  # (C, N, 3)
    _, ref, _ = ray_ellipsoid_intersect(o, d, c, R, a)
    assert torch.equal(ids, ref.reshape(4, 70, 90))  # the room is behind the body everywhere
    assert sil.sum() > 200


def test_distractor_occludes_body():
    """Silhouettes are the body pixels in front of the static scene: a box between camera 0 and the legs hides them."""
    rig = ring_rig(C=2)
    box = dataclasses.replace(QUIET, distractor=True, distractor_xy_m=(1.4, 0.0), distractor_size_m=(0.3, 0.8, 1.3))
    _, sil_box, _ = render_body(SceneRenderer(rig, box))
    _, sil, _ = render_body(SceneRenderer(rig, QUIET))
    assert (sil_box <= sil).all()
    assert (sil[0] & ~sil_box[0]).sum() > 30  # legs hidden in camera 0
    assert torch.equal(sil_box[1], sil[1])  # camera 1 sees the body in front of the box


def test_empty_body():
    sr = SceneRenderer(ring_rig(C=2), QUIET)
    empty = torch.zeros(0, 3)
    images, sil, ids = sr.render(empty, torch.zeros(0, 3, 3), empty, empty)
    assert not sil.any() and (ids == -1).all()
    torch.testing.assert_close(images, sr.background())


def floor_pixels(rig: CameraRig, cfg: SceneConfig) -> torch.Tensor:
    """(C, H, W) pixels whose ray ends on the floor (independent of the renderer: z = 0 before the wall)."""
    W, H = (int(v) for v in rig.image_size_wh[0])
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    uv = torch.stack([u, v], -1).reshape(1, -1, 2).expand(rig.num_cameras, -1, -1).to(rig.K)
    o, d = rig.pixel_rays(uv)
    t = -o[..., 2] / d[..., 2]
    p = o + t[..., None] * d
    return ((d[..., 2] < 0) & (p[..., :2].norm(dim=-1) < cfg.wall_radius_m)).reshape(-1, H, W)


def test_shadow_darkens_only_floor(device):
    rig = ring_rig(C=4, device=device)
    cfg = dataclasses.replace(QUIET, shadow=True, shadow_strength=0.6)
    plain, _, ids_plain = render_body(SceneRenderer(rig, QUIET))
    shadowed, sil, ids = render_body(SceneRenderer(rig, cfg))
    assert torch.equal(ids, ids_plain)  # the shadow is not part of the silhouettes
    assert torch.equal(sil, ids_plain >= 0)
    changed = (shadowed != plain).any(1)  # (C, H, W)
    assert changed.sum() > 20
    assert (shadowed <= plain + 1e-6).all()  # only darker
    assert not (changed & sil).any()
    assert (changed <= floor_pixels(rig, cfg).to(device)).all()  # only floor pixels


def box_corners(cfg: SceneConfig) -> torch.Tensor:
    sx, sy, sz = cfg.distractor_size_m
    cy, syaw = math.cos(cfg.distractor_yaw), math.sin(cfg.distractor_yaw)
    local = torch.tensor([[x * sx / 2, y * sy / 2, z] for x in (-1, 1) for y in (-1, 1) for z in (0, sz)])
    rot = torch.tensor([[cy, -syaw, 0], [syaw, cy, 0], [0, 0, 1.0]])
    return local @ rot.T + torch.tensor([*cfg.distractor_xy_m, 0.0])


def test_distractor(device):
    # Camera 0 at (3, 0) looks at the box's far side near its feet; the box at (2.6, 0) sits below its view.
    rig = ring_rig(C=4, device=device)
    cfg = dataclasses.replace(QUIET, distractor=True, distractor_xy_m=(2.6, 0.0), distractor_size_m=(0.3, 0.3, 0.4))
    sr = SceneRenderer(rig, cfg)
    plain_sr = SceneRenderer(rig, QUIET)
    assert torch.equal(sr.background(), plain_sr.background())  # never in background frames
    images, sil, ids = render_body(sr)
    plain, _, ids_plain = render_body(plain_sr)
    assert torch.equal(ids, ids_plain)  # not part of the silhouettes
    shows = (images != plain).any(1).flatten(1).any(1).cpu()  # (C,)
    # Reference: which views see a box corner inside the image (the box is small, so that decides it).
    _, valid = rig.project(box_corners(cfg).to(device))  # (C, 8)
    expected = valid.any(1).cpu()
    assert expected.any() and not expected.all()
    assert torch.equal(shows, expected)
    assert torch.equal(sr.distractor_visible.cpu(), expected)
    # Restricted to a subset of views.
    subset = dataclasses.replace(cfg, distractor_cameras=(int(expected.nonzero()[-1]),))
    images_sub, _, _ = render_body(SceneRenderer(rig, subset))
    shows_sub = (images_sub != plain).any(1).flatten(1).any(1).cpu()
    assert shows_sub.tolist() == [i in subset.distractor_cameras for i in range(4)]


def test_illumination_gain(device):
    rig = ring_rig(C=2, device=device)
    cfg = dataclasses.replace(QUIET, illumination_change=0.2)
    sr = SceneRenderer(rig, cfg)
    base, _, _ = render_body(sr, frame=0, num_frames=8)
    lit, _, _ = render_body(sr, frame=2, num_frames=8)  # gain 1.2
    assert illumination_gain(2, 8, 0.2) == pytest.approx(1.2)
    ok = base < 1 / 1.2 - 1e-3
    torch.testing.assert_close(lit[ok], base[ok] * 1.2)
    assert torch.equal(lit[~ok], (base[~ok] * 1.2).clamp(max=1))


def test_noise_statistics_and_generator(device):
    rig = ring_rig(C=4, device=device)
    sr = SceneRenderer(rig, SceneConfig(noise_std=0.02))
    clean = SceneRenderer(rig, QUIET).background()
    a = sr.background(torch.Generator(device=device).manual_seed(5))
    b = sr.background(torch.Generator(device=device).manual_seed(5))
    c = sr.background(torch.Generator(device=device).manual_seed(6))
    assert torch.equal(a, b) and not torch.equal(a, c)
    inner = (clean > 0.1) & (clean < 0.9)
    resid = (a - clean)[inner]
    assert abs(float(resid.mean())) < 2e-3
    assert float(resid.std()) == pytest.approx(0.02, rel=0.05)
    f1 = render_body(sr, generator=torch.Generator(device=device).manual_seed(9))
    f2 = render_body(sr, generator=torch.Generator(device=device).manual_seed(9))
    assert all(torch.equal(x, y) for x, y in zip(f1, f2))


def test_batched_equals_per_camera_and_mixed_sizes():
    """Rendering all cameras at once equals rendering each camera's one-camera rig; mixed sizes give lists."""
    cfg = dataclasses.replace(QUIET, shadow=True, distractor=True, distractor_xy_m=(1.5, 0.5))
    rig = ring_rig(C=3, sizes=[(80, 60), (64, 48), (96, 50)])
    sr = SceneRenderer(rig, cfg)
    assert not sr.same_size
    images, sil, ids = render_body(sr)
    bg = sr.background()
    assert [tuple(x.shape) for x in images] == [(3, 60, 80), (3, 48, 64), (3, 50, 96)]
    assert [tuple(x.shape) for x in sil] == [(60, 80), (48, 64), (50, 96)]
    for cam in range(3):
        one = SceneRenderer(rig.subset([cam]), cfg)
        img1, sil1, ids1 = render_body(one)
        torch.testing.assert_close(images[cam], img1[0], atol=1e-5, rtol=0)
        assert torch.equal(ids[cam], ids1[0]) and torch.equal(sil[cam], sil1[0])
        torch.testing.assert_close(bg[cam], one.background()[0], atol=1e-5, rtol=0)
        assert sil1[0].any()


def test_cpu_and_device_agree(device):
    rig = ring_rig(C=3)
    cfg = dataclasses.replace(QUIET, shadow=True, distractor=True, illumination_change=0.1)
    body = small_body(torch.float32)
    ref = render_body(SceneRenderer(rig, cfg), body, frame=1, num_frames=4)
    got = render_body(SceneRenderer(rig, cfg).to(device), tuple(x.to(device) for x in body), frame=1, num_frames=4)
    torch.testing.assert_close(got[0].cpu(), ref[0], atol=1e-4, rtol=0)
    mismatch = (got[2].cpu() != ref[2]).float().mean()
    assert mismatch < 1e-3  # at most rounding-level boundary pixels


def test_scene_bad_input():
    rig = ring_rig(C=2)
    sr = SceneRenderer(rig, QUIET)
    c, R, a, col = small_body(torch.float32)
    with pytest.raises(ShapeError, match="colours"):
        sr.render(c, R, a, col[:3])
    with pytest.raises(ShapeError, match="R_world_ellipsoid"):
        sr.render(c, R[:, :2], a, col)
    with pytest.raises(InputError, match="semi_axes"):
        sr.render(c, R, -a, col)
    with pytest.raises(InputError, match="inside the room"):
        SceneRenderer(rig, SceneConfig(wall_radius_m=2.0))
    with pytest.raises(InputError, match="distractor_cameras"):
        SceneRenderer(rig, SceneConfig(distractor=True, distractor_cameras=(5,)))
    with pytest.raises(InputError, match="ambient"):
        SceneConfig(ambient=1.5)
    with pytest.raises(InputError, match="num_frames"):
        sr.render(c, R, a, col, frame=0, num_frames=0)
