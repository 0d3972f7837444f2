"""Acclaim ASF (skeleton) + AMC (motion) parser -> :class:`SourceMotion` (CMU mocap format).

Conventions (Acclaim / CMU, column vectors):
- ASF ``:units length L`` is read the CMU way: one unit = 1/L inch (``length 0.45`` ->
  0.05644 m per unit) unless ``unit_scale`` is given; ``angle deg`` or ``rad``.
- Each bone has ``direction`` (unit vector, world axes at rest), ``length`` and
  ``axis a b c ORDER``: its rest frame C = R_ORDER[2] R_ORDER[1] R_ORDER[0] (the first listed
  axis is applied first, so ``XYZ`` -> Rz(c) Ry(b) Rx(a)).
- An AMC line gives the bone's dof values; M = product of the dof rotations with the first
  listed applied first (``rx ry rz`` -> Rz Ry Rx). The bone's world rotation change is
  dR = dR_parent C M C^-1, and its frame in the world is dR C (the Acclaim L = C^-1 M C B
  written for row vectors).
- The root: ``order`` lists its AMC channels (TX TY TZ RX RY RZ), ``axis``/``orientation`` its
  C, ``position`` its rest position; root position per frame = the TX TY TZ values.
- A bone's head is its parent's tail (the root's position for the root's children); a joint
  of the :class:`SourceMotion` is the bone starting there. Translation/length dofs of non-root
  bones (``tx ty tz l``) are validated and ignored. ASF/AMC is Y-up.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inference.motion.skeleton import (
    DEFAULT_MAX_FRAMES,
    MAX_JOINTS,
    MotionFormatError,
    SourceMotion,
    euler_to_matrix,
)

CMU_FPS = 120.0
_ROT_DOFS = ("rx", "ry", "rz")
_ALL_DOFS = ("rx", "ry", "rz", "tx", "ty", "tz", "l")


@dataclass(frozen=True)
class AsfSkeleton:
    """A parsed ASF skeleton (metres, radians, Y-up). Bone 0 is ``root``.

    names      : J bone names
    parents    : (J,) int64, -1 for the root, parents[j] < j
    heads      : (J, 3) float64 metres, rest head of each bone (parent's tail)
    tails      : (J, 3) float64 metres, rest tail (head + direction * length)
    axes       : (J, 3, 3) float64, rest frame C of each bone
    dofs       : J tuples of dof names in AMC order ("rx", "ty", ...; the root's from ``order``)
    angle_scale: radians per AMC angle unit
    """

    names: tuple[str, ...]
    parents: np.ndarray
    heads: np.ndarray
    tails: np.ndarray
    axes: np.ndarray
    dofs: tuple[tuple[str, ...], ...]
    unit_scale: float
    angle_scale: float


def _err(line: int, msg: str) -> MotionFormatError:
    return MotionFormatError(f"ASF line {line}: {msg}")


def _floats(parts: list[str], n: int, line: int, what: str, kind: str = "ASF") -> list[float]:
    if len(parts) != n:
        raise MotionFormatError(f"{kind} line {line}: {what} needs {n} numbers, got {len(parts)}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise MotionFormatError(f"{kind} line {line}: {what}: expected numbers, got {' '.join(parts)!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise MotionFormatError(f"{kind} line {line}: {what}: non-finite value")
    return values


def _axis_frame(angles: list[float], order: str, line: int, angle_scale: float) -> np.ndarray:
    order = order.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise _err(line, f"axis order must be a permutation of XYZ, got {order!r}")
    # First listed applied first: R = R_o[2] R_o[1] R_o[0].
    return euler_to_matrix(np.asarray(angles[::-1]) * angle_scale, order[::-1])


def parse_asf(text: str, *, unit_scale: float | None = None) -> AsfSkeleton:
    """Parse ASF text. unit_scale: metres per unit, None = 0.0254 / ``length`` (CMU)."""
    lines = text.splitlines()
    section = None
    length_unit, angle_scale = None, math.pi / 180.0
    root = {"order": None, "axis": "XYZ", "position": [0.0, 0.0, 0.0], "orientation": [0.0, 0.0, 0.0]}
    bones: list[dict] = []
    bone: dict | None = None
    hierarchy: list[tuple[int, list[str]]] = []
    for i, raw in enumerate(lines):
        n = i + 1
        parts = raw.split()
        if not parts or parts[0].startswith("#"):
            continue
        key = parts[0].lower()
        if key.startswith(":"):
            section = key
            continue
        if section == ":units":
            if key == "length":
                length_unit = _floats(parts[1:], 1, n, "length")[0]
                if length_unit <= 0:
                    raise _err(n, "length unit must be positive")
            elif key == "angle":
                if len(parts) != 2 or parts[1].lower() not in ("deg", "rad"):
                    raise _err(n, f"angle unit must be 'deg' or 'rad', got {' '.join(parts[1:])!r}")
                angle_scale = math.pi / 180.0 if parts[1].lower() == "deg" else 1.0
        elif section == ":root":
            if key == "order":
                root["order"] = [p.lower() for p in parts[1:]]
                root["order_line"] = n
            elif key == "axis":
                root["axis"] = parts[1] if len(parts) == 2 else ""
                root["axis_line"] = n
            elif key in ("position", "orientation"):
                root[key] = _floats(parts[1:], 3, n, key)
        elif section == ":bonedata":
            if key == "begin":
                if bone is not None:
                    raise _err(n, "'begin' inside a bone block (missing 'end')")
                if len(bones) + 1 >= MAX_JOINTS:
                    raise _err(n, f"more than {MAX_JOINTS} bones")
                bone = {"line": n, "dof": (), "axis": ([0.0, 0.0, 0.0], "XYZ", n)}
            elif key == "end":
                if bone is None:
                    raise _err(n, "'end' without 'begin'")
                for field in ("name", "direction", "length"):
                    if field not in bone:
                        raise _err(n, f"bone block starting at line {bone['line']} has no {field!r}")
                bones.append(bone)
                bone = None
            elif bone is None:
                raise _err(n, f"expected 'begin', got {parts[0]!r}")
            elif key == "name":
                if len(parts) != 2:
                    raise _err(n, "name needs one word")
                bone["name"] = parts[1]
            elif key == "direction":
                bone["direction"] = _floats(parts[1:], 3, n, "direction")
            elif key == "length":
                bone["length"] = _floats(parts[1:], 1, n, "length")[0]
            elif key == "axis":
                if len(parts) != 5:
                    raise _err(n, "axis needs three angles and an order (e.g. 'axis 0 0 20 XYZ')")
                bone["axis"] = (_floats(parts[1:4], 3, n, "axis"), parts[4], n)
            elif key == "dof":
                dofs = tuple(p.lower() for p in parts[1:])
                bad = [d for d in dofs if d not in _ALL_DOFS]
                if bad or len(set(dofs)) != len(dofs):
                    raise _err(n, f"dof must be distinct names from {_ALL_DOFS}, got {' '.join(parts[1:])!r}")
                bone["dof"] = dofs
            # id, limits and their continuation lines, bodymass, cofmass: not needed.
        elif section == ":hierarchy":
            if key in ("begin", "end"):
                continue
            hierarchy.append((n, parts))
    if bone is not None:
        raise MotionFormatError(f"ASF: bone block starting at line {bone['line']} is not closed (truncated?)")
    if not bones:
        raise MotionFormatError("ASF: no :bonedata bones")
    if root["order"] is None:
        raise MotionFormatError("ASF: :root has no 'order' line")
    bad = [c for c in root["order"] if c not in _ALL_DOFS[:6]]
    if bad:
        raise _err(root["order_line"], f"root order must use TX TY TZ RX RY RZ, got {bad}")

    if unit_scale is None:
        unit_scale = 0.0254 / (length_unit if length_unit is not None else 1.0)

    # Tree: root first, then bones in breadth-first hierarchy order (parents before children).
    by_name = {"root": None}
    for b in bones:
        if b["name"] in by_name:
            raise _err(b["line"], f"bone {b['name']!r} defined twice")
        by_name[b["name"]] = b
    children: dict[str, list[str]] = {}
    parent_of: dict[str, str] = {}
    for n, parts in hierarchy:
        for name in parts:
            if name not in by_name:
                raise _err(n, f"hierarchy names unknown bone {name!r}")
        for child in parts[1:]:
            if child in parent_of or child == "root":
                raise _err(n, f"bone {child!r} has two parents")
            parent_of[child] = parts[0]
        children.setdefault(parts[0], []).extend(parts[1:])
    order = ["root"]
    k = 0
    while k < len(order):
        order.extend(children.get(order[k], []))
        k += 1
    if len(order) != len(by_name):
        missing = sorted(set(by_name) - set(order))
        raise MotionFormatError(f"ASF: bones not reachable from root in :hierarchy: {missing[:10]}")

    J = len(order)
    index = {name: j for j, name in enumerate(order)}
    parents = np.array([-1] + [index[parent_of[name]] for name in order[1:]], dtype=np.int64)
    heads = np.zeros((J, 3))
    tails = np.zeros((J, 3))
    axes = np.zeros((J, 3, 3))
    heads[0] = tails[0] = np.asarray(root["position"]) * unit_scale
    axes[0] = _axis_frame(root["orientation"], root["axis"], root.get("axis_line", 0), angle_scale)
    dofs: list[tuple[str, ...]] = [tuple(root["order"])]
    for j, name in enumerate(order[1:], start=1):
        b = by_name[name]
        direction = np.asarray(b["direction"])
        norm = np.linalg.norm(direction)
        if norm < 1e-9 and b["length"] != 0:
            raise _err(b["line"], f"bone {name!r} has a zero direction")
        heads[j] = tails[parents[j]]
        tails[j] = heads[j] + (direction / max(norm, 1e-12)) * b["length"] * unit_scale
        angles, axis_order, axis_line = b["axis"]
        axes[j] = _axis_frame(angles, axis_order, axis_line, angle_scale)
        dofs.append(b["dof"])
    return AsfSkeleton(tuple(order), parents, heads, tails, axes, tuple(dofs), float(unit_scale), angle_scale)


_FRAME_LINE = re.compile(r"^\s*\d+\s*$", re.MULTILINE)


def amc_frames(text: str) -> int:
    """Frames in an AMC text, counted from its frame-number lines alone (no parsing)."""
    return len(_FRAME_LINE.findall(text))


def parse_amc(
    text: str,
    skeleton: AsfSkeleton,
    *,
    fps: float = CMU_FPS,
    max_frames: int = DEFAULT_MAX_FRAMES,
) -> SourceMotion:
    """Parse AMC text for ``skeleton`` into a :class:`SourceMotion` (metres, Y-up).

    Every frame must list every bone that has dofs, once, with one value per dof.
    """
    names = skeleton.names
    J = len(names)
    index = {name: j for j, name in enumerate(names)}
    widths = [len(d) for d in skeleton.dofs]
    starts = np.concatenate([[0], np.cumsum(widths)]).astype(int)
    D = int(starts[-1])
    required = sum(1 for w in widths if w > 0)
    rows: list[np.ndarray] = []
    current: np.ndarray | None = None
    seen: set[str] = set()
    frame_line = 0
    first_number = 0

    def close_frame(line: int) -> None:
        if current is not None and len(seen) != required:
            missing = [names[j] for j in range(J) if widths[j] and names[j] not in seen]
            raise MotionFormatError(
                f"AMC line {line}: frame {len(rows)} (line {frame_line}) lacks bones {missing[:8]}"
            )

    for i, raw in enumerate(text.splitlines()):
        n = i + 1
        parts = raw.split()
        if not parts or parts[0].startswith("#") or parts[0].startswith(":"):
            continue
        if len(parts) == 1 and parts[0].isdigit():
            close_frame(n)
            if len(rows) >= max_frames:
                raise MotionFormatError(f"AMC line {n}: more than the limit of {max_frames} frames")
            number = int(parts[0])
            if rows and number != first_number + len(rows):
                raise MotionFormatError(
                    f"AMC line {n}: frame number {number}, expected {first_number + len(rows)} (frames must be consecutive)"
                )
            if not rows:
                first_number = number
            current = np.zeros(D)
            rows.append(current)
            seen = set()
            frame_line = n
            continue
        if current is None:
            raise MotionFormatError(f"AMC line {n}: expected a frame number, got {parts[0]!r}")
        name = parts[0]
        j = index.get(name)
        if j is None:
            raise MotionFormatError(f"AMC line {n}: unknown bone {name!r} (not in the ASF)")
        if name in seen:
            raise MotionFormatError(f"AMC line {n}: bone {name!r} listed twice in frame {len(rows)}")
        seen.add(name)
        what = f"bone {name!r} ({' '.join(skeleton.dofs[j]) or 'no dof'})"
        current[starts[j] : starts[j + 1]] = _floats(parts[1:], widths[j], n, what, "AMC")
    if not rows:
        raise MotionFormatError("AMC: no frames")
    close_frame(len(text.splitlines()))
    values = np.stack(rows)  # (T, D)
    return _motion_from_values(skeleton, values, starts, fps)


def _motion_from_values(skel: AsfSkeleton, values: np.ndarray, starts: np.ndarray, fps: float) -> SourceMotion:
    T, J = values.shape[0], len(skel.names)
    axes_T = np.swapaxes(skel.axes, -1, -2)
    delta = np.empty((T, J, 3, 3))
    root_pos = np.broadcast_to(skel.heads[0], (T, 3)).copy()
    for j in range(J):  # loop over bones, vectorised over frames
        dofs = skel.dofs[j]
        v = values[:, starts[j] : starts[j + 1]]
        rot = [k for k, d in enumerate(dofs) if d in _ROT_DOFS]
        if rot:
            # First listed applied first: M = R_last ... R_first.
            axes = "".join(dofs[k][1].upper() for k in rot[::-1])
            M = euler_to_matrix(v[:, rot[::-1]] * skel.angle_scale, axes)
        else:
            M = np.broadcast_to(np.eye(3), (T, 3, 3))
        local_delta = skel.axes[j] @ M @ axes_T[j]  # C M C^-1
        delta[:, j] = local_delta if j == 0 else delta[:, skel.parents[j]] @ local_delta
        if j == 0:
            for k, d in enumerate(dofs):
                if d.startswith("t"):
                    root_pos[:, "xyz".index(d[1])] = v[:, k] * skel.unit_scale
    return SourceMotion(
        names=skel.names,
        parents=skel.parents,
        rest_heads=skel.heads,
        rest_tails=skel.tails,
        rest_rotations=skel.axes,
        world_rotations=delta @ skel.axes,
        root_positions=root_pos,
        fps=float(fps),
        up_axis="y",
    )


def load_asf_amc(asf_path: str | Path, amc_path: str | Path, **kwargs) -> SourceMotion:
    """Read an ASF + AMC pair (keyword arguments go to :func:`parse_amc`)."""
    skel = parse_asf(Path(asf_path).read_text(encoding="utf-8", errors="replace"))
    return parse_amc(Path(amc_path).read_text(encoding="utf-8", errors="replace"), skel, **kwargs)
