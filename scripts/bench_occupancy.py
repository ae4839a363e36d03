#!/usr/bin/env python
"""Benchmark of the occupancy models: Bayesian grid, hierarchical hull, binary carving vs Open3D's carving.

Scenes: ring rigs from ``make_ring_rig`` (8 cameras; the 4-camera ring is every other camera of it, which is
what ``make_ring_rig(RigConfig(num_cameras=4))`` builds: checked) at 320x240 and 640x480, rendered by
``SceneRenderer`` with a walking body (4 frames of the procedural walk) and a ``BackgroundModel`` from 4 rendered
empty frames. Grids: 64 or 128 voxels along x and y of the box ``BOX_LOWER_M``-``BOX_UPPER_M`` (2.6 x 2.6 x 2.1
m; z gets the voxels that fit, the actual shape is printed).

Prints, per device (CPU; CUDA when present, synchronized around every timing):

1. Bayesian grid: median ms/frame of the full forward (background likelihood, log-ratio, window, gather,
   fusion) for batches of 1 and 4 frames and voxel-camera updates per second (B V C / time); the one-off
   voxel -> pixel lookup construction separately; then the time of each stage on the target configuration.
2. Hierarchical hull (``hull_from_images``, one frame at a time, frames cycled): median ms/frame, and of that
   the hull itself (``hierarchical_hull`` on precomputed Mahalanobis distances and colours).
3. Open3D: ``VoxelGrid.create_dense`` over the same box and voxel size, then ``carve_silhouette`` per camera
   with the same binary masks (the rendered silhouettes) and a rig without lens distortion (k1 = 0), against
   torchtrack's ``carve`` (same masks, same grid) and the Bayesian grid (images) at 640x480; speed-ups and the
   agreement (IoU) of the voxel sets.

Timings are wall-clock medians (the minimum is printed too); figures that are compared with each other (the
stages, hull vs hull-only, Open3D vs torchtrack) are timed in interleaved rounds so that they see the same load.
The 1-minute load average is printed at the start and the end: above the thread count, other processes
compete for the CPU and the CPU figures are inflated. The targets are printed next to their figures with
PASS / MISS. Needs Open3D for part 3
(``.venv/bin/pip install open3d``; on Debian/Ubuntu its wheel also needs ``apt-get install -y libusb-1.0-0``).

Usage: .venv/bin/python scripts/bench_occupancy.py [--runs 5] [--device cpu cuda] [--skip-open3d] [--threads N]
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from torchtrack.background import BackgroundModel
from torchtrack.blobs import BlobModel
from torchtrack.cameras import CameraRig
from torchtrack.occupancy import BayesConfig, BayesianGrid, GridSpec
from torchtrack.occupancy.bayes import pixel_log_ratio, window_sum
from torchtrack.occupancy.metrics import iou
from torchtrack.occupancy.silhouette import carve
from torchtrack.skeleton import Skeleton
from torchtrack.synth.scene import SceneConfig, SceneRenderer
from torchtrack.synth.sequence import RigConfig, SynthConfig, make_ring_rig, motion_angles

BOX_LOWER_M = (-1.3, -1.3, 0.0)
BOX_UPPER_M = (1.3, 1.3, 2.1)
GRID_RESOLUTIONS = (64, 128)  # voxels along x and y of the box
IMAGE_SIZES_WH = ((320, 240), (640, 480))
CAMERA_COUNTS = (4, 8)
BATCH_SIZES = (1, 4)
FOUR_OF_EIGHT = [0, 2, 4, 6]  # the 4-camera ring inside the 8-camera ring

TARGET_BAYES_MS = 150.0  # 128^3 x 8 cameras x 640x480, per frame
TARGET_HULL_MS = 15.0  # 4 cameras 320x240 down to 1.5 cm, per frame
TARGET_SPEEDUP = 10.0  # vs Open3D carving at equal resolution
PARTS = ("bayes", "hull", "open3d")
HULL_CASES = ((4, (320, 240), 0.015, TARGET_HULL_MS), (8, (640, 480), 0.02, None))

OPEN3D_INSTALL = ("install it with `.venv/bin/pip install open3d`; on Debian/Ubuntu its wheel also needs "
                  "`apt-get install -y libusb-1.0-0`")


# ------------------------------------------------------------------------------------------------ scenes


@dataclass
class Scene:
    """Rendered frames of one rig.

    Attributes:
        rig: float64 CameraRig. images: (B, C, 3, H, W) RGB in [0, 1]. silhouettes: (B, C, H, W) bool, the
        renderer's exact body masks. background: BackgroundModel from rendered empty frames.
    """

    rig: CameraRig
    images: torch.Tensor
    silhouettes: torch.Tensor
    background: BackgroundModel

    @property
    def label(self) -> str:
        W, H = (int(v) for v in self.rig.image_size_wh[0])
        return f"{W}x{H}"

    def to(self, device: torch.device) -> Scene:
        return Scene(self.rig.to(device), self.images.to(device), self.silhouettes.to(device),
                     self.background.to(device))


def walking_bodies(num_frames: int) -> list[tuple[torch.Tensor, ...]]:
    """Ellipsoid bodies (centres (K, 3), R (K, 3, 3), semi-axes (K, 3), colours (K, 3)) of walk frames."""
    skel, angles = motion_angles(SynthConfig(motion="walk", duration_s=1.0, starfish_s=0.0, fps=10),
                                 Skeleton.from_urdf())
    blobs = BlobModel.from_config(skel)
    centres, R = blobs.ellipsoids(skel(angles.double()).bone_frames)  # (T, K, 3), (T, K, 3, 3)
    pick = torch.linspace(0, angles.shape[0] - 1, num_frames).round().long().tolist()
    return [(centres[t].float(), R[t].float(), blobs.semi_axes.float(), blobs.colour.float()) for t in pick]


def render_scene(rig_cfg: RigConfig, bodies: list[tuple[torch.Tensor, ...]], background_frames: int = 4) -> Scene:
    """Render ``bodies`` (one frame each) and empty frames with a ring rig; fit the background model."""
    renderer = SceneRenderer(make_ring_rig(rig_cfg, dtype=torch.float32), SceneConfig())
    gen = torch.Generator().manual_seed(0)
    empty = torch.stack([renderer.background(generator=gen) for _ in range(background_frames)])
    rendered = [renderer.render(*body, generator=gen) for body in bodies]
    images = torch.stack([r[0] for r in rendered])  # (B, C, 3, H, W)
    silhouettes = torch.stack([r[1] for r in rendered])  # (B, C, H, W)
    rig = make_ring_rig(rig_cfg)
    return Scene(rig, images, silhouettes, BackgroundModel.from_frames(empty, camera_names=rig.names))


def camera_subset(scene: Scene, cameras: list[int], rig_cfg: RigConfig) -> Scene:
    """The scene seen by some of its cameras; checks that they form ``make_ring_rig(rig_cfg)``."""
    rig = scene.rig.subset(cameras)
    ring = make_ring_rig(rig_cfg)
    if not (torch.allclose(rig.R_cam_world, ring.R_cam_world, atol=1e-9)
            and torch.allclose(rig.t_cam_world, ring.t_cam_world, atol=1e-9)):
        raise RuntimeError(f"cameras {cameras} of the 8-camera ring are not make_ring_rig({rig_cfg})")
    bg = scene.background
    background = BackgroundModel(bg.mean_yuv[cameras], bg.std_yuv[cameras], bg.config, rig.names)
    return Scene(rig, scene.images[:, cameras], scene.silhouettes[:, cameras], background)


def box_spec(voxels_xy: int) -> GridSpec:
    """The benchmark box with ``voxels_xy`` voxels along x and y."""
    return GridSpec(BOX_LOWER_M, BOX_UPPER_M, (BOX_UPPER_M[0] - BOX_LOWER_M[0]) / voxels_xy)


def shape_label(spec: GridSpec) -> str:
    return "x".join(map(str, spec.shape))


# ------------------------------------------------------------------------------------------------ timing


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_times(fn: Callable[[int], object], runs: int, device: torch.device, warmup: int = 1) -> list[float]:
    """Wall times (s) of ``fn(run_index)`` for ``runs`` runs after ``warmup`` runs."""
    for i in range(warmup):
        fn(i)
    times = []
    for i in range(runs):
        sync(device)
        start = time.perf_counter()
        fn(i)
        sync(device)
        times.append(time.perf_counter() - start)
    return times


def timed_once(fn: Callable[[], object], device: torch.device) -> tuple[object, float]:
    sync(device)
    start = time.perf_counter()
    out = fn()
    sync(device)
    return out, time.perf_counter() - start


def load_average(warn: bool = True) -> str:
    """The 1-minute load average; with ``warn``, a warning when other processes use the CPU (call it before
    this process starts working)."""
    try:
        load = os.getloadavg()[0]
    except OSError:
        return "load average unknown"
    busy = warn and load > 1.0
    return f"1-min load average {load:.1f}" + (" (other processes use the CPU: CPU timings inflated, with several "
                                                 "threads erratically; see --threads)" if busy else "")


def verdict(value: float, limit: float, below: bool = True) -> str:
    ok = value < limit if below else value >= limit
    return "PASS" if ok else "MISS"


# ------------------------------------------------------------------------------------------------ 1. Bayes


def bench_bayes(scenes: dict[tuple[str, int], Scene], runs: int, device: torch.device) -> None:
    k = BayesConfig().window
    print(f"\n[{device}] Bayesian occupancy grid (full forward: likelihood + log-ratio + {k}x{k} window + gather + "
          f"fusion; median of {runs} runs)")
    print(f"{'images':>8} {'cams':>4} {'grid':>6} {'shape':>12} {'voxels':>10} {'lookup':>8} {'B':>2} "
          f"{'ms/frame':>9} {'(min)':>7} {'Mvox-cam/s':>11}  target")
    for label in (f"{w}x{h}" for w, h in IMAGE_SIZES_WH):
        for C in CAMERA_COUNTS:
            scene = scenes[(label, C)]
            for n in GRID_RESOLUTIONS:
                spec = box_spec(n)
                grid, build_s = timed_once(lambda: BayesianGrid(scene.rig, spec, scene.background), device)
                for B in BATCH_SIZES:
                    x = scene.images[:B]
                    times = run_times(lambda _: grid(x), runs, device)
                    t = float(np.median(times))
                    target = ""
                    if (label, C, n) == ("640x480", 8, 128):
                        target = f"< {TARGET_BAYES_MS:.0f} ms/frame: {verdict(1e3 * t / B, TARGET_BAYES_MS)}"
                    print(f"{label:>8} {C:>4} {n:>4}^3 {shape_label(spec):>12} {spec.num_voxels:>10,} "
                          f"{build_s:>7.2f}s {B:>2} {1e3 * t / B:>9.1f} {1e3 * min(times) / B:>7.1f} "
                          f"{B * spec.num_voxels * C / t / 1e6:>11.1f}"
                          f"  {target}")
                del grid


def bayes_stages(scene: Scene, n: int, runs: int, device: torch.device) -> None:
    """Time each stage of ``BayesianGrid.forward`` on one frame (the pieces the forward is made of)."""
    spec = box_spec(n)
    grid = BayesianGrid(scene.rig, spec, scene.background)
    bg, cfg = grid.background, grid.config
    x = scene.images[:1]
    ll = bg.log_likelihood(x)
    ratio = pixel_log_ratio(ll, bg.log_uniform, cfg)
    ev = window_sum(torch.nan_to_num(ratio, nan=0.0), cfg.window)
    per_cam = grid.lookup.gather(ev)
    prior = math.log(cfg.prior / (1 - cfg.prior))
    window = f"nan_to_num + {cfg.window}x{cfg.window} window sum"
    pieces = {
        "background log-likelihood (total)": lambda: bg.log_likelihood(x),
        "  of which RGB->YUV": lambda: bg.to_yuv(x),
        "  of which global gain (median over pixels)": lambda: bg.gain(x),  # includes its own RGB->YUV
        "pixel log-ratio (2 logaddexp)": lambda: pixel_log_ratio(ll, bg.log_uniform, cfg),
        window: lambda: window_sum(torch.nan_to_num(ratio, nan=0.0), cfg.window),
        "lookup gather -> (B, C, V)": lambda: grid.lookup.gather(ev),
        "sum over cameras + prior": lambda: per_cam.sum(dim=1) + prior,
        "full forward": lambda: grid(x),
    }
    medians = {k: float(np.median(v)) for k, v in interleaved_times(pieces, runs, device).items()}
    medians["  of which global gain (median over pixels)"] -= medians["  of which RGB->YUV"]
    full = medians.pop("full forward")
    stages = list(medians.items())
    top = sum(t for name, t in stages if not name.startswith("  "))
    C = scene.rig.num_cameras
    print(f"\n[{device}] Bayesian grid stages, {scene.label} x {C} cameras x {n}^3 ({shape_label(spec)}), B=1 "
          f"(median of {runs}):")
    for name, t in stages:
        print(f"  {name:<46} {1e3 * t:8.1f} ms  {100 * t / top:5.1f} %")
    print(f"  {'sum of the stages':<46} {1e3 * top:8.1f} ms   (full forward {1e3 * full:.1f} ms)")
    per_pixel = stages[0][1] + stages[3][1] + stages[4][1]
    print(f"  per-pixel work (C*H*W = {scene.images[0].numel() // 3:,} pixels): {1e3 * per_pixel:.1f} ms; "
          f"per-voxel work (V*C = {spec.num_voxels * C:,}): {1e3 * (stages[5][1] + stages[6][1]):.1f} ms")


# ------------------------------------------------------------------------------------------------ 2. hull


def bench_hull(scenes: dict[tuple[str, int], Scene], runs: int, device: torch.device) -> None:
    try:
        from torchtrack.occupancy.hull import HierarchicalHull, HullConfig
    except ImportError as exc:
        print(f"\n[{device}] hierarchical hull: skipped, torchtrack.occupancy.hull is not importable ({exc})")
        return
    print(f"\n[{device}] hierarchical hull (hull_from_images on one frame, frames cycled; median of {runs} runs)")
    print("  early-out 'footprint': HullConfig's default (voxels whose samples miss a thin part are subdivided);"
          " 'points': the paper's 8 point samples only (footprint_early_out=False)")
    print(f"{'images':>8} {'cams':>4} {'finest':>7} {'early-out':>9} {'levels':>6} {'first call':>10} {'ms/frame':>9} "
          f"{'(min)':>7} {'hull only':>9} {'voxels':>7}  target")
    for (C, (w, h), finest_m, target_ms), footprint in itertools.product(HULL_CASES, (True, False)):
        scene = scenes[(f"{w}x{h}", C)]
        cfg = HullConfig(lower_m=BOX_LOWER_M, upper_m=BOX_UPPER_M, finest_voxel_m=finest_m,
                         footprint_early_out=footprint)
        B = scene.images.shape[0]
        first, first_s = timed_once(lambda: HierarchicalHull(scene.rig, cfg).from_images(scene.background,
                                                                                          scene.images[0]), device)
        hull_of = HierarchicalHull(scene.rig, cfg)  # the plan (first call: built with it)
        mahal2 = scene.background.mahalanobis2(scene.images)  # (B, C, H, W)
        yuv = scene.background.normalise(scene.images)  # (B, C, 3, H, W)
        frames, hull_frames = itertools.cycle(range(B)), itertools.cycle(range(B))

        def full() -> object:
            return hull_of.from_images(scene.background, scene.images[next(frames)])

        def hull_only() -> object:
            i = next(hull_frames)
            return hull_of(mahal2[i], yuv[i])

        times = interleaved_times({"full": full, "hull": hull_only}, runs, device)
        t, t_hull = float(np.median(times["full"])), float(np.median(times["hull"]))
        levels = int(first.level.max()) + 1 if first.num_voxels else 0
        mark = f"< {target_ms:.0f} ms/frame: {verdict(1e3 * t, target_ms)}" if target_ms else ""
        print(f"{scene.label:>8} {C:>4} {100 * finest_m:>5.1f}cm {'footprint' if footprint else 'points':>9} "
              f"{levels:>6} {first_s:>9.2f}s {1e3 * t:>9.1f} "
              f"{1e3 * min(times['full']):>7.1f} {1e3 * t_hull:>9.1f} {first.num_voxels:>7}  {mark}")


# ------------------------------------------------------------------------------------------------ 3. Open3D


def import_open3d():
    """open3d, or None after printing how to install it."""
    try:
        import open3d
    except (ImportError, OSError) as exc:  # a missing shared library (libusb) is an ImportError or OSError
        print(f"\nOpen3D comparison skipped: cannot import open3d ({exc}); {OPEN3D_INSTALL}")
        return None
    return open3d


def open3d_camera(o3d, rig: CameraRig, c: int):
    """PinholeCameraParameters of camera ``c`` (no distortion): intrinsic K, extrinsic world -> camera 4x4."""
    W, H = (int(v) for v in rig.image_size_wh[c])
    params = o3d.camera.PinholeCameraParameters()
    params.intrinsic = o3d.camera.PinholeCameraIntrinsic(W, H, rig.K[c].double().cpu().numpy())
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = rig.R_cam_world[c].double().cpu().numpy()
    extrinsic[:3, 3] = rig.t_cam_world[c].double().cpu().numpy()
    params.extrinsic = extrinsic
    return params


def open3d_carve(o3d, dense, masks: np.ndarray, cameras: list) -> object:
    """One frame of Open3D carving: a copy of the dense grid carved by every camera's mask (C, H, W) float32.

    ``keep_voxels_outside_image=False`` (the default): a voxel none of whose corners falls inside a camera's
    image is carved by it, i.e. every camera must see it, as ``carve(..., min_views=C)``.
    """
    grid = o3d.geometry.VoxelGrid(dense)  # carving is destructive: start every frame from the dense grid
    for mask, params in zip(masks, cameras):
        grid.carve_silhouette(o3d.geometry.Image(mask), params, keep_voxels_outside_image=False)
    return grid


def open3d_occupancy(grid, spec: GridSpec) -> torch.Tensor:
    """(V,) bool over ``spec`` of the voxels left in an Open3D VoxelGrid (index (i * ny + j) * nz + k)."""
    out = torch.zeros(spec.num_voxels, dtype=torch.bool)
    ijk = np.asarray([v.grid_index for v in grid.get_voxels()], dtype=np.int64).reshape(-1, 3)
    if len(ijk):
        _, ny, nz = spec.shape
        out[torch.from_numpy((ijk[:, 0] * ny + ijk[:, 1]) * nz + ijk[:, 2])] = True
    return out


def open3d_rule_carve(rig: CameraRig, spec: GridSpec, masks: torch.Tensor) -> torch.Tensor:
    """Plain-torch reference of Open3D's ``carve_silhouette`` rule, on the voxel corners.

    Open3D keeps a voxel in a view when one of its 8 corners projects (pinhole, no distortion) to
    ``0 <= u <= W - 1, 0 <= v <= H - 1`` with a bilinearly interpolated mask value > 0, i.e. when a corner
    touches a foreground pixel or its 1-pixel neighbourhood. Corners are shared: each lattice point is
    projected once and a 2x2x2 max-pool gives "some corner of the voxel".

    Args:
        masks: (C, H, W) bool. The rig must have no lens distortion.

    Returns:
        (V,) bool.
    """
    nx, ny, nz = spec.shape
    axes = [lo + torch.arange(n + 1, dtype=torch.float64) * spec.voxel_size_m
            for lo, n in zip(spec.lower_m, (nx, ny, nz))]
    corners = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # (P, 3) lattice points
    keep = torch.ones(nx, ny, nz, dtype=torch.bool)
    for c in range(rig.num_cameras):
        K, R, t = (x.double().cpu() for x in (rig.K[c], rig.R_cam_world[c], rig.t_cam_world[c]))
        W, H = (int(v) for v in rig.image_size_wh[c])
        uvz = (corners @ R.T + t) @ K.T  # (P, 3)
        u, v = uvz[:, 0] / uvz[:, 2], uvz[:, 1] / uvz[:, 2]
        inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        ui = u.floor().clamp(0, W - 2).long().where(inside, 0)
        vi = v.floor().clamp(0, H - 2).long().where(inside, 0)
        pu, pv = u - ui, v - vi
        m = masks[c].double().cpu()
        val = ((m[vi, ui] * (1 - pv) + m[vi + 1, ui] * pv) * (1 - pu)
               + (m[vi, ui + 1] * (1 - pv) + m[vi + 1, ui + 1] * pv) * pu)  # (P,) bilinear
        lit = (inside & (val > 0)).reshape(1, 1, nx + 1, ny + 1, nz + 1).float()
        keep &= F.max_pool3d(lit, kernel_size=2, stride=1)[0, 0] > 0  # (nx, ny, nz): some corner lit
    return keep.reshape(-1)


def interleaved_times(contenders: dict[str, Callable[[], object]], runs: int, device: torch.device
                      ) -> dict[str, list[float]]:
    """Wall times (s) of each contender, run in turn within every round (after one warm-up round), so that
    all of them see the same competing load."""
    times: dict[str, list[float]] = {k: [] for k in contenders}
    for r in range(runs + 1):
        for name, fn in contenders.items():
            _, t = timed_once(fn, device)
            if r:
                times[name].append(t)
    return times


def bench_open3d(o3d, scenes: dict[int, Scene], runs: int, device: torch.device) -> None:
    print(f"\nOpen3D {o3d.__version__} carve_silhouette vs torchtrack, {scenes[8].label}, k1 = 0 rig, the same "
          f"rendered silhouettes and grid (origin {BOX_LOWER_M}); Open3D on the CPU, torchtrack on {device}; "
          f"median of {runs} interleaved rounds; per frame, lookup/dense grid built once")
    print(f"{'grid':>6} {'shape':>12} {'cams':>4} {'o3d dense':>9} {'o3d/frame':>10} {'(copy)':>9} {'carve':>8} "
          f"{'speed-up':>8} {'bayes':>8} {'speed-up':>8}  target (carve >= {TARGET_SPEEDUP:.0f}x)")
    agreement = []
    for n in GRID_RESOLUTIONS:
        spec = box_spec(n)
        nx, ny, nz = spec.shape
        v = spec.voxel_size_m
        dense, dense_s = timed_once(lambda: o3d.geometry.VoxelGrid.create_dense(
            np.asarray(BOX_LOWER_M, dtype=np.float64), np.zeros(3), v, nx * v, ny * v, nz * v), torch.device("cpu"))
        if len(dense.get_voxels()) != spec.num_voxels:
            raise RuntimeError(f"Open3D dense grid has {len(dense.get_voxels())} voxels, expected {spec.num_voxels}")
        for C in CAMERA_COUNTS:
            scene = scenes[C]
            masks_cpu = scene.silhouettes[0].cpu()  # (C, H, W) bool
            masks_np = masks_cpu.numpy().astype(np.float32)  # Open3D reads float32 single-channel masks
            cameras = [open3d_camera(o3d, scene.rig, c) for c in range(C)]
            sdev = scene.to(device)
            grid = BayesianGrid(sdev.rig, spec, sdev.background)  # its lookup serves the carving too
            masks = sdev.silhouettes[:1]
            contenders = {"o3d": lambda: open3d_carve(o3d, dense, masks_np, cameras),
                          "copy": lambda: o3d.geometry.VoxelGrid(dense),
                          "carve": lambda: carve(masks, grid.lookup, C),
                          "bayes": lambda: grid(sdev.images[:1])}
            times = interleaved_times(contenders, runs, device)
            t_o3d, t_copy, t_carve, t_bayes = (float(np.median(times[k])) for k in ("o3d", "copy", "carve", "bayes"))
            o3d_occ = open3d_occupancy(open3d_carve(o3d, dense, masks_np, cameras), spec)
            ours = carve(masks, grid.lookup, C)[0].cpu()
            bayes = grid(sdev.images[:1]).occupied()[0].cpu()
            rule = open3d_rule_carve(scene.rig, spec, masks_cpu)
            unseen = int((grid.lookup.num_views < C).sum())
            speed_carve, speed_bayes = t_o3d / t_carve, t_o3d / t_bayes
            print(f"{n:>4}^3 {shape_label(spec):>12} {C:>4} {1e3 * dense_s:>7.0f}ms {1e3 * t_o3d:>8.1f}ms "
                  f"({1e3 * t_copy:>5.1f}ms) {1e3 * t_carve:>6.1f}ms {speed_carve:>7.1f}x {1e3 * t_bayes:>6.1f}ms "
                  f"{speed_bayes:>7.1f}x  "
                  f"{verdict(speed_carve, TARGET_SPEEDUP, below=False)} (bayes "
                  f"{verdict(speed_bayes, TARGET_SPEEDUP, below=False)})")
            agreement.append((n, C, o3d_occ, ours, rule, bayes, unseen))
        del dense
    print("\nagreement on frame 0 (voxel counts; IoU):")
    print(f"{'grid':>6} {'cams':>4} {'open3d':>7} {'carve':>7} {'o3d-only':>8} {'carve-only':>10} "
          f"{'IoU o3d/carve':>13} {'IoU o3d/o3d-rule':>16} {'IoU o3d/bayes':>13} {'not seen by all':>15}")
    for n, C, o3d_occ, ours, rule, bayes, unseen in agreement:
        print(f"{n:>4}^3 {C:>4} {int(o3d_occ.sum()):>7} {int(ours.sum()):>7} {int((o3d_occ & ~ours).sum()):>8} "
              f"{int((ours & ~o3d_occ).sum()):>10} {iou(o3d_occ, ours):>13.3f} {iou(o3d_occ, rule):>16.4f} "
              f"{iou(o3d_occ, bayes):>13.3f} {unseen:>15,}")
    print("  o3d-rule: plain-torch reference of Open3D's rule (a voxel survives a view when one of its 8 corners "
          "lands,\n  bilinearly, on a foreground pixel or its 1-px neighbourhood); carve: torchtrack's rule (the "
          "voxel centre's\n  nearest pixel is foreground). 'not seen by all': voxels whose centre some camera does "
          "not see (both remove them).")


# ------------------------------------------------------------------------------------------------ main


def cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="timed runs per figure (median), after 1 warm-up")
    parser.add_argument("--device", nargs="*", default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    parser.add_argument("--skip-open3d", action="store_true", help="leave out the Open3D comparison")
    parser.add_argument("--parts", nargs="*", choices=PARTS, default=list(PARTS),
                        help="what to measure (default: all; --skip-open3d drops 'open3d')")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default: torch's). With other processes on the CPU, 1 thread gives "
                             "stabler figures: each multi-threaded op waits for its slowest, possibly descheduled, "
                             "thread")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.set_grad_enabled(False)
    start = time.perf_counter()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads ({os.cpu_count()} logical CPUs: "
          f"{cpu_name()}), Python {platform.python_version()}")
    if torch.cuda.is_available():
        print(f"CUDA {torch.version.cuda}: {torch.cuda.get_device_name(0)}")
    print(load_average())
    print(f"box {BOX_LOWER_M} - {BOX_UPPER_M} m; body: procedural walk, 4 frames; background model from 4 empty "
          f"frames; Bayes {BayesConfig()}")

    bodies = walking_bodies(max(BATCH_SIZES))
    scenes: dict[tuple[str, int], Scene] = {}
    for w, h in IMAGE_SIZES_WH:
        eight = render_scene(RigConfig(num_cameras=8, width=w, height=h), bodies)
        scenes[(eight.label, 8)] = eight
        scenes[(eight.label, 4)] = camera_subset(eight, FOUR_OF_EIGHT, RigConfig(num_cameras=4, width=w, height=h))
    print(f"(scenes rendered in {time.perf_counter() - start:.0f} s)")

    for dev in args.device:
        device = torch.device(dev)
        on_device = {k: s.to(device) for k, s in scenes.items()}
        if "bayes" in args.parts:
            bench_bayes(on_device, args.runs, device)
            bayes_stages(on_device[("640x480", 8)], 128, args.runs, device)
        if "hull" in args.parts:
            bench_hull(on_device, args.runs, device)

    if "open3d" in args.parts and not args.skip_open3d:
        o3d = import_open3d()
        if o3d is not None:
            w, h = IMAGE_SIZES_WH[-1]
            eight = render_scene(RigConfig(num_cameras=8, width=w, height=h, k1=0.0), bodies[:1])
            undistorted = {8: eight, 4: camera_subset(eight, FOUR_OF_EIGHT,
                                                      RigConfig(num_cameras=4, width=w, height=h, k1=0.0))}
            for dev in args.device:
                bench_open3d(o3d, undistorted, args.runs, torch.device(dev))
    print(f"\n(total {time.perf_counter() - start:.0f} s; {load_average(warn=False)}, this run included)")


if __name__ == "__main__":
    main()
