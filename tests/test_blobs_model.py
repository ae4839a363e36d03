"""Blob appearance model: placement (eq. 17) and covariance (eq. 18) against independent references."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.blobs.model import load_blob_specs
from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton


@pytest.fixture(scope="module")
def model():
    skel = Skeleton.from_urdf()
    return skel, BlobModel.from_config(skel)


def test_rest_pose_centres_by_hand(model):
    skel, blobs = model
    angles = skel.rest_angles()[None].double()
    centres, R = blobs.ellipsoids(skel(angles).bone_frames)
    z_pelvis = skel.standing_root_height()
    chest = centres[0, blobs.names.index("chest")]
    # torso bone starts 0.10 m above the pelvis, is 0.45 m long, the chest sits at 60 % of it
    torch.testing.assert_close(chest, torch.tensor([0.0, 0.0, z_pelvis + 0.10 + 0.6 * 0.45], dtype=torch.float64))
    # the shank's blob sits at 45 % of the bone (its centre of mass towards the knee)
    shank = centres[0, blobs.names.index("r_shank")]
    torch.testing.assert_close(shank, torch.tensor([0.0, -0.09, z_pelvis - 0.42 - 0.45 * 0.42], dtype=torch.float64))
    # the 'along' axis of a hanging limb points down, 'width' to the left
    Rs = R[0, blobs.names.index("l_forearm")]
    torch.testing.assert_close(Rs[:, 0], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    torch.testing.assert_close(Rs[:, 2], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))


def test_gaussian_equals_moments_of_solid_ellipsoid(model):
    """Monte Carlo moments of points drawn uniformly inside each ellipsoid match (mu, Sigma)."""
    skel, blobs = model
    g = torch.Generator().manual_seed(0)
    angles = skel.starfish_angles()[None].double()
    angles[0, 3] = 0.7  # turn the body so covariances are not axis-aligned
    angles[0, skel.dof_names.index("l_elbow_flex")] = 1.0
    frames = skel(angles).bone_frames
    mu, cov = blobs.gaussians(frames)
    centres, R = blobs.ellipsoids(frames)
    u = torch.randn(200_000, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True) * torch.rand(200_000, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    for k in range(blobs.num_blobs):
        pts = centres[0, k] + (u * blobs.semi_axes[k].double()) @ R[0, k].T  # uniform in the solid ellipsoid
        torch.testing.assert_close(pts.mean(0), mu[0, k], atol=2e-3 * blobs.semi_axes[k].max().item(), rtol=0)
        emp = torch.cov(pts.T)
        torch.testing.assert_close(emp, cov[0, k], atol=0.02 * blobs.semi_axes[k].max().item() ** 2, rtol=0)
    assert torch.allclose(cov, cov.transpose(-1, -2))
    assert bool((torch.linalg.eigvalsh(cov) > 0).all())


def test_scales_with_subject(model):
    skel, blobs = model
    small = Skeleton.from_urdf().scaled_to_height(1.5)
    b2 = BlobModel.from_config(small)
    torch.testing.assert_close(b2.semi_axes, blobs.semi_axes * 1.5 / 1.75, rtol=1e-5, atol=1e-6)


def test_bad_config(tmp_path, model):
    skel, _ = model
    p = tmp_path / "b.yaml"
    p.write_text("blobs:\n  - {name: x, bone: tail, offset: 0, along: 1, depth: 0.1, width: 0.1, colour: [1,0,0]}\n")
    with pytest.raises(InputError, match="tail"):
        BlobModel.from_config(skel, p)
    p.write_text("blobs:\n  - {name: x, bone: head, offset: 0}\n")
    with pytest.raises(InputError, match=r"blob 0 \(x\).*missing fields"):
        load_blob_specs(p)
    p.write_text("blobs: [\n")
    with pytest.raises(InputError, match="YAML"):
        load_blob_specs(p)
    assert math.isclose(load_blob_specs()[1], 1.75)
