"""BVH (Biovision hierarchy) parser -> :class:`SourceMotion`.

Supported: one ROOT, any number of JOINTs (<= MAX_JOINTS), End Sites, 0-6 channels per joint
in any order (``Xposition Yposition Zposition`` and ``Xrotation Yrotation Zrotation``, angles in
degrees, the first listed rotation outermost: ``Zrotation Yrotation Xrotation`` -> Rz Ry Rx),
one frame per line. Position channels set the root position (they replace the OFFSET, as
Blender's importer does); position channels of other joints are validated and ignored, since
retargeting transfers orientations. Rest orientations are the identity (offset pose).

Units: ``unit_scale`` metres per file unit, or None to infer it from the rest skeleton's height
(see :func:`infer_unit_scale`). BVH is Y-up unless told otherwise (``up_axis``).
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from inference.motion.skeleton import (
    CMU_UNIT_M,
    DEFAULT_MAX_FRAMES,
    MAX_JOINTS,
    MotionFormatError,
    SourceMotion,
    euler_to_matrix,
)

_CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
_CHANNEL_LOOKUP = {c.lower(): c for c in _CHANNELS}

# (lower bound of the rest skeleton's height span in file units, metres per unit, unit name)
_UNIT_TABLE = (
    (0.5, 1.0, "metres"),
    (3.0, None, None),
    (12.0, CMU_UNIT_M, "CMU units (1/0.45 inch)"),
    (45.0, 0.0254, "inches"),
    (100.0, 0.01, "centimetres"),
    (300.0, None, None),
)


# Unit names a client may give (service schema BvhMotion.units) -> metres per unit; None infers.
BVH_UNITS: dict[str, float | None] = {
    "auto": None,
    "metres": 1.0,
    "centimetres": 0.01,
    "inches": 0.0254,
    "cmu": CMU_UNIT_M,
}


class _Tokens:
    """Whitespace tokens with their 1-based line numbers, for error messages."""

    def __init__(self, lines: list[str], start: int, stop: int):
        self.items: list[tuple[str, int]] = []
        for i in range(start, stop):
            self.items.extend((tok, i + 1) for tok in lines[i].split())
        self.pos = 0

    def peek(self) -> tuple[str | None, int]:
        if self.pos < len(self.items):
            return self.items[self.pos]
        last = self.items[-1][1] if self.items else 1
        return None, last

    def next(self, expected: str) -> tuple[str, int]:
        tok, line = self.peek()
        if tok is None:
            raise MotionFormatError(f"BVH line {line}: unexpected end of HIERARCHY, expected {expected}")
        self.pos += 1
        return tok, line

    def keyword(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok.upper() != word.upper():
            raise MotionFormatError(f"BVH line {line}: expected {word!r}, got {tok!r}")
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        return _to_float(tok, line, what)


def _to_float(tok: str, line: int, what: str) -> float:
    try:
        value = float(tok)
    except ValueError:
        raise MotionFormatError(f"BVH line {line}: expected a number ({what}), got {tok!r}") from None
    if not math.isfinite(value):
        raise MotionFormatError(f"BVH line {line}: {what} is not finite ({tok!r})")
    return value


def infer_unit_scale(span: float) -> float:
    """Metres per file unit from the rest skeleton's vertical span (file units).

    A human is 1-2 m tall: a span in [0.5, 3) is metres, [12, 45) CMU units
    (0.05644 m), [45, 100) inches, [100, 300) centimetres; anything else is refused.
    """
    scale = None
    for lower, s, _ in _UNIT_TABLE:
        if span >= lower:
            scale = s
    if scale is None or span < _UNIT_TABLE[0][0]:
        raise MotionFormatError(
            f"cannot infer BVH units from a rest skeleton {span:.3g} units tall; pass unit_scale"
        )
    return scale


_HEADER = re.compile(r"^\s*MOTION\s*\n\s*Frames:\s*(\d+)\s*\n\s*Frame\s+Time:\s*([0-9.eE+-]+)", re.MULTILINE)


def bvh_frames(text: str) -> tuple[int, float] | None:
    """(frames, fps) from a BVH text's MOTION header alone (a regex scan: no parsing), or None
    where it has no readable header (``parse_bvh`` then says what is wrong)."""
    m = _HEADER.search(text)
    if m is None:
        return None
    try:
        frames, frame_time = int(m.group(1)), float(m.group(2))
    except ValueError:
        return None
    return (frames, 1.0 / frame_time) if frame_time > 0 else None


def parse_bvh(
    text: str,
    *,
    unit_scale: float | None = None,
    up_axis: str = "y",
    max_frames: int = DEFAULT_MAX_FRAMES,
) -> SourceMotion:
    """Parse BVH text into a :class:`SourceMotion` (metres, source axes).

    text       : the whole file
    unit_scale : metres per file unit; None infers it (:func:`infer_unit_scale`)
    up_axis    : "y" (BVH default) or "z"
    max_frames : refuse files declaring more frames (MotionFormatError)
    Raises MotionFormatError with the line number on malformed input.
    """
    if up_axis not in ("y", "z"):
        raise ValueError(f"up_axis must be 'y' or 'z', got {up_axis!r}")
    lines = text.splitlines()
    motion_line = next((i for i, ln in enumerate(lines) if ln.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise MotionFormatError("BVH: no MOTION section (truncated or not a BVH file)")
    toks = _Tokens(lines, 0, motion_line)
    toks.keyword("HIERARCHY")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_sites: dict[int, list[float]] = {}

    # Iterative recursive-descent over JOINT blocks: stack of open joint indices.
    tok, line = toks.next("'ROOT'")
    if tok.upper() != "ROOT":
        raise MotionFormatError(f"BVH line {line}: expected 'ROOT', got {tok!r}")
    stack: list[int] = []
    pending_parent = -1
    while True:
        # At this point a ROOT/JOINT keyword has been consumed: read name { OFFSET CHANNELS
        name, line = toks.next("a joint name")
        if name in ("{", "}"):
            raise MotionFormatError(f"BVH line {line}: expected a joint name, got {name!r}")
        if len(names) >= MAX_JOINTS:
            raise MotionFormatError(f"BVH line {line}: more than {MAX_JOINTS} joints")
        j = len(names)
        names.append(name)
        parents.append(pending_parent)
        toks.keyword("{")
        toks.keyword("OFFSET")
        offsets.append([toks.number("OFFSET x"), toks.number("OFFSET y"), toks.number("OFFSET z")])
        toks.keyword("CHANNELS")
        tok, line = toks.next("a channel count")
        if not tok.isdigit() or int(tok) > 6:
            raise MotionFormatError(f"BVH line {line}: expected a channel count 0-6, got {tok!r}")
        chans = []
        for _ in range(int(tok)):
            c, line = toks.next("a channel name")
            if c.lower() not in _CHANNEL_LOOKUP:
                raise MotionFormatError(
                    f"BVH line {line}: joint {name!r} declares {tok} channels; expected a channel "
                    f"name (one of {', '.join(_CHANNELS)}), got {c!r}"
                )
            c = _CHANNEL_LOOKUP[c.lower()]
            if c in chans:
                raise MotionFormatError(f"BVH line {line}: channel {c} repeated for joint {name!r}")
            chans.append(c)
        channels.append(chans)
        stack.append(j)
        # Children, End Sites and closing braces until we find the next JOINT (or finish).
        while True:
            tok, line = toks.next("'JOINT', 'End Site' or '}'")
            up = tok.upper()
            if up == "JOINT":
                pending_parent = stack[-1]
                break
            if up == "END":
                toks.keyword("Site")
                toks.keyword("{")
                toks.keyword("OFFSET")
                site = [toks.number("End Site x"), toks.number("End Site y"), toks.number("End Site z")]
                toks.keyword("}")
                end_sites.setdefault(stack[-1], site)
                continue
            if tok == "}":
                stack.pop()
                if not stack:
                    break
                continue
            raise MotionFormatError(f"BVH line {line}: expected 'JOINT', 'End Site' or '}}', got {tok!r}")
        if not stack:
            break
    tok, line = toks.peek()
    if tok is not None:
        raise MotionFormatError(f"BVH line {line}: unexpected {tok!r} after the ROOT block (one ROOT only)")

    # MOTION header.
    header = _Tokens(lines, motion_line + 1, min(len(lines), motion_line + 3))
    header.keyword("Frames:")
    tok, line = header.next("the frame count")
    if not tok.isdigit():
        raise MotionFormatError(f"BVH line {line}: expected a frame count, got {tok!r}")
    num_frames = int(tok)
    if num_frames < 1:
        raise MotionFormatError(f"BVH line {line}: the clip has no frames")
    if num_frames > max_frames:
        raise MotionFormatError(f"BVH line {line}: {num_frames} frames, more than the limit {max_frames}")
    header.keyword("Frame")
    header.keyword("Time:")
    frame_time = header.number("the frame time")
    if not 1e-4 <= frame_time <= 10.0:
        raise MotionFormatError(f"BVH line {line + 1}: frame time {frame_time} s out of range")

    # Frame lines: exactly one frame per non-empty line, sum(channels) values each. Check the
    # declared count against the lines there are before allocating anything for it.
    available = len(lines) - (motion_line + 3)
    if num_frames > available:
        raise MotionFormatError(f"BVH: truncated, {num_frames} frames declared but only {max(available, 0)} lines follow")
    width = sum(len(c) for c in channels)
    data = np.empty((num_frames, width))
    t = 0
    for i in range(motion_line + 3, len(lines)):
        parts = lines[i].split()
        if not parts:
            continue
        if t >= num_frames:
            raise MotionFormatError(f"BVH line {i + 1}: more frame lines than the declared {num_frames} frames")
        if len(parts) != width:
            raise MotionFormatError(
                f"BVH line {i + 1}: frame {t + 1} has {len(parts)} values, expected {width} (sum of CHANNELS)"
            )
        try:
            data[t] = np.array(parts, dtype=np.float64)
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            raise MotionFormatError(f"BVH line {i + 1}: expected a number, got {bad!r}") from None
        t += 1
    if t < num_frames:
        raise MotionFormatError(f"BVH: truncated, {t} frame lines for the declared {num_frames} frames")
    if not np.all(np.isfinite(data)):
        raise MotionFormatError("BVH: non-finite channel value in the MOTION data")

    return _build(names, parents, offsets, channels, end_sites, data, 1.0 / frame_time, unit_scale, up_axis)


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _build(names, parents, offsets, channels, end_sites, data, fps, unit_scale, up_axis) -> SourceMotion:
    J, T = len(names), data.shape[0]
    parents_arr = np.asarray(parents, dtype=np.int64)
    offsets_arr = np.asarray(offsets, dtype=np.float64)
    heads = np.zeros((J, 3))
    for j in range(J):
        heads[j] = offsets_arr[j] if parents[j] < 0 else heads[parents[j]] + offsets_arr[j]
    tails = heads.copy()
    for j in range(J):
        children = np.flatnonzero(parents_arr == j)
        if j in end_sites:
            tails[j] = heads[j] + np.asarray(end_sites[j])
        elif len(children) == 1:
            tails[j] = heads[children[0]]
    up = {"y": 1, "z": 2}[up_axis]
    if unit_scale is None:
        span = max(heads[:, up].max(), tails[:, up].max()) - min(heads[:, up].min(), tails[:, up].min())
        unit_scale = infer_unit_scale(span)
    if not (unit_scale > 0 and math.isfinite(unit_scale)):
        raise ValueError(f"unit_scale must be a positive number of metres per unit, got {unit_scale}")

    local = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    root_pos = np.broadcast_to(offsets_arr[0], (T, 3)).copy()
    col = 0
    for j in range(J):  # loop over joints, vectorised over frames
        chans = channels[j]
        values = data[:, col : col + len(chans)]
        col += len(chans)
        rot_idx = [k for k, c in enumerate(chans) if c.endswith("rotation")]
        if rot_idx:
            axes = "".join(chans[k][0] for k in rot_idx)
            local[:, j] = euler_to_matrix(np.deg2rad(values[:, rot_idx]), axes)
        if j == 0:
            for k, c in enumerate(chans):
                if c.endswith("position"):
                    root_pos[:, "XYZ".index(c[0])] = values[:, k]
    world = np.empty_like(local)
    for j in range(J):
        world[:, j] = local[:, j] if parents[j] < 0 else world[:, parents[j]] @ local[:, j]
    return SourceMotion(
        names=tuple(names),
        parents=parents_arr,
        rest_heads=heads * unit_scale,
        rest_tails=tails * unit_scale,
        rest_rotations=np.broadcast_to(np.eye(3), (J, 3, 3)).copy(),
        world_rotations=world,
        root_positions=root_pos * unit_scale,
        fps=float(fps),
        up_axis=up_axis,
    )


def load_bvh(path: str | Path, **kwargs) -> SourceMotion:
    """Read and parse a BVH file (see :func:`parse_bvh` for the keyword arguments)."""
    return parse_bvh(Path(path).read_text(encoding="utf-8", errors="replace"), **kwargs)
