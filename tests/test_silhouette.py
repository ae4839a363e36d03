"""Silhouette carving against a plain per-voxel, per-camera loop."""

from __future__ import annotations

import torch

from torchtrack.occupancy import GridSpec, VoxelLookup
from torchtrack.occupancy.silhouette import carve
from torchtrack.synth.sequence import RigConfig, make_ring_rig


def test_progressive_carving_equals_plain_loop():
    rig = make_ring_rig(RigConfig(num_cameras=4, width=48, height=36)).float()
    spec = GridSpec((-0.8, -0.8, 0.0), (0.8, 0.8, 2.0), 0.1)
    lk = VoxelLookup(rig, spec)
    g = torch.Generator().manual_seed(1)
    masks = torch.rand(3, 4, 36, 48, generator=g) < 0.7
    masks[:, :, 8:30, 18:30] = True
    for min_views in (4, 2):
        out = carve(masks, lk, min_views)
        for b in range(3):
            for v in range(spec.num_voxels):
                seen = [c for c in range(4) if lk.pixel_index[c, v] >= 0]
                keep = len(seen) >= min_views and all(
                    bool(masks[b, c].reshape(-1)[lk.pixel_index[c, v]]) for c in seen)
                assert bool(out[b, v]) == keep, (b, v, min_views)
    assert 0 < int(out.sum()) < out.numel()
