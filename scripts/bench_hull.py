"""Time the hierarchical visual hull (torchtrack.occupancy.hull) per frame on synthetic frames.

Ring rigs of 4 cameras at 320x240 and 8 cameras at 640x480 see a 1.75 m body (starfish pose and a walking
pose) in a 2 m x 2 m x 2.1 m zone; the hull is computed at 1.5 cm and 2 cm finest voxels. Per-pixel squared
Mahalanobis distances come from a BackgroundModel estimated on noisy empty frames (``--oracle``: 100 inside the
rendered silhouettes, 0 outside). Prints the median wall-clock and CPU ms per frame over ``--repeats`` calls.

    .venv/bin/python scripts/bench_hull.py [--threads 2] [--repeats 50] [--oracle] [--device cpu]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from torchtrack.blobs import BlobModel
from torchtrack.occupancy.hull import HierarchicalHull, HullConfig
from torchtrack.skeleton import Skeleton
from torchtrack.synth.scene import SceneConfig, SceneRenderer
from torchtrack.synth.sequence import RigConfig, make_ring_rig

ZONE = ((-1.0, -1.0, 0.0), (1.0, 1.0, 2.1))


def body_poses() -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """(centres, R, semi-axes, colours) of the body in a starfish and a mid-stride walking pose."""
    skel = Skeleton.from_urdf().scaled_to_height(1.75)
    blobs = BlobModel.from_config(skel)
    walk = skel.rest_angles()
    for name, value in (("l_hip_flex", 0.4), ("r_hip_flex", -0.3), ("l_knee_flex", 0.5),
                        ("l_shoulder_flex", -0.4), ("r_shoulder_flex", 0.4)):
        if name in skel.dof_names:
            walk[skel.dof_names.index(name)] = value
    out = []
    for angles in (skel.starfish_angles(), skel.clamp(walk)):
        fk = skel(angles[None].double())
        c, R = blobs.ellipsoids(fk.bone_frames)
        out.append((c[0].float(), R[0].float(), blobs.semi_axes.float(), blobs.colour.float()))
    return out


def frame_maps(rig, body, oracle: bool, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """(mahal2 (C, H, W), colour (C, 3, H, W)) of one rendered frame."""
    renderer = SceneRenderer(rig, SceneConfig(noise_std=0.0 if oracle else 2.0 / 255.0))
    images, sil, _ = renderer.render(*body, generator=gen)
    if oracle:
        return torch.where(sil, 100.0, 0.0), images
    from torchtrack.background import BackgroundModel

    empty = torch.stack([renderer.background(generator=gen) for _ in range(10)])  # (N, C, 3, H, W)
    bg = BackgroundModel.from_frames(empty)
    return bg.mahalanobis2(images[None])[0], bg.normalise(images[None])[0]


def time_ms(fn, repeats: int) -> tuple[float, float]:
    """Median wall-clock and CPU (process) milliseconds of ``fn()``."""
    for _ in range(3):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append((time.perf_counter() - w0) * 1e3)
        cpu.append((time.process_time() - c0) * 1e3)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--oracle", action="store_true", help="silhouette oracle instead of a background model")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    bodies = body_poses()
    print(f"threads={args.threads} device={args.device} maps={'oracle' if args.oracle else 'background model'}")
    for cams, (w, h) in ((4, (320, 240)), (8, (640, 480))):
        rig = make_ring_rig(RigConfig(num_cameras=cams, width=w, height=h)).float()
        maps = [frame_maps(rig, body, args.oracle, gen) for body in bodies]
        rig = rig.to(args.device)
        maps = [(m.to(args.device), c.to(args.device)) for m, c in maps]
        for voxel in (0.015, 0.02):
            hull_of = HierarchicalHull(rig, HullConfig(lower_m=ZONE[0], upper_m=ZONE[1], finest_voxel_m=voxel))
            for name, (mahal2, colour) in zip(("starfish", "walk"), maps):
                def run():
                    hull = hull_of(mahal2, colour)
                    if args.device != "cpu":
                        torch.cuda.synchronize()
                    return hull

                hull = run()
                wall, cpu = time_ms(run, args.repeats)
                levels = torch.bincount(hull.level.cpu(), minlength=1).tolist()
                print(f"{cams} cams {w}x{h}, {voxel * 100:.1f} cm, {name:8s}: {wall:6.2f} ms/frame wall, "
                      f"{cpu:6.2f} ms CPU; {hull.num_voxels} voxels per level {levels}, "
                      f"{hull.volume_m3() * 1e3:.1f} litres")


if __name__ == "__main__":
    main()
