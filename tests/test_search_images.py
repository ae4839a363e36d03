"""The start search's image terms (torchtrack.tracking.search.image_terms) against silhouettes rendered by ray
casting (torchtrack.ellipsoids.ray_ellipsoid_intersect through the lens model), not by the projection they test."""

from __future__ import annotations

import torch

import torchtrack.tracking.search as search
from torchtrack.blobs.model import BlobModel
from torchtrack.blobs.shape import unit_ball_samples
from torchtrack.skeleton import Skeleton
from torchtrack.ellipsoids import ray_ellipsoid_intersect
from torchtrack.synth.sequence import RigConfig, make_ring_rig
from torchtrack.tracking.observation import ViewSilhouettes
from torchtrack.tracking.search import INSIDE_GROW, _Views, image_terms


def _rendered(rig, centres, R, semi) -> torch.Tensor:
    """(C, H, W) bool: pixels whose ray (through the lens model) meets an ellipsoid."""
    W, H = (int(v) for v in rig.image_size_wh[0].tolist())
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    uv = torch.stack([u, v], -1).reshape(1, -1, 2).expand(len(rig), -1, -1)
    origins, dirs = rig.pixel_rays(uv)
    _, part, _ = ray_ellipsoid_intersect(origins, dirs, centres, R, semi)
    return (part >= 0).reshape(len(rig), H, W)


def _body(dx: float = 0.0):
    skel = Skeleton.from_urdf().scaled_to_height(1.75)
    blobs = BlobModel.from_config(skel)
    angles = skel.starfish_angles()
    angles[skel.dof_names.index("root_tx")] += dx
    centres, R = blobs.ellipsoids(skel.forward(angles[None]).bone_frames)
    return centres.float(), R.float(), blobs.semi_axes.float()[None]


def _terms(views, centres, R, semi):
    q = centres[:, :, None] + torch.einsum("hkij,hksj->hksi", R, semi[:, :, None] * unit_ball_samples(
        48, dtype=torch.float32)[None, None])
    return image_terms(centres, R, semi, q, semi.prod(-1), views)


def test_the_projected_ellipses_cover_the_rendered_body_and_no_more():
    """A starfish rendered into a 4-camera ring with barrel distortion: at the true pose every foreground cell is
    inside the projected blobs (grown by INSIDE_GROW) and the body's points are on foreground; the same body
    30 cm aside keeps a fraction of each. One ellipsoid's linearised projection (not grown) against its own
    rendered silhouette: IoU over 0.9 in every view."""
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120, radius_m=3.0, k1=-0.08)).float()
    centres, R, semi = _body()
    fg = _rendered(rig, centres[0], R[0], semi[0])
    sil = ViewSilhouettes.from_evidence(fg.float() - 0.5, rig, cell_px=2)
    views = _Views(sil, torch.ones(len(rig), dtype=torch.bool))
    explained, filled = _terms(views, centres, R, semi)
    assert float(explained) > 0.97 and float(filled) > 0.9, (float(explained), float(filled))
    aside = _terms(views, *_body(dx=0.3))
    assert float(aside[0]) < 0.75 * float(explained) and float(aside[1]) < 0.75 * float(filled)


def test_a_projected_ellipse_has_the_rendered_silhouettes_size():
    """One blob (the chest's) against its own silhouette rendered by ray casting at its grown size (INSIDE_GROW)
    and at 1.25 times that: the projected ellipse covers the first (explained over 0.97) and the share of the
    second that an ellipse 1/1.25 its size covers, (1/1.25)^2 = 0.64 of the cells, within 0.06."""
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120, radius_m=3.0, k1=-0.08)).float()
    centres, R, semi = _body()
    k = BlobModel.from_config(Skeleton.from_urdf()).names.index("chest")
    one = centres[:, k:k + 1], R[:, k:k + 1], semi[:, k:k + 1]
    for factor, want, tol in ((INSIDE_GROW, 0.985, 0.015), (1.25 * INSIDE_GROW, 0.64, 0.06)):
        mask = _rendered(rig, one[0][0], one[1][0], factor * one[2][0])
        views = _Views(ViewSilhouettes.from_evidence(mask.float() - 0.5, rig, cell_px=1),
                       torch.ones(len(rig), dtype=torch.bool))
        explained, _ = _terms(views, *one)
        assert abs(float(explained) - want) < tol, (factor, float(explained))


def test_blobs_past_the_lens_models_fold_cover_nothing():
    """CameraRig.in_lens_model is project()'s validity without the image bounds: the same on points that land in
    the images; a point in front of a camera but far off its axis (past the radius where the barrel distortion
    folds back) is out. The image terms then give such a camera nothing from a body beside it: a starfish 3.5 m
    aside, level with camera 0, covers none of camera 0's foreground drawn where the folded projection would put
    its blobs."""
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120, radius_m=3.0, k1=-0.08)).float()
    pts = torch.randn(500, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([1.0, 1.0, 0.5]) + \
        torch.tensor([0.0, 0.0, 1.0])
    _, valid = rig.project(pts)
    assert bool(rig.in_lens_model(pts)[valid].all())
    cam0 = rig.centers()[0]
    side = torch.stack([-cam0[1], cam0[0], torch.tensor(0.0)]) / cam0[:2].norm()  # across camera 0's axis
    beside = cam0 + 0.2 * (-cam0 / cam0.norm()) + 3.0 * side  # 0.2 m in front of its plane, 3 m aside
    assert not bool(rig.in_lens_model(beside[None])[0, 0])
    centres, R, semi = _body()
    aside = centres + (beside - centres[0, 0])  # the pelvis there
    uv, _ = rig.project(aside.reshape(-1, 3))
    folded = torch.zeros(4, 120, 160, dtype=torch.bool)  # foreground wherever the fold puts the blobs' centres
    for c in range(4):
        u = uv[c, :, 0].round().long().clamp(0, 159)
        v = uv[c, :, 1].round().long().clamp(0, 119)
        folded[c, v, u] = True
    views = _Views(ViewSilhouettes.from_evidence(folded.float() - 0.5, rig, cell_px=1),
                   torch.tensor([True, False, False, False]))
    explained, _ = _terms(views, aside, R, semi)
    assert float(explained) < 0.2, float(explained)


def test_foreground_cells_are_the_pixels_they_pool():
    """ViewSilhouettes at 4-pixel cells against a plain loop over the pixels: a cell is foreground when more than
    half of its pixels are (the partial cells at the right and bottom edges over the pixels they have); _Views
    puts each cell's centre at the centre of its 4 x 4 block and looks every pixel up in its own cell."""
    rig = make_ring_rig(RigConfig(num_cameras=2, width=22, height=18, radius_m=3.0)).float()
    gen = torch.Generator().manual_seed(3)
    ev = torch.rand(2, 18, 22, generator=gen) - 0.45  # > 0: foreground, a little over half the pixels
    sil = ViewSilhouettes.from_evidence(ev, rig, cell_px=4)
    views = _Views(sil, torch.ones(2, dtype=torch.bool))
    want, centres = torch.zeros(2, 5, 6, dtype=torch.bool), [[], []]
    for c in range(2):
        for iv in range(5):
            for iu in range(6):
                block = ev[c, 4 * iv:4 * iv + 4, 4 * iu:4 * iu + 4] > 0
                want[c, iv, iu] = block.float().mean() > 0.5
                if want[c, iv, iu]:
                    centres[c].append((4 * iu + 1.5, 4 * iv + 1.5))
    assert torch.equal(sil.fg, want)
    for c in range(2):
        got = views.cells[c, views.cell_ok[c]]
        assert torch.allclose(got, torch.tensor(centres[c]).reshape(-1, 2)), c
    v, u = torch.meshgrid(torch.arange(18.0), torch.arange(22.0), indexing="ij")
    uv = torch.stack([u, v], -1).expand(2, -1, -1, -1)
    looked = views.lookup(uv, torch.ones(2, 18, 22, dtype=torch.bool))
    assert torch.equal(looked, want[:, (v // 4).long(), (u // 4).long()])


def test_an_unreadable_camera_counts_for_nothing():
    """The terms come from the readable cameras only: a body scored with camera 2 unreadable (its stale
    foreground all set) equals the mean of the terms scored on each readable camera alone (each sees the whole
    body, so the pooled "filled" is their mean too)."""
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120, radius_m=3.0, k1=-0.08)).float()
    centres, R, semi = _body()
    fg = _rendered(rig, centres[0], R[0], semi[0])
    fg[2] = True  # what an unreadable camera's evidence must not bring
    sil = ViewSilhouettes.from_evidence(fg.float() - 0.5, rig, cell_px=2)
    aside = _body(dx=0.15)
    readable = torch.tensor([True, True, False, True])
    both = _terms(_Views(sil, readable), *aside)
    alone = [_terms(_Views(sil, torch.arange(4) == k), *aside) for k in (0, 1, 3)]
    for term in range(2):
        want = sum(float(a[term]) for a in alone) / 3
        assert abs(float(both[term]) - want) < 1e-5, (term, float(both[term]), want)
    assert float(both[0]) > 0.3 and float(both[1]) > 0.3  # not trivially 0
    counted = _terms(_Views(sil, torch.ones(4, dtype=torch.bool)), *aside)  # the junk, were it read
    assert float(counted[0]) < float(both[0]) - 0.05


def test_a_camera_that_sees_none_of_the_body_does_not_empty_it():
    """A body beyond camera 0 (behind it, out of its view and of cameras 1 and 3's), seen whole by camera 2;
    camera 0's foreground is something else: "filled" is camera 2's alone (the cameras pooled by what they see
    of the body), while "explained" averages camera 0's unexplained foreground in (half camera 2's)."""
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120, radius_m=3.0, k1=-0.08)).float()
    centres, R, semi = _body()
    cam0 = rig.centers()[0]
    flat = torch.tensor([1.0, 1.0, 0.0])
    beyond = centres + (1.35 * cam0 - centres[0, 0]) * flat  # the pelvis 1.05 m behind camera 0
    fg = _rendered(rig, beyond[0], R[0], semi[0])
    assert not bool(fg[0].any()) and not bool(fg[1].any()) and not bool(fg[3].any()) and int(fg[2].sum()) > 50
    fg[0, 40:80, 60:100] = True  # something else in camera 0's view
    sil = ViewSilhouettes.from_evidence(fg.float() - 0.5, rig, cell_px=2)
    every = _terms(_Views(sil, torch.ones(4, dtype=torch.bool)), beyond, R, semi)
    two = _terms(_Views(sil, torch.arange(4) == 2), beyond, R, semi)
    assert float(two[1]) > 0.6 and abs(float(every[1]) - float(two[1])) < 1e-5, (float(every[1]), float(two[1]))
    assert abs(float(every[0]) - 0.5 * float(two[0])) < 1e-5


def test_the_ellipse_test_in_steps_matches_the_whole_quadratic_form(monkeypatch):
    """The cells each blob's ellipse covers, taken a few hypotheses at a time (IMAGE_TERM_ELEMENTS forced down to
    steps of 2 over 7 hypotheses), against the whole quadratic form d^T S^-1 d <= 1 written out here over every
    hypothesis at once: "explained" identical. A body no camera sees (50 m away) scores 0 in both terms, not
    NaN."""
    rig = make_ring_rig(RigConfig(num_cameras=4, width=160, height=120, radius_m=3.0, k1=-0.08)).float()
    centres, R, semi = _body()
    fg = _rendered(rig, centres[0], R[0], semi[0])
    views = _Views(ViewSilhouettes.from_evidence(fg.float() - 0.5, rig, cell_px=2), torch.ones(4, dtype=torch.bool))
    gen = torch.Generator().manual_seed(1)
    H = 7
    c = centres.expand(H, -1, -1) + 0.1 * torch.randn(H, 1, 3, generator=gen)
    Rh, a = R.expand(H, -1, -1, -1), semi.expand(H, -1, -1) * (0.8 + 0.4 * torch.rand(H, 1, 1, generator=gen))
    C, K, N = 4, c.shape[1], views.cells.shape[1]
    monkeypatch.setattr(search, "IMAGE_TERM_ELEMENTS", 2 * C * K * N)  # 2 hypotheses a step: 2, 2, 2, 1
    stepped, _ = _terms(views, c, Rh, a)
    # reference: the ellipses from the same linearised projection, every cell against every blob in one einsum
    eye = torch.eye(3)
    probe = torch.cat([c[:, :, None], c[:, :, None] + search.JACOBIAN_STEP_M * eye], 2)
    uv, _ = rig.project(probe.reshape(-1, 4, 3))
    m = uv[:, :, 0].reshape(C, H, K, 2)
    J = ((uv[:, :, 1:] - uv[:, :, :1]) / search.JACOBIAN_STEP_M).transpose(-1, -2).reshape(C, H, K, 2, 3)
    sig = Rh @ torch.diag_embed((INSIDE_GROW * a) ** 2) @ Rh.transpose(-1, -2)
    Sinv = torch.linalg.inv(J @ sig[None] @ J.transpose(-1, -2) + 1e-6 * torch.eye(2))
    d = views.cells[:, None, None] - m[:, :, :, None]  # (C, H, K, N, 2)
    inside = torch.einsum("chkni,chkij,chknj->chkn", d, Sinv, d) <= 1.0
    inside &= rig.in_lens_model(c.reshape(-1, 3)).reshape(C, H, K)[..., None]
    covered = inside.any(2) & views.cell_ok[:, None]
    want = (covered.float().sum(-1) / views.counts[:, None]).mean(0)
    assert torch.allclose(stepped, want, atol=1e-6), (stepped, want)
    far = _terms(views, centres + torch.tensor([50.0, 0.0, 0.0]), R, semi)
    assert float(far[0]) == 0.0 and float(far[1]) == 0.0
