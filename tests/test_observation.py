"""The observer (torchtrack.tracking.observation): voxels and colours from a given probability, the box its voxels
cover.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from torchtrack.checks import InputError

from conftest import small_walk

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return small_walk(tmp_path_factory.mktemp("track") / "seq", duration_s=0.5, video_format="png")


def test_observer_voxels_from_a_given_probability_take_the_projected_pixels_colour(seq):
    """Observer.from_probability (the Bayesian grid's voxels from any per-voxel probability): the kept voxels are
    those over the threshold, weighted P s^3, each with the YUV of the pixel its centre projects to in every view
    (reference: CameraRig.project, checked against OpenCV's projectPoints in test_cameras)."""
    from torchtrack.background import BackgroundModel
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.tracking.observation import Observer

    folder = SequenceFolder(seq)
    rig = folder.rig.float()
    W, H = (int(v) for v in rig.image_size_wh[0].tolist())
    bg = BackgroundModel.from_folder(folder, size_wh=(W, H))
    observer = Observer(rig, bg, "bayes", voxel_size_m=0.05)
    images = folder.read_frame(0, size_wh=(W, H))[None]  # (1, C, 3, H, W)
    yuv = bg.normalise(images)
    V = observer.centres.shape[0]
    prob = torch.rand(1, V, generator=torch.Generator().manual_seed(0))
    obs = observer.from_probability(prob, yuv, torch.ones(1, len(rig), dtype=torch.bool))[0]
    keep = (prob[0] > observer.threshold).nonzero()[:, 0]
    assert torch.equal(obs.points, observer.centres[keep])
    assert torch.allclose(obs.weights, prob[0, keep] * 0.05 ** 3)
    uv, visible = rig.project(obs.points)  # (C, N, 2), (C, N)
    px = uv.round().long()
    agree = []
    for c in range(len(rig)):
        seen = visible[c].nonzero()[:, 0]
        ref = yuv[0, c][:, px[c, seen, 1], px[c, seen, 0]].T  # (n, 3)
        agree.append((obs.colours[seen, c] - ref).abs().amax(-1) < 1e-6)
        assert bool(torch.isnan(obs.colours[~visible[c], c]).all())
    # a centre within float rounding of a pixel border may land on the neighbour in the lookup
    assert float(torch.cat(agree).float().mean()) > 0.999
    with pytest.raises(InputError, match="Bayesian grid"):
        Observer(rig, bg, "hull", voxel_size_m=0.05).from_probability(prob, yuv, torch.ones(1, len(rig)).bool())


@pytest.mark.parametrize("model", ["bayes", "hull"])
def test_observer_gives_the_box_its_voxels_cover(seq, model):
    """The observation's ``volume_m`` is the box the model's voxels can fill: the tracking zone's lower corner and
    its upper one rounded up to whole voxels (the hull's to whole level-0 cubes); every voxel lies in
    it, and it goes on through ``pooled`` and ``split``."""
    from torchtrack.background import BackgroundModel
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.tracking.observation import Observer

    folder = SequenceFolder(seq)
    rig = folder.rig.float()
    W, H = (int(v) for v in rig.image_size_wh[0].tolist())
    bg = BackgroundModel.from_folder(folder, size_wh=(W, H))
    zone = ((-1.0, -1.0, 0.0), (1.0, 1.13, 2.0))
    observer = Observer(rig, bg, model, voxel_size_m=0.05, lower_m=zone[0], upper_m=zone[1])
    obs = observer(folder.read_frame(0, size_wh=(W, H))[None])[0]
    lower, upper = (torch.tensor(c, dtype=torch.float64) for c in obs.volume_m)
    assert torch.allclose(lower, torch.tensor(zone[0], dtype=torch.float64))
    # 2.13 m along y: 43 voxels of 0.05 m; the hull's level 0 has 0.05 * 2^round(log2(2.13 / (16 * 0.05))) = 0.1 m
    # cubes, 22 of them
    expected = (1.0, 1.15, 2.0) if model == "bayes" else (1.0, 1.2, 2.0)
    assert torch.allclose(upper, torch.tensor(expected, dtype=torch.float64), atol=1e-9)
    half = obs.sizes.double()[:, None] / 2
    pts = obs.points.double()
    assert obs.num_voxels > 0 and bool(((pts - half >= lower - 1e-6) & (pts + half <= upper + 1e-6)).all())
    assert obs.pooled(0.1).volume_m == obs.volume_m and obs.split(0.01).volume_m == obs.volume_m


