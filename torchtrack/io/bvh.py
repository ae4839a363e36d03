"""BVH (Biovision Hierarchy) motion files: parser, writer, forward kinematics, conversion to the world frame.

BVH semantics used here (the common reading of the format, as CMU/3ds Max/Blender files use it):

* ``OFFSET`` is the joint's origin in its parent's frame; ``End Site`` blocks become joints named
  ``<parent>_end`` without channels (``is_end_site``), so segment tips such as the head top have positions.
* ``CHANNELS`` lists, per joint, the motion columns it owns, in file order. Rotation channels are Euler angles in
  **degrees** composed in the listed order as *intrinsic* rotations: ``Zrotation Yrotation Xrotation`` means
  ``R_local = Rz @ Ry @ Rx``. Position channels add to the offset:
  ``t_local = OFFSET + (Xposition, Yposition, Zposition)`` (CMU roots have a zero offset, so the convention of
  adding vs replacing the offset does not matter for them).
* FK: ``R_j = R_parent @ R_local_j``, ``p_j = p_parent + R_parent @ t_local_j``; a root's parent is the identity.

Positions stay in the file's own units and axes (BVH is Y up). :func:`bvh_to_world` converts to torchtrack's
world (Z up, metres) with ``(x_w, y_w, z_w) = (z_bvh, x_bvh, y_bvh)``: a cyclic, hence right-handed, axis
permutation under which a CMU subject facing +Z_bvh with its left side at +X_bvh faces +X with its left at +Y,
as the body frame of :mod:`torchtrack.conventions`.

The FK is hand-written (pytorch-kinematics reads URDF, not BVH's per-joint Euler orders); it is vectorised over
frames and loops over tree depth only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError
from torchtrack.io.atomic import write_text_atomic

#: One CMU length unit in metres (the CMU skeletons are scaled by 0.45 from inches: 2.54 / 0.45 cm).
CMU_UNIT_M: float = 0.0254 / 0.45
#: World axis k takes BVH axis BVH_TO_WORLD_AXES[k]: (x_w, y_w, z_w) = (z_bvh, x_bvh, y_bvh).
BVH_TO_WORLD_AXES: tuple[int, int, int] = (2, 0, 1)

_CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNEL_LOOKUP = {c.lower(): c for c in _CHANNELS}


@dataclass
class BVH:
    """A parsed BVH file. J counts joints including end sites; T frames; N motion columns.

    Attributes:
        joint_names: (J,) names, in file order (a parent always precedes its children).
        parents: (J,) int64 parent index, -1 for a root.
        offsets: (J, 3) float64 OFFSET in the parent's frame, file units.
        channels: (J,) tuple of channel names per joint (empty for end sites), e.g. ``("Zrotation", ...)``.
        channel_start: (J,) int64 first motion column of each joint's channels.
        is_end_site: (J,) bool.
        motion: (T, N) float64 channel values (degrees for rotations, file units for positions).
        frame_time: seconds per frame.
        source: file name (or ``"<string>"``) for messages.
    """

    joint_names: list[str]
    parents: np.ndarray
    offsets: np.ndarray
    channels: list[tuple[str, ...]]
    channel_start: np.ndarray
    is_end_site: np.ndarray
    motion: np.ndarray
    frame_time: float
    source: str = "<string>"

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def num_channels(self) -> int:
        return int(self.motion.shape[1])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def index(self, name: str) -> int:
        """Index of joint ``name``; ``KeyError`` listing the names if absent."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise KeyError(f"{self.source}: no joint {name!r}; joints: {self.joint_names}") from None


# ----------------------------------------------------------------------------------------------- parsing


class _Tokens:
    """Whitespace tokens of the HIERARCHY section with 1-based line numbers."""

    def __init__(self, lines: list[str], source: str) -> None:
        self.items = [(tok, n + 1) for n, line in enumerate(lines) for tok in line.split()]
        self.pos = 0
        self.source = source

    def error(self, msg: str, line: int | None = None) -> InputError:
        if line is None:
            line = self.items[min(self.pos, len(self.items) - 1)][1] if self.items else 1
        return InputError(f"{self.source}, line {line}: {msg}")

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            raise self.error(f"unexpected end of file, expected {what}")
        self.pos += 1
        return self.items[self.pos - 1]

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok != word:
            raise self.error(f"expected {word!r}, got {tok!r}", line)
        return line

    def rest_of_line(self, line: int) -> str:
        """The remaining tokens on ``line`` (a joint name may contain spaces), without a trailing '{'."""
        words = []
        while self.pos < len(self.items) and self.items[self.pos][1] == line and self.items[self.pos][0] != "{":
            words.append(self.items[self.pos][0])
            self.pos += 1
        return " ".join(words)

    def floats(self, n: int, what: str) -> list[float]:
        out = []
        for _ in range(n):
            tok, line = self.next(what)
            try:
                out.append(float(tok))
            except ValueError:
                raise self.error(f"{what}: expected a number, got {tok!r}", line) from None
        return out


class _Builder:
    def __init__(self) -> None:
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[list[float]] = []
        self.channels: list[tuple[str, ...]] = []
        self.end: list[bool] = []

    def add(self, name: str, parent: int, offset: list[float], channels: tuple[str, ...], end: bool) -> int:
        self.names.append(name)
        self.parents.append(parent)
        self.offsets.append(offset)
        self.channels.append(channels)
        self.end.append(end)
        return len(self.names) - 1


def _parse_channels(tk: _Tokens) -> tuple[str, ...]:
    line = tk.expect("CHANNELS")
    tok, _ = tk.next("the channel count")
    if not tok.isdigit():
        raise tk.error(f"CHANNELS: expected a channel count, got {tok!r}", line)
    n = int(tok)
    on_line = sum(1 for _, ln in tk.items[tk.pos:] if ln == line)
    if on_line > n:
        raise tk.error(f"CHANNELS declares {n} channels but the line lists {on_line}", line)
    out: list[str] = []
    for _ in range(n):
        name, ln = tk.next("a channel name")
        canon = _CHANNEL_LOOKUP.get(name.lower())
        if canon is None and ln != line and name in ("JOINT", "End", "}"):
            raise tk.error(f"CHANNELS declares {n} channels but lists {len(out)}", line)
        if canon is None:
            raise tk.error(f"unknown channel name {name!r} (known: {', '.join(_CHANNELS)})", ln)
        if canon in out:
            raise tk.error(f"channel {canon} listed twice", ln)
        out.append(canon)
    return tuple(out)


def _parse_joint(tk: _Tokens, b: _Builder, name: str, parent: int, line: int) -> None:
    """Parse ``{ OFFSET .. CHANNELS .. (JOINT ..| End Site ..)* }`` after a ROOT/JOINT name on ``line``."""
    if name in b.names:
        raise tk.error(f"joint name {name!r} used twice", line)
    tk.expect("{")
    tk.expect("OFFSET")
    offset = tk.floats(3, f"OFFSET of {name}")
    channels = _parse_channels(tk)
    me = b.add(name, parent, offset, channels, False)
    while True:
        tok, line = tk.next("JOINT, End Site or '}'")
        if tok == "}":
            return
        if tok == "JOINT":
            child = tk.rest_of_line(line)
            if not child:
                raise tk.error("JOINT without a name", line)
            _parse_joint(tk, b, child, me, line)
        elif tok == "End":
            tk.expect("Site")
            if f"{name}_end" in b.names:
                raise tk.error(f"End Site name {name}_end is already a joint name", line)
            tk.expect("{")
            tk.expect("OFFSET")
            end_offset = tk.floats(3, f"End Site OFFSET of {name}")
            tk.expect("}")
            b.add(f"{name}_end", me, end_offset, (), True)
        else:
            raise tk.error(f"unexpected {tok!r} in joint {name!r} (expected JOINT, End Site or '}}')", line)


def _parse_header_value(line: str, key: str, source: str, number: int) -> str:
    if not line.strip().startswith(key):
        raise InputError(f"{source}, line {number}: expected '{key} ...', got {line.strip()[:40]!r}")
    return line.split(":", 1)[1].strip() if ":" in line else line.strip()[len(key):].strip()


def _parse_motion(lines: list[str], first: int, n_channels: int, source: str) -> tuple[np.ndarray, float]:
    """Parse ``Frames:``, ``Frame Time:`` and the data rows starting at 0-based line ``first``."""
    rows = [(n, ln) for n, ln in enumerate(lines[first:], start=first) if ln.strip()]
    if len(rows) < 2:
        raise InputError(f"{source}, line {len(lines)}: MOTION needs 'Frames:' and 'Frame Time:' lines")
    (n_f, frames_line), (n_t, time_line) = rows[0], rows[1]
    try:
        num_frames = int(_parse_header_value(frames_line, "Frames", source, n_f + 1))
        frame_time = float(_parse_header_value(time_line, "Frame Time", source, n_t + 1))
    except ValueError as e:
        raise InputError(f"{source}, line {n_f + 1}-{n_t + 1}: bad Frames / Frame Time value ({e})") from None
    if num_frames < 0 or not frame_time > 0:
        raise InputError(f"{source}, line {n_f + 1}: need Frames >= 0 and Frame Time > 0, got {num_frames}, "
                         f"{frame_time}")
    data = rows[2:]
    if len(data) != num_frames:
        last = data[-1][0] + 1 if data else n_t + 1
        kind = "truncated motion" if len(data) < num_frames else "more motion rows than declared"
        raise InputError(f"{source}, line {last}: {kind}: 'Frames: {num_frames}' but {len(data)} data rows")
    motion = np.empty((num_frames, n_channels), np.float64)  # (T, N)
    for t, (n, ln) in enumerate(data):
        values = ln.split()
        if len(values) != n_channels:
            raise InputError(f"{source}, line {n + 1}: frame {t} has {len(values)} values, the hierarchy declares "
                             f"{n_channels} channels")
        try:
            motion[t] = [float(v) for v in values]
        except ValueError:
            raise InputError(f"{source}, line {n + 1}: frame {t} holds a value that is not a number") from None
    return motion, frame_time


def parse_bvh(text: str, source: str = "<string>") -> BVH:
    """Parse BVH text. ``source`` names the file in error messages.

    Raises:
        InputError: naming ``source`` and the line: bad structure, unknown channel, channel count mismatch,
            truncated motion, non-numeric values.
    """
    lines = text.splitlines()
    motion_at = next((n for n, ln in enumerate(lines) if ln.strip() == "MOTION"), None)
    if motion_at is None:
        raise InputError(f"{source}, line {len(lines)}: no MOTION section")
    tk = _Tokens(lines[:motion_at], source)
    tk.expect("HIERARCHY")
    b = _Builder()
    while tk.pos < len(tk.items):
        tok, line = tk.next("ROOT")
        if tok != "ROOT":
            raise tk.error(f"expected ROOT, got {tok!r}", line)
        name = tk.rest_of_line(line)
        if not name:
            raise tk.error("ROOT without a name", line)
        _parse_joint(tk, b, name, -1, line)
    if not b.names:
        raise InputError(f"{source}, line {motion_at + 1}: the hierarchy has no ROOT")
    sizes = np.array([len(c) for c in b.channels], np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    motion, frame_time = _parse_motion(lines, motion_at + 1, int(sizes.sum()), source)
    return BVH(joint_names=b.names, parents=np.array(b.parents, np.int64),
               offsets=np.array(b.offsets, np.float64).reshape(-1, 3), channels=b.channels, channel_start=starts,
               is_end_site=np.array(b.end, bool), motion=motion, frame_time=frame_time, source=source)


def read_bvh(path: str | Path) -> BVH:
    """Read a BVH file; see :func:`parse_bvh`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"BVH file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not a text file ({e})") from None
    return parse_bvh(text, source=str(path))


def format_bvh(bvh: BVH, precision: int = 6) -> str:
    """BVH text of ``bvh`` (tabs, values with ``precision`` decimals)."""
    children: dict[int, list[int]] = {}
    for j, p in enumerate(bvh.parents):
        children.setdefault(int(p), []).append(j)
    out = ["HIERARCHY"]

    def vec(v) -> str:
        return " ".join(f"{x:.{precision}f}" for x in v)

    def emit(j: int, depth: int) -> None:
        pad = "\t" * depth
        if bvh.is_end_site[j]:
            out.extend([f"{pad}End Site", f"{pad}{{", f"{pad}\tOFFSET {vec(bvh.offsets[j])}", f"{pad}}}"])
            return
        kind = "ROOT" if bvh.parents[j] < 0 else "JOINT"
        out.extend([f"{pad}{kind} {bvh.joint_names[j]}", f"{pad}{{", f"{pad}\tOFFSET {vec(bvh.offsets[j])}",
                    f"{pad}\tCHANNELS {len(bvh.channels[j])} {' '.join(bvh.channels[j])}".rstrip()])
        for c in children.get(j, []):
            emit(c, depth + 1)
        out.append(f"{pad}}}")

    for root in children.get(-1, []):
        emit(root, 0)
    out.extend(["MOTION", f"Frames: {bvh.num_frames}", f"Frame Time: {bvh.frame_time:.7f}"])
    out.extend(vec(row) for row in bvh.motion)
    return "\n".join(out) + "\n"


def write_bvh(path: str | Path, bvh: BVH, precision: int = 6) -> None:
    """Write ``bvh`` to ``path`` atomically; :func:`read_bvh` reads it back to within ``10**-precision``."""
    write_text_atomic(path, format_bvh(bvh, precision))


# ----------------------------------------------------------------------------------------------- kinematics


def _axis_rotations(axis: int, angle_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices about coordinate ``axis`` (0 x, 1 y, 2 z): (...,) -> (..., 3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    R = np.zeros(angle_rad.shape + (3, 3))
    i, k = [(1, 2), (2, 0), (0, 1)][axis]  # the plane rotated, in right-handed order
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., k, k] = c
    R[..., i, k] = -s
    R[..., k, i] = s
    return R


def bvh_local_transforms(bvh: BVH, frames=None) -> tuple[np.ndarray, np.ndarray]:
    """Per-joint local rotations and translations.

    Args:
        frames: None (all), a slice, or (T,) indices into the motion.

    Returns:
        R_parent_joint: (T, J, 3, 3); t_parent_joint: (T, J, 3) file units (offset + position channels).
    """
    motion = bvh.motion if frames is None else bvh.motion[frames]  # (T, N)
    T, J = motion.shape[0], bvh.num_joints
    R = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()  # (T, J, 3, 3)
    t = np.broadcast_to(bvh.offsets, (T, J, 3)).copy()  # (T, J, 3)
    # slots[k]: (joint, column, axis) of each joint's k-th rotation channel, to compose in file order
    slots: list[list[tuple[int, int, int]]] = [[], [], []]
    for j, chans in enumerate(bvh.channels):
        k = 0
        for n, ch in enumerate(chans):
            col, axis = int(bvh.channel_start[j]) + n, "XYZ".index(ch[0])
            if ch.endswith("position"):
                t[:, j, axis] += motion[:, col]
            else:
                slots[k].append((j, col, axis))
                k += 1
    for slot in slots:  # at most 3 slots x 3 axes, each vectorised over frames and joints
        for axis in range(3):
            sel = [(j, col) for j, col, a in slot if a == axis]
            if sel:
                js, cols = (np.array(v) for v in zip(*sel))
                R[:, js] = R[:, js] @ _axis_rotations(axis, np.deg2rad(motion[:, cols]))
    return R, t


def bvh_forward_kinematics(bvh: BVH, frames=None) -> np.ndarray:
    """Joint positions of ``bvh`` (see the module docstring for the semantics).

    Args:
        bvh: a parsed file.
        frames: None (all), a slice, or (T,) indices into the motion.

    Returns:
        positions: (T, J, 3) float64, in the file's units and axes (end sites included).
    """
    R_local, t_local = bvh_local_transforms(bvh, frames)  # (T, J, 3, 3), (T, J, 3)
    parents = bvh.parents
    depth = np.zeros(bvh.num_joints, np.int64)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1  # parents precede children in file order
    R_world = np.empty_like(R_local)  # (T, J, 3, 3)
    pos = np.empty_like(t_local)  # (T, J, 3)
    for d in range(int(depth.max()) + 1):
        js = np.nonzero(depth == d)[0]
        if d == 0:
            R_world[:, js], pos[:, js] = R_local[:, js], t_local[:, js]
            continue
        ps = parents[js]
        R_world[:, js] = R_world[:, ps] @ R_local[:, js]
        pos[:, js] = pos[:, ps] + (R_world[:, ps] @ t_local[:, js, :, None])[..., 0]
    return pos


def bvh_to_world(positions, *, unit_to_m: float):
    """BVH positions (Y up, file units) to torchtrack's world (Z up, metres).

    ``(x_w, y_w, z_w) = unit_to_m * (z_bvh, x_bvh, y_bvh)``; use :data:`CMU_UNIT_M` for CMU files.

    Args:
        positions: (..., 3) numpy array or torch tensor.

    Returns:
        (..., 3) of the same type.
    """
    if positions.shape[-1] != 3:
        raise InputError(f"bvh_to_world: expected (..., 3) positions, got shape {tuple(positions.shape)}")
    return positions[..., list(BVH_TO_WORLD_AXES)] * unit_to_m
