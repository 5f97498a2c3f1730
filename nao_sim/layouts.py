"""Landmark layouts drawn as users lay them out, for the randomized worlds (nao_sim/randomize.py).

The fixed layouts of config/landmarks are rooms the project was written in. A drawn layout is one it
was not: ``draw_layout(rng, params)`` puts landmarks on the walls of a square room as a user with
tape and a printer would (docs/landmarks.md, "Where to put them"; docs/simulator.md, "Drawn
layouts"; config/sim.yaml ``randomizer.drawn_layout`` holds every range):

* the room: walls at x, y = +-h, h ~ U(``half_size``);
* the kind: ArUco markers, coloured balls or both (each wall one kind, both kinds present), equally likely;
* the walls: ``walls`` of the four carry landmarks (the others are bare: a door, a window, furniture);
* along a wall: one spacing s ~ U(``spacing``) per wall, landmarks at s apart centred on the wall,
  each moved along it by U(-``jitter``, ``jitter``) s and kept ``corner_margin`` from the corners,
  at a height z ~ U(``height``), ``WALL_GAP`` proud of the wall, facing into the room;
* ArUco: one printed size U(``marker_size``) for the layout (a user prints one sheet), DICT_4X4_50,
  distinct ids drawn at random (at most 50 markers: a denser draw is thinned evenly);
* balls: one diameter U(``ball_size``), four of the non-red colours (red is the object's), dealt in a
  shuffled order that uses each about as often: a colour alone names no ball.

The map is written, as a user's landmark file, to ``layout_file(map)``: a content-addressed file
in the temporary directory, so that a world drawn twice names the same file.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Tuple

import numpy as np
import yaml

from nao_core.config import bounds
from nao_core.landmark_map import Landmark, LandmarkMap

WALL_GAP = 0.01  # m: a landmark's centre in front of its wall (tape, a board's thickness)
DICTIONARY = "DICT_4X4_50"
DICTIONARY_SIZE = 50
BALL_COLOURS = ("green", "yellow", "magenta", "cyan", "blue")  # nao_sim/render.py draws these; none is the object's red
COLOURS_USED = 4
KINDS = ("aruco", "colour", "mixed")


@dataclass(frozen=True)
class DrawnLayoutParams:
    """Ranges of a drawn layout (module docstring)."""

    share: float = field(metadata=bounds(0.0, 1.0))  # of the randomized worlds, drawn last (the others' draws stay)
    half_size: Tuple[float, float] = field(metadata=bounds(1.0, 10.0))  # m, walls at +-this
    walls: Tuple[int, int] = field(metadata=bounds(1, 4))  # how many walls carry landmarks (range, inclusive)
    spacing: Tuple[float, float] = field(metadata=bounds(0.1, 5.0))  # m between neighbours along a wall
    jitter: float = field(metadata=bounds(0.0, 0.5))  # of the spacing, each landmark along its wall
    corner_margin: float = field(metadata=bounds(0.0, 2.0))  # m, nearest a landmark comes to a corner
    height: Tuple[float, float] = field(metadata=bounds(0.0, 3.0))  # m, centre above the floor
    marker_size: Tuple[float, float] = field(metadata=bounds(0.02, 1.0))  # m, ArUco black square's side
    ball_size: Tuple[float, float] = field(metadata=bounds(0.02, 1.0))  # m, ball diameter


@dataclass(frozen=True)
class DrawnLayout:
    kind: str  # one of KINDS
    half_size: float  # m
    landmarks: LandmarkMap


def _wall_positions(rng: np.random.Generator, p: DrawnLayoutParams, half: float) -> np.ndarray:
    """Offsets along one wall (from its middle), s apart and jittered, within the corner margins."""
    spacing = rng.uniform(*p.spacing)
    reach = half - p.corner_margin
    count = int(2.0 * reach / spacing) + 1
    along = (np.arange(count) - 0.5 * (count - 1)) * spacing
    along = along + rng.uniform(-p.jitter, p.jitter, count) * spacing
    return np.clip(along, -reach, reach)


def _wall_pose(wall: int, along: float, half: float) -> Tuple[float, float, float]:
    """(x, y, yaw) of a point ``along`` a wall (0: x = +h, 1: y = +h, 2: x = -h, 3: y = -h), facing in."""
    inner = half - WALL_GAP
    return [(inner, along, math.pi), (-along, inner, -math.pi / 2), (-inner, -along, 0.0), (along, -inner, math.pi / 2)][wall]


def draw_layout(rng: np.random.Generator, p: DrawnLayoutParams) -> DrawnLayout:
    """One layout (module docstring), from ``rng`` alone."""
    half = float(rng.uniform(*p.half_size))
    kind = KINDS[int(rng.integers(len(KINDS)))]
    used = sorted(rng.choice(4, size=int(rng.integers(p.walls[0], p.walls[1] + 1)), replace=False).tolist())
    if kind == "mixed":
        used = used if len(used) >= 2 else sorted({used[0], (used[0] + 2) % 4})  # room for both kinds
        wall_kinds = {w: ("aruco", "colour")[i % 2] for i, w in enumerate(rng.permutation(used).tolist())}
    else:
        wall_kinds = {w: kind for w in used}
    spots = {w: _wall_positions(rng, p, half) for w in used}
    marker_size, ball_size = float(rng.uniform(*p.marker_size)), float(rng.uniform(*p.ball_size))
    colours = rng.permutation(BALL_COLOURS)[:COLOURS_USED].tolist()

    markers = [(w, a) for w in used if wall_kinds[w] == "aruco" for a in spots[w]]
    if len(markers) > DICTIONARY_SIZE:  # thinned evenly: more markers than the dictionary has ids
        markers = [markers[i] for i in np.linspace(0, len(markers) - 1, DICTIONARY_SIZE).round().astype(int)]
    ids = rng.permutation(DICTIONARY_SIZE)[:len(markers)].tolist()
    balls = [(w, a) for w in used if wall_kinds[w] == "colour" for a in spots[w]]
    dealt = rng.permutation(np.resize(colours, len(balls))).tolist()

    landmarks: List[Landmark] = []
    for (wall, along), marker_id in zip(markers, ids):
        x, y, yaw = _wall_pose(wall, float(along), half)
        landmarks.append(Landmark(id=int(marker_id), kind="aruco", dictionary=DICTIONARY, size=round(marker_size, 4),
                                  position=(round(x, 4), round(y, 4), round(float(rng.uniform(*p.height)), 3)),
                                  yaw=round(yaw, 4)))
    counts = {c: 0 for c in colours}
    for (wall, along), colour in zip(balls, dealt):
        x, y, _ = _wall_pose(wall, float(along), half)
        counts[colour] += 1
        landmarks.append(Landmark(id=f"{colour}-{counts[colour]}", kind="color", color=colour, diameter=round(ball_size, 4),
                                  position=(round(x, 4), round(y, 4), round(float(rng.uniform(*p.height)), 3))))
    return DrawnLayout(kind, half, LandmarkMap(tuple(landmarks)))


def one_wall(layout: DrawnLayout) -> DrawnLayout:
    """``layout`` with the landmarks of its most-marked wall alone (of those tied, the first of +x, +y,
    -x, -y): a user who taped landmarks on one wall (docs/simulator.md, "Drawn layouts")."""
    def wall(lm: Landmark) -> int:
        x, y = lm.position[:2]
        return (0 if x > 0.0 else 2) if abs(x) >= abs(y) else (1 if y > 0.0 else 3)

    kept = max(([lm for lm in layout.landmarks.landmarks if wall(lm) == w] for w in range(4)), key=len)
    kinds = {lm.kind for lm in kept}
    kind = "mixed" if len(kinds) > 1 else ("aruco" if kinds == {"aruco"} else "colour")
    return DrawnLayout(kind, layout.half_size, LandmarkMap(tuple(kept)))


def sample_layout(kind: str, p: DrawnLayoutParams) -> DrawnLayout:
    """The first layout of ``kind`` drawn from seeds 0, 1, ...: one fixed room of each kind (tests, benchmarks)."""
    if kind not in KINDS:
        raise ValueError(f"layout kind {kind!r}: one of {', '.join(KINDS)}")
    return next(layout for layout in (draw_layout(np.random.default_rng(seed), p) for seed in range(1000)) if layout.kind == kind)


def map_yaml(landmark_map: LandmarkMap, header: str) -> str:
    """A landmark file (config/landmarks format, docs/landmarks.md) of ``landmark_map``, after ``header``."""
    rows = []
    for lm in landmark_map.landmarks:
        row = {"id": lm.id, "kind": lm.kind, "position": [float(v) for v in lm.position]}
        row.update({"dictionary": lm.dictionary, "size": lm.size, "yaw": lm.yaw} if lm.kind == "aruco"
                   else {"color": lm.color, "diameter": lm.diameter})
        rows.append(row)
    precision = {"position_sigma": float(landmark_map.position_sigma), "yaw_sigma": float(landmark_map.yaw_sigma)}  # stated, 0 too
    return header + yaml.safe_dump({"landmarks": rows, **precision}, sort_keys=False, default_flow_style=None)


def layout_yaml(layout: DrawnLayout) -> str:
    """The layout as a landmark file."""
    return map_yaml(layout.landmarks, f"# A drawn layout (nao_sim/layouts.py): {layout.kind}, {len(layout.landmarks.landmarks)} "
                                      f"landmarks on the walls of a room of half size {layout.half_size:.3f} m\n")


def measured(landmark_map: LandmarkMap, position_sigma: float, yaw_sigma: float, rng: np.random.Generator,
             told: bool = True) -> LandmarkMap:
    """``landmark_map`` as a user measures it: each landmark's centre moved by N(0, position_sigma^2 I_3), each
    marker's facing by N(0, yaw_sigma^2); ``told``: the map says so (its ``position_sigma``, ``yaw_sigma``)."""
    moved = tuple(dataclasses.replace(lm, position=tuple(float(v) for v in np.add(lm.position, rng.normal(0.0, position_sigma, 3))),
                                      yaw=float(lm.yaw + rng.normal(0.0, yaw_sigma)) if lm.kind == "aruco" else lm.yaw)
                  for lm in landmark_map.landmarks)
    return LandmarkMap(moved, position_sigma if told else 0.0, yaw_sigma if told else 0.0)


def layout_file(layout: DrawnLayout) -> Path:
    """The landmark file of ``layout``, written once under the temporary directory (named by its content)."""
    text = layout_yaml(layout)
    path = Path(tempfile.gettempdir()) / "nao_sim_layouts" / f"{hashlib.sha1(text.encode()).hexdigest()[:16]}.yaml"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(f".{os.getpid()}.part")
        partial.write_text(text)
        partial.replace(path)  # atomic: a concurrent reader sees the whole file or none
    return path
