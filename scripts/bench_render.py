"""Benchmark of the synthetic scene renderer: rendered views per second.

An 8-camera 640x480 ring rig (radius 3.5 m, 2 m high, looking at (0, 0, 1)) sees a 19-ellipsoid body standing at
the origin in the textured room; every frame moves the body a little so nothing is cached between frames.
Prints views/s for the plain scene and with shadow + distractor + illumination change, on the CPU and on CUDA
when present, and the body-casting work: (tile, part) candidate rays vs the dense ``C * H * W * K``.

    python scripts/bench_render.py [--frames 20] [--tile 16] [--device cpu cuda]
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from torchtrack.cameras.rig import CameraRig
from torchtrack.ellipsoids import nearest_hits, ray_ellipsoid_intersect, ray_ellipsoid_pair_hits
from torchtrack.synth.scene import SceneConfig, SceneRenderer


def ring_rig(num_cameras=8, width=640, height=480, focal_px=560.0, radius_m=3.5, height_m=2.0) -> CameraRig:
    """Cameras on a circle looking at (0, 0, 1), OpenCV convention, world Z up."""
    Rs, ts = [], []
    target = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    for i in range(num_cameras):
        a = 2 * math.pi * i / num_cameras
        centre = torch.tensor([radius_m * math.cos(a), radius_m * math.sin(a), height_m], dtype=torch.float64)
        z = torch.nn.functional.normalize(target - centre, dim=0)
        x = torch.nn.functional.normalize(torch.linalg.cross(z, up), dim=0)
        R = torch.stack([x, torch.linalg.cross(z, x), z])  # rows: camera axes in world
        Rs.append(R)
        ts.append(-R @ centre)
    K = torch.tensor([[focal_px, 0, (width - 1) / 2], [0, focal_px, (height - 1) / 2], [0, 0, 1]])
    return CameraRig([f"cam{i}" for i in range(num_cameras)], K.expand(num_cameras, 3, 3).clone(),
                     torch.stack(Rs).float(), torch.stack(ts).float(),
                     torch.tensor([[width, height]] * num_cameras))


def _limb(p0, p1, radius):
    """Ellipsoid spanning the segment p0 -> p1 (long axis = third column), with the given thickness."""
    p0, p1 = torch.tensor(p0, dtype=torch.float64), torch.tensor(p1, dtype=torch.float64)
    z = torch.nn.functional.normalize(p1 - p0, dim=0)
    helper = torch.tensor([1.0, 0, 0] if abs(float(z[0])) < 0.9 else [0, 1.0, 0], dtype=torch.float64)
    x = torch.nn.functional.normalize(torch.linalg.cross(helper, z), dim=0)
    R = torch.stack([x, torch.linalg.cross(z, x), z], 1)
    semi = torch.tensor([radius, radius, float((p1 - p0).norm()) / 2 + 0.3 * radius], dtype=torch.float64)
    return (p0 + p1) / 2, R, semi


def standing_body():
    """19 ellipsoids of a 1.75 m person standing at the origin, facing +X: centres, R, semi-axes, colours."""
    eye = torch.eye(3, dtype=torch.float64)
    trunk = [((0, 0, 0.95), (0.11, 0.16, 0.10)),  # pelvis
             ((0, 0, 1.12), (0.10, 0.15, 0.10)),  # abdomen
             ((0, 0, 1.32), (0.12, 0.18, 0.14)),  # chest
             ((0, 0, 1.53), (0.055, 0.055, 0.06)),  # neck
             ((0.01, 0, 1.66), (0.10, 0.085, 0.12))]  # head
    parts = [(torch.tensor(c, dtype=torch.float64), eye, torch.tensor(s, dtype=torch.float64)) for c, s in trunk]
    for side in (1, -1):  # left (+Y), right
        parts += [_limb((0, side * 0.05, 1.44), (0, side * 0.19, 1.42), 0.05),  # shoulder
                  _limb((0, side * 0.20, 1.41), (0.02, side * 0.23, 1.15), 0.05),  # upper arm
                  _limb((0.02, side * 0.23, 1.14), (0.08, side * 0.25, 0.90), 0.042),  # forearm
                  _limb((0.08, side * 0.25, 0.89), (0.10, side * 0.26, 0.80), 0.038),  # hand
                  _limb((0, side * 0.09, 0.90), (0.02, side * 0.10, 0.50), 0.075),  # thigh
                  _limb((0.02, side * 0.10, 0.49), (0, side * 0.10, 0.09), 0.055),  # shank
                  _limb((-0.03, side * 0.10, 0.05), (0.17, side * 0.11, 0.04), 0.042)]  # foot
    centers, R, semi = (torch.stack([p[i] for p in parts]).float() for i in range(3))
    shirt, skin, trousers, shoes = (0.70, 0.25, 0.20), (0.85, 0.65, 0.52), (0.20, 0.25, 0.50), (0.15, 0.15, 0.15)
    palette = [shirt, shirt, shirt, skin, skin] + 2 * [shirt, shirt, skin, skin, trousers, trousers, shoes]
    return centers, R, semi, torch.tensor(palette)


def bench(renderer: SceneRenderer, body, frames: int, device: torch.device) -> tuple[float, float]:
    """Views per second of ``renderer.render`` over ``frames`` frames (after two warm-up frames).

    Returns:
        (throughput over all frames, rate of the median frame); the median is less sensitive to other
        processes sharing the CPU.
    """
    centers, R, semi, colours = (x.to(device) for x in body)
    gen = torch.Generator(device=device).manual_seed(0)

    def frame(i: int) -> float:
        sway = torch.tensor([0.05 * math.sin(0.3 * i), 0.05 * math.cos(0.2 * i), 0.0], device=device)
        start = time.perf_counter()
        renderer.render(centers + sway, R, semi, colours, frame=i, num_frames=frames, generator=gen)
        if device.type == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - start

    for i in range(2):
        frame(i)
    times = sorted(frame(i) for i in range(frames))
    C = renderer.num_cameras
    return C * frames / sum(times), C / times[len(times) // 2]


def culling_report(renderer: SceneRenderer, body) -> None:
    """Work of the body cast: candidate (ray, part) pairs per frame vs dense, and the generic function's cost."""
    centers, R, semi, _ = body
    C, nT = renderer.tile_half_angle.shape
    T2 = renderer.config.tile_px ** 2
    v = centers[None] - renderer.cam_centers[:, None]
    beta = torch.arcsin((semi.amax(-1)[None] / v.norm(dim=-1)).clamp(max=1))
    cos_ang = renderer.tile_axis @ torch.nn.functional.normalize(v, dim=-1).transpose(1, 2)
    blocks = int((torch.arccos(cos_ang.clamp(-1, 1)) <= renderer.tile_half_angle[..., None] + beta[:, None]).sum())
    W, H = renderer.image_sizes_wh[0]
    dense = C * H * W * centers.shape[0]
    print(f"  body cast: {blocks} (tile, part) blocks = {blocks * T2:,} ray/part pairs per frame, "
          f"{100 * blocks * T2 / dense:.1f}% of dense C*H*W*K = {dense:,}")
    # Generic ray_ellipsoid_intersect (bounding-sphere cull) vs all pairs, on camera 0's rays.
    dirs = renderer.tile_dirs[:nT].reshape(-1, 3)
    origins = renderer.cam_centers[:1].expand_as(dirs)
    K = centers.shape[0]
    ray = torch.arange(dirs.shape[0]).repeat_interleave(K)
    k = torch.arange(K).repeat(dirs.shape[0])

    def culled() -> None:
        ray_ellipsoid_intersect(origins, dirs, centers, R, semi)

    def dense() -> None:
        for start in range(0, ray.shape[0], 1 << 20):  # chunks of all pairs, to bound memory
            sl = slice(start, start + (1 << 20))
            t = ray_ellipsoid_pair_hits(origins[ray[sl]], dirs[ray[sl]], k[sl], centers, R, semi)
            nearest_hits(t, ray[sl] - ray[sl][0], k[sl], int(ray[sl][-1] - ray[sl][0]) + 1)

    def best_of_3(fn) -> float:
        fn()  # warm-up
        times = []
        for _ in range(3):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        return min(times)

    t_culled, t_dense = best_of_3(culled), best_of_3(dense)
    print(f"  ray_ellipsoid_intersect on one camera's {dirs.shape[0]:,} rays: {1e3 * t_culled:.0f} ms with "
          f"bounding-sphere culling vs {1e3 * t_dense:.0f} ms for all {ray.shape[0]:,} pairs")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--tile", type=int, default=SceneConfig.tile_px)
    parser.add_argument("--device", nargs="*", default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads")
    rig, body = ring_rig(), standing_body()
    configs = {"plain": SceneConfig(tile_px=args.tile),
               "shadow+distractor+illumination": SceneConfig(tile_px=args.tile, shadow=True, distractor=True,
                                                             illumination_change=0.2)}
    for dev in args.device:
        device = torch.device(dev)
        for name, cfg in configs.items():
            start = time.perf_counter()
            renderer = SceneRenderer(rig.to(device), cfg).to(device)
            init_s = time.perf_counter() - start
            rate, median = bench(renderer, body, args.frames, device)
            print(f"{dev:5s} {name:32s} {rate:7.1f} views/s ({median:.1f} at the median frame; 640x480, "
                  f"{args.frames} frames x {renderer.num_cameras} views; setup {init_s:.1f} s)")
        if device.type == "cpu":
            culling_report(renderer, body)


if __name__ == "__main__":
    main()
