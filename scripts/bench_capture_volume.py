#!/usr/bin/env python
"""What the capture volume costs the Bayesian grid: the tracker's observation of one frame over the box that
``min_views`` cameras of a ring see, summed over every camera at every voxel (``BayesianGrid.from_log_likelihood``
and a threshold) against the first views and a bound (``BayesianGrid.occupied_voxels``, the tracker's).

Scene: ``make_ring_rig`` (8 cameras, 3.5 m ring) at the tracking's processing size (320x240), 3 cm voxels, the
procedural walk rendered by ``SceneRenderer``, a ``BackgroundModel`` from rendered empty frames. Prints, per
``min_views``: the box's voxels, median ms per frame of both (timed in interleaved rounds, batches of 4 frames, the
background likelihood included in neither), the share of voxels the bound leaves to sum over every camera, and
whether both keep the same voxels.

Usage: .venv/bin/python scripts/bench_capture_volume.py [--runs 5] [--views 8 6 4 3] [--device cpu]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from torchtrack.background import BackgroundModel
from torchtrack.blobs import BlobModel
from torchtrack.occupancy import BayesConfig, BayesianGrid, grid_from_rig
from torchtrack.occupancy.bayes import BOUND_MARGIN, default_pd
from torchtrack.skeleton import Skeleton
from torchtrack.synth.scene import SceneConfig, SceneRenderer
from torchtrack.synth.sequence import RigConfig, SynthConfig, make_ring_rig, motion_angles

THRESHOLD = 0.5  # the tracking config's observation.threshold
VOXEL_M = 0.03  # the tracking config's observation.voxel_m
FRAMES = 4


def scene(cameras: int) -> tuple[torch.nn.Module, torch.Tensor, BackgroundModel]:
    """A ring rig at 320x240, FRAMES rendered walk frames (B, C, 3, H, W) and the background of empty frames."""
    cfg = RigConfig(num_cameras=cameras, width=320, height=240)
    renderer = SceneRenderer(make_ring_rig(cfg, dtype=torch.float32), SceneConfig())
    skel, angles = motion_angles(SynthConfig(motion="walk", duration_s=1.0, starfish_s=0.0, fps=10),
                                 Skeleton.from_urdf())
    blobs = BlobModel.from_config(skel)
    centres, R = blobs.ellipsoids(skel(angles.double()).bone_frames)
    gen = torch.Generator().manual_seed(0)
    empty = torch.stack([renderer.background(generator=gen) for _ in range(4)])
    pick = torch.linspace(0, angles.shape[0] - 1, FRAMES).round().long().tolist()
    images = torch.stack([renderer.render(centres[t].float(), R[t].float(), blobs.semi_axes.float(),
                                          blobs.colour.float(), generator=gen)[0] for t in pick])
    rig = make_ring_rig(cfg, dtype=torch.float32)
    return rig, images, BackgroundModel.from_frames(empty, camera_names=rig.names)


def timed(fn, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="timed rounds (default: %(default)s)")
    ap.add_argument("--views", type=int, nargs="+", default=[8, 6, 4, 3], help="min_views to compare")
    ap.add_argument("--cameras", type=int, default=8, help="cameras on the ring (default: %(default)s)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    device = torch.device(args.device)
    rig, images, bg = scene(args.cameras)
    rig, images, bg = rig.to(device), images.to(device), bg.to(device)
    lit, shadowed, _ = bg.log_likelihood_and_yuv(images, shadows=True)
    print(f"{args.cameras}-camera ring, {images.shape[-1]}x{images.shape[-2]}, {VOXEL_M * 100:.0f} cm voxels, "
          f"pd {default_pd(args.cameras)}, batches of {FRAMES} frames, {torch.get_num_threads()} threads, "
          f"{args.runs} runs")
    print(f"{'min_views':>9} {'box (m)':>13} {'voxels':>10} {'every camera':>13} {'first views':>12} "
          f"{'summed':>7} {'same':>5}")
    for views in args.views:
        spec = grid_from_rig(rig, VOXEL_M, min_views=views)
        grid = BayesianGrid(rig, spec, bg, BayesConfig(pd=None, min_views=views)).to(device)

        def dense():
            prob = grid.from_log_likelihood(lit, shadowed).probability()
            keep = prob > THRESHOLD
            return [(keep[b].nonzero()[:, 0], prob[b][keep[b]]) for b in range(prob.shape[0])]

        def sparse():
            return grid.occupied_voxels(lit, shadowed, THRESHOLD)

        a, b = dense(), sparse()  # warm-up, and the agreement
        same = all(torch.equal(x[0], y[0]) and torch.allclose(x[1], y[1]) for x, y in zip(a, b))
        t_dense, t_sparse = [], []
        for _ in range(args.runs):  # interleaved: both see the same load
            t_dense.append(timed(dense, device))
            t_sparse.append(timed(sparse, device))
        # the share of the upper voxels the bound leaves, recomputed as occupied_voxels does
        bound = grid.first_views_bound(grid._flat_evidence(lit))  # what occupied_voxels sums over every camera
        share = float((bound > -BOUND_MARGIN).float().mean())  # prior 0.5, threshold 0.5
        size = spec.upper_m[0] - spec.lower_m[0]
        ms_dense, ms_sparse = (1e3 * statistics.median(t) / FRAMES for t in (t_dense, t_sparse))
        print(f"{views:>9} {size:>6.2f} x {spec.upper_m[1] - spec.lower_m[1]:<4.2f} {spec.num_voxels:>10,} "
              f"{ms_dense:>10.1f} ms {ms_sparse:>9.1f} ms {100 * share:>6.1f}% {'yes' if same else 'NO':>5}")


if __name__ == "__main__":
    main()
