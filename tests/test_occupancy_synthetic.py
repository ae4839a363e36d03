"""Occupancy of rendered scenes against the ground-truth body volume (closed-form ellipsoids).

Small versions of scripts/eval_occupancy.py (which prints the full figures at 640x480 and 2 cm): here
320x240 images and 3 cm voxels keep the test fast; thresholds sit a little under the measured values.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchtrack.background import BackgroundModel
from torchtrack.blobs import BlobModel
from torchtrack.occupancy import BayesianGrid, GridSpec, SilhouetteCarving
from torchtrack.occupancy.metrics import false_components, inside_ellipsoids, iou
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.synth.scene import SceneConfig, SceneRenderer
from torchtrack.synth.sequence import RigConfig, make_ring_rig

SPEC = GridSpec((-1.2, -1.2, 0.0), (1.2, 1.2, 2.1), 0.03)


def _scene(cams: int, **scene):
    skel = Skeleton.from_urdf()
    blobs = BlobModel.from_config(skel)
    angles = procedural_motion(skel, "walk", 1.0, 10, starfish_s=0.3)[[2, 8]]  # starfish, mid-walk
    with torch.no_grad():
        centres, R = blobs.ellipsoids(skel(angles.double()).bone_frames)
    rig = make_ring_rig(RigConfig(num_cameras=cams, width=320, height=240)).float()
    renderer = SceneRenderer(rig, dataclasses.replace(SceneConfig(), **scene))
    g = torch.Generator().manual_seed(0)
    empty = torch.stack([renderer.background(generator=g) for _ in range(8)])
    images = torch.stack([renderer.render(centres[i].float(), R[i].float(), blobs.semi_axes, blobs.colour,
                                          frame=i, num_frames=2, generator=g)[0] for i in range(2)])
    truth = [inside_ellipsoids(SPEC.centres(), centres[i].float(), R[i].float(), blobs.semi_axes) for i in range(2)]
    return rig, BackgroundModel.from_frames(empty), images, truth, empty[0]


@pytest.mark.parametrize("cams, bayes_min, sfs_min", [(8, 0.75, 0.70), (4, 0.55, 0.52)])
def test_iou_with_the_body(cams, bayes_min, sfs_min):
    rig, bg, images, truth, _ = _scene(cams)
    with torch.no_grad():
        bayes = BayesianGrid(rig, SPEC, bg)(images).occupied()
        sfs = SilhouetteCarving(rig, SPEC, bg)(images).occupied()
    for i in range(2):
        print(f"{cams} cameras frame {i}: IoU bayes {iou(bayes[i], truth[i]):.3f} sfs {iou(sfs[i], truth[i]):.3f}")
        assert iou(bayes[i], truth[i]) > bayes_min, (cams, i, iou(bayes[i], truth[i]))
        assert iou(sfs[i], truth[i]) > sfs_min, (cams, i, iou(sfs[i], truth[i]))


def test_no_phantoms_from_shadow_illumination_distractor():
    rig, bg, images, truth, empty = _scene(8, shadow=True, illumination_change=0.25, distractor=True)
    with torch.no_grad():
        occ = BayesianGrid(rig, SPEC, bg)(images).occupied()
    for i in range(2):
        comps = false_components(occ[i], truth[i], SPEC)
        assert comps.largest_extent_m < 0.35, comps  # nothing near human size (measured: at most a few voxels)
        assert iou(occ[i], truth[i]) > 0.75


def test_empty_frame_gives_an_empty_grid():
    rig, bg, _, _, empty = _scene(4)
    with torch.no_grad():
        occ = BayesianGrid(rig, SPEC, bg)(empty[None]).occupied()
    assert int(occ.sum()) < 5
