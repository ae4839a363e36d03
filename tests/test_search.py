"""The start search's selection (torchtrack.tracking.search)."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.tracking.search import _top_both_ways, ellipsoid_distance2


def _reference(score: list[float], heading: list[float], n: int) -> set[int]:
    """A plain loop: walk the hypotheses best first; each joins its side (facing within 90 deg of the best's heading,
    or not) while that side has fewer than its share (half of ``n`` ahead, rounded up, the rest behind); then the
    best of those left until there are ``n``."""
    order = sorted(range(len(score)), key=lambda i: -score[i])
    h0 = heading[order[0]]

    def ahead(i: int) -> bool:
        d = (heading[i] - h0) % (2 * math.pi)
        return min(d, 2 * math.pi - d) < 0.5 * math.pi

    n_ahead = min(n - n // 2, sum(ahead(i) for i in order))
    n_behind = min(n - n_ahead, sum(not ahead(i) for i in order))
    got, a, b = [], 0, 0
    for i in order:
        if ahead(i) and a < n_ahead:
            got.append(i)
            a += 1
        elif not ahead(i) and b < n_behind:
            got.append(i)
            b += 1
    for i in order:
        if len(got) >= n:
            break
        if i not in got:
            got.append(i)
    return set(got)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n", [1, 4, 7, 16])
def test_the_kept_hypotheses_face_both_ways_as_a_plain_loop_picks_them(seed, n):
    g = torch.Generator().manual_seed(seed)
    m = 40
    score = torch.rand(m, generator=g)
    # mostly facing one way, as an annealed search's pool does; seed 0 all one way (the rest from that side)
    heading = 0.3 * torch.randn(m, generator=g) + (math.pi * (torch.rand(m, generator=g) < 0.2) if seed else 0.0)
    heading = heading + 4 * math.pi * torch.randint(-1, 2, (m,), generator=g)  # headings not wrapped
    got = _top_both_ways(score, heading, n)
    assert got.shape[0] == n and len(set(got.tolist())) == n
    assert set(got.tolist()) == _reference(score.tolist(), heading.tolist(), n)
    assert int(score.argmax()) in got.tolist()  # the best is always kept


def test_a_short_side_leaves_its_share_to_the_other():
    """Two hypotheses face the best's way, ten away: n = 8 keeps both and the best six facing away; n = 20 all."""
    score = torch.tensor([0.9, 0.1] + [0.8 - 0.05 * k for k in range(10)])
    heading = torch.tensor([0.2, -0.3] + [math.pi + 0.1 * k for k in range(10)])
    assert set(_top_both_ways(score, heading, 8).tolist()) == {0, 1, 2, 3, 4, 5, 6, 7}
    assert sorted(_top_both_ways(score, heading, 20).tolist()) == list(range(12))


@pytest.mark.parametrize("seed", range(3))
def test_ellipsoid_distance2_matches_a_plain_loop(seed):
    """The quadric product against each point turned into each ellipsoid's axes and divided by its semi-axes, in
    float64 one pair at a time; body-sized ellipsoids 2-3 m from the origin, as in a room."""
    g = torch.Generator().manual_seed(seed)
    H, K, N = 3, 5, 40
    centres = torch.tensor([2.0, -1.5, 1.0]) + 0.4 * torch.randn(H, K, 3, generator=g)
    R = torch.linalg.qr(torch.randn(H, K, 3, 3, generator=g))[0]
    semi = 0.03 + 0.2 * torch.rand(H, K, 3, generator=g)
    points = centres.reshape(-1, 3)[torch.randint(H * K, (N,), generator=g)] + 0.15 * torch.randn(N, 3, generator=g)
    got = ellipsoid_distance2(points, centres, R, semi)
    want = torch.empty(N, H, K, dtype=torch.float64)
    for n in range(N):
        for h in range(H):
            for k in range(K):
                local = R[h, k].double().T @ (points[n] - centres[h, k]).double() / semi[h, k].double()
                want[n, h, k] = float(local @ local)
    assert torch.allclose(got.double(), want, rtol=1e-4, atol=1e-3)
    assert ((got <= 1) == (want <= 1)).float().mean() > 0.99  # inside tests agree but at the boundary's rounding
