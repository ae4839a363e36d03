"""TRC marker files (OpenSim / Motion Analysis / Pose2Sim): reader and conversion to the world frame.

Layout: line 1 ``PathFileType ...``; line 2 the header keys (DataRate, CameraRate, NumFrames, NumMarkers,
Units, ...), line 3 their values; line 4 ``Frame#  Time  name1 <tab><tab> name2 ...``; line 5 the
``X1 Y1 Z1 ...`` labels; data from line 6 (a blank line may come first). Rows may be shorter than the header
says, or hold empty fields, where markers are missing (real files do both): those values become NaN.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError, check_file

_UNIT_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2}


@dataclass
class TRC:
    """A TRC file. T frames, M markers.

    Attributes:
        marker_names: (M,) names as written (subject prefixes kept).
        frame_numbers: (T,) int64; times: (T,) float64 seconds.
        positions: (T, M, 3) float64 in the file's units and axes; NaN where missing.
        rate_hz: DataRate; units: the Units field ("m", "mm", ...).
    """

    marker_names: list[str]
    frame_numbers: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    rate_hz: float
    units: str
    source: str

    def positions_m(self) -> np.ndarray:
        """(T, M, 3) positions in metres (file axes)."""
        if self.units.lower() not in _UNIT_TO_M:
            raise InputError(f"{self.source}: unknown Units {self.units!r}; expected one of {sorted(_UNIT_TO_M)}")
        return self.positions * _UNIT_TO_M[self.units.lower()]


def read_trc(path: str | Path) -> TRC:
    """Read a TRC file; malformed headers or values give InputError naming the file and line."""
    p = check_file(path, "TRC file")
    try:
        lines = p.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc})") from None
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise InputError(f"{p}: not a TRC file (line 1 should start with 'PathFileType')")
    header = dict(zip(lines[1].split("\t"), lines[2].split("\t")))
    try:
        rate = float(header["DataRate"])
        num_markers = int(header["NumMarkers"])
        units = header.get("Units", "m").strip()
    except (KeyError, ValueError) as exc:
        raise InputError(f"{p}: line 2-3: header field missing or not a number ({exc})") from None
    names = [n.strip() for n in lines[3].split("\t")[2:] if n.strip()]
    frames, times, rows = [], [], []
    for number, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        fields = [f.strip() for f in line.split("\t")]
        while fields and not fields[-1]:
            fields.pop()
        try:
            frames.append(int(float(fields[0])))
            times.append(float(fields[1]))
            rows.append([float(v) if v else np.nan for v in fields[2:]])
        except (ValueError, IndexError) as exc:
            raise InputError(f"{p}: line {number}: not a frame number, time and coordinates ({exc})") from None
    if not rows:
        raise InputError(f"{p}: no data rows")
    count = max(num_markers, -(-max(len(r) for r in rows) // 3))
    if count != num_markers or len(names) != count:
        # Real files disagree (BTK's Gait.trc: NumMarkers 66, 33 names, rows of up to 68 markers' fields)
        warnings.warn(f"{p}: header says NumMarkers = {num_markers}, line 4 names {len(names)}, the widest row "
                      f"holds {count}; reading {count} markers, unnamed ones as marker_<i>", stacklevel=2)
    names = (names + [f"marker_{i}" for i in range(len(names), count)])[:count]
    rows = [r + [np.nan] * (3 * count - len(r)) for r in rows]
    pos = np.asarray(rows, dtype=np.float64).reshape(len(rows), count, 3)
    return TRC(names, np.asarray(frames, np.int64), np.asarray(times), pos, rate, units, str(p))


def y_up_to_world(xyz: np.ndarray) -> np.ndarray:
    """(..., 3) Y-up coordinates (TRC/OpenSim convention) to the Z-up world: (x, y, z) = (Z', X', Y')."""
    return np.ascontiguousarray(xyz[..., [2, 0, 1]])
