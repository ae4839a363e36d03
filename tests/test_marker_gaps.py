"""Each marker's output position (torchtrack.markers.gaps) against a plain per-marker, per-frame loop of its rules."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.markers.gaps import BODY, FILLED, MEASURED, NONE, measured_markers


def _reference(body, X, views, min_views, within_m, gap, smooth, neighbour_m, agree_m):
    """The rules written out one marker and one frame at a time, in plain Python."""
    T, M, _ = body.shape
    counted = []  # [t][m]: the triangulation near the body's marker, nearer it than any other, agreeing with its
    for t in range(T):  # neighbours' offsets
        first = []
        for m in range(M):
            good = (int(views[t, m]) >= min_views and bool(torch.isfinite(X[t, m]).all())
                    and bool(torch.isfinite(body[t, m]).all()))
            d = [float((X[t, m] - body[t, j]).norm()) for j in range(M) if bool(torch.isfinite(body[t, j]).all())]
            first.append(good and float((X[t, m] - body[t, m]).norm()) < within_m
                         and float((X[t, m] - body[t, m]).norm()) <= min(d))
        row = []
        for m in range(M):
            apart = sorted(float(((X[t, m] - body[t, m]) - (X[t, j] - body[t, j])).norm()) for j in range(M)
                           if j != m and first[j] and float((body[t, m] - body[t, j]).norm()) < neighbour_m)
            row.append(first[m] and (not apart or apart[(len(apart) - 1) // 2] < agree_m))
        counted.append(row)
    out = body.clone()
    source = torch.full((T, M), BODY, dtype=torch.uint8)
    for m in range(M):
        if not bool(torch.isfinite(body[:, m]).all()):
            source[:, m] = NONE
            continue
        ok = [counted[t][m] for t in range(T)]
        raw = {t: X[t, m] - body[t, m] for t in range(T) if ok[t]}
        offset = {}
        for t in raw:
            if smooth > 0:
                w = {s: math.exp(-0.5 * ((s - t) / smooth) ** 2) for s in raw if abs(s - t) <= math.ceil(3 * smooth)}
                offset[t] = sum(w[s] * raw[s] for s in w) / sum(w.values())
            else:
                offset[t] = raw[t]
        for t in range(T):
            if ok[t]:
                out[t, m], source[t, m] = body[t, m] + offset[t], MEASURED
                continue
            before = [s for s in offset if s < t]
            after = [s for s in offset if s > t]
            p, n = (max(before) if before else None), (min(after) if after else None)
            if p is not None and n is not None and n - p <= gap + 1:  # a short gap: interpolated
                a = (t - p) / (n - p)
                carried, weight = (1 - a) * offset[p] + a * offset[n], 1.0
            else:  # a long gap or an end: each side's offset fading over `gap` frames
                wp = max(0.0, 1 - (t - p) / gap) if p is not None else 0.0
                wn = max(0.0, 1 - (n - t) / gap) if n is not None else 0.0
                carried = (wp * offset[p] if wp else 0) + (wn * offset[n] if wn else 0)
                weight = wp + wn
            out[t, m] = body[t, m] + carried
            source[t, m] = FILLED if weight > 0 else BODY
    return out, source


@pytest.mark.parametrize("smooth", [0.0, 1.5])
def test_measured_markers_follow_their_rules(smooth):
    gen = torch.Generator().manual_seed(3)
    T, M, gap = 60, 10, 6
    body = torch.cumsum(0.01 * torch.randn(T, M, 3, generator=gen, dtype=torch.float64), 0)
    skin = 0.02 * torch.sin(torch.linspace(0, 3, T, dtype=torch.float64))[:, None, None].expand(T, M, 3)
    X = body + skin + 0.002 * torch.randn(T, M, 3, generator=gen, dtype=torch.float64)
    views = torch.full((T, M), 3)
    X[10:14, 0] = math.nan  # marker 0: a short gap (bridged), a long one (faded from both sides), a trailing one
    X[20:40, 0] = math.nan
    X[55:, 0] = math.nan
    views[:8, 1] = 1  # marker 1: its first frames in one view only (a leading gap) ...
    X[30, 1] += 0.2  # ... and a detection of another marker 20 cm off, refused
    X[:, 2] = math.nan  # marker 2: never measured, the body's alone
    body[:, 3] = math.nan  # marker 3: not tracked
    X[44:44 + gap, 4] = math.nan  # marker 4: a gap of exactly `gap` frames, the longest bridged
    # markers 5 and 6, 4 cm apart on the body, their labels swapped on frames 20-29 (their neighbour 7 is right);
    # marker 8's triangulation on frame 5 is 2 cm off but nearer marker 9's body marker, 1 cm from its own
    body[:, 6] = body[:, 5] + torch.tensor([0.04, 0.0, 0.0], dtype=torch.float64)
    body[:, 7] = body[:, 5] + torch.tensor([0.0, 0.08, 0.0], dtype=torch.float64)
    X[:, 5:8] = body[:, 5:8] + skin[:, :3] + 0.002 * torch.randn(T, 3, 3, generator=gen, dtype=torch.float64)
    X[20:30, 5], X[20:30, 6] = X[20:30, 6].clone(), X[20:30, 5].clone()
    body[:, 9] = body[:, 8] + torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64)
    X[5, 8] = body[5, 8] + torch.tensor([0.0, 0.0, 0.02], dtype=torch.float64)
    got, source = measured_markers(body, X, views, min_views=2, within_m=0.05, gap=gap, smooth=smooth,
                                   neighbour_m=0.25, agree_m=0.03)
    want, want_source = _reference(body, X, views, 2, 0.05, gap, smooth, 0.25, 0.03)
    torch.testing.assert_close(got, want, equal_nan=True)
    assert torch.equal(source, want_source)
    # the rules' plain consequences, whatever the reference
    assert source[30, 1] == FILLED and source[22, 0] == FILLED and source[30, 0] == BODY
    assert (source[:, 2] == BODY).all() and (source[:, 3] == NONE).all() and source[15, 4] == MEASURED
    assert (source[20:30, 5:7] != MEASURED).all() and (source[:20, 5:8] == MEASURED).all()
    assert source[5, 8] != MEASURED and source[6, 8] == MEASURED
    if smooth == 0:
        torch.testing.assert_close(got[15, 4], X[15, 4])  # a measured marker is its triangulation


def test_smoothing_the_offsets_averages_out_pixel_noise():
    """Noisy triangulations of a marker whose skin offset drifts slowly: the smoothed markers lie nearer the true
    ones than the raw triangulations, and nearer than the rigid body's."""
    gen = torch.Generator().manual_seed(0)
    T = 300
    body = torch.zeros(T, 1, 3, dtype=torch.float64)
    truth = body + 0.015 * torch.sin(torch.linspace(0, 2 * math.pi, T, dtype=torch.float64))[:, None, None]
    X = truth + 0.004 * torch.randn(T, 1, 3, generator=gen, dtype=torch.float64)
    views = torch.full((T, 1), 2)
    err = {s: float((measured_markers(body, X, views, smooth=s)[0] - truth).norm(dim=-1).mean()) for s in (0, 1, 3)}
    body_err = float((body - truth).norm(dim=-1).mean())
    assert err[3] < err[1] < err[0] < body_err, (err, body_err)
