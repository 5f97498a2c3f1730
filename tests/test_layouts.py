"""Landmark layouts drawn as users lay them out (nao_sim/layouts.py) and their place among the
randomized worlds (nao_sim/randomize.py)."""

from __future__ import annotations

import collections
import dataclasses
import math

import numpy as np
import pytest

from agent.perception import PerceptionParams
from nao_core.config import CONFIG_DIR, load
from nao_core.landmark_map import load_landmark_map
from nao_sim.layouts import (BALL_COLOURS, COLOURS_USED, DICTIONARY_SIZE, KINDS, WALL_GAP, draw_layout, layout_file, map_yaml, measured,
                             one_wall, sample_layout)
from nao_sim.randomize import load_randomizer, random_world

RANDOMIZER = load_randomizer()
P = RANDOMIZER.drawn_layout
OBJECT_COLOR = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception").object_color
LAYOUTS = [draw_layout(np.random.default_rng(seed), P) for seed in range(300)]


def _wall(position, half):
    """The wall a landmark is on (0: x = +h, 1: y = +h, 2: x = -h, 3: y = -h) and its offset along it."""
    x, y, _ = position
    inner = half - WALL_GAP
    on = [abs(x - inner) < 1e-3, abs(y - inner) < 1e-3, abs(x + inner) < 1e-3, abs(y + inner) < 1e-3]
    assert sum(on) == 1, (position, half)
    wall = on.index(True)
    return wall, (y if wall % 2 == 0 else x)


def test_every_landmark_is_on_a_wall_facing_into_the_room_within_the_ranges():
    for layout in LAYOUTS:
        half = layout.half_size
        assert P.half_size[0] <= half <= P.half_size[1]
        walls = collections.defaultdict(list)
        for lm in layout.landmarks.landmarks:
            wall, along = _wall(lm.position, half)
            walls[wall].append(lm)
            assert abs(along) <= half - P.corner_margin + 1e-3
            assert P.height[0] - 1e-3 <= lm.position[2] <= P.height[1] + 1e-3
            if lm.kind == "aruco":  # its marker faces the room's centre
                assert float(np.dot(lm.normal[:2], lm.position[:2])) == pytest.approx(-(half - WALL_GAP), abs=1e-3)
        assert P.walls[0] <= len(walls) <= P.walls[1]
        if layout.kind == "mixed":  # a wall is of one kind; both kinds are in the room
            assert all(len({lm.kind for lm in on}) == 1 for on in walls.values())
            assert {lm.kind for lm in layout.landmarks.landmarks} == {"aruco", "color"}
        else:
            assert {lm.kind for lm in layout.landmarks.landmarks} == {"aruco" if layout.kind == "aruco" else "color"}
    assert {layout.kind for layout in LAYOUTS} == set(KINDS)


def test_markers_are_one_printed_size_with_distinct_ids_and_balls_repeat_four_colours_none_the_objects():
    for layout in LAYOUTS:
        markers, balls = layout.landmarks.of_kind("aruco"), layout.landmarks.of_kind("color")
        ids = [lm.id for lm in markers]
        assert len(set(ids)) == len(ids) and all(0 <= i < DICTIONARY_SIZE for i in ids)
        assert len({lm.size for lm in markers}) <= 1 and all(P.marker_size[0] - 1e-4 <= lm.size <= P.marker_size[1] + 1e-4 for lm in markers)
        assert len({lm.diameter for lm in balls}) <= 1
        counts = collections.Counter(lm.color for lm in balls)
        assert OBJECT_COLOR not in counts and set(counts) <= set(BALL_COLOURS) and len(counts) <= COLOURS_USED
        if len(balls) >= 2 * COLOURS_USED:  # each colour used about as often: no colour names its ball
            assert len(counts) == COLOURS_USED and min(counts.values()) >= len(balls) // COLOURS_USED - 1
    dense = dataclasses.replace(P, spacing=(0.1, 0.1), walls=(4, 4), half_size=(2.5, 2.5))  # 4 x 47 spots
    crowded = [draw_layout(np.random.default_rng(seed), dense) for seed in range(12)]
    markers = [layout.landmarks.of_kind("aruco") for layout in crowded if layout.kind == "aruco"]
    assert markers and all(len(m) == DICTIONARY_SIZE for m in markers)  # thinned to the dictionary's ids, none repeated


def test_a_drawn_layout_is_a_landmark_file_that_reads_back_the_same_under_one_name():
    for layout in LAYOUTS[:20]:
        path = layout_file(layout)
        assert load_landmark_map(path) == layout.landmarks
        assert layout_file(draw_layout(np.random.default_rng(LAYOUTS.index(layout)), P)) == path
    for kind in KINDS:  # the fixed sample rooms of the tests and the localization benchmark
        assert sample_layout(kind, P).kind == kind and sample_layout(kind, P) == sample_layout(kind, P)
    with pytest.raises(ValueError, match="'walls': one of aruco, colour, mixed"):
        sample_layout("walls", P)


def _painted_as(world, other):
    """``world`` with ``other``'s object paint (the same seed, another map), which they may differ in
    only where a ball of one map has the other's paint (nao_sim/randomize.py)."""
    balls = [load_landmark_map(w.landmark_path).ball_colors for w in (world, other)]
    if world.object_color != other.object_color:
        assert other.object_color in balls[0] or world.object_color in balls[1], (world.seed, other.object_color)
    scenario = dataclasses.replace(world.scenario, color=other.scenario.color)
    return dataclasses.replace(world, object_color=other.object_color, scenario=scenario,
                               config=dataclasses.replace(world.config, scenarios={world.object_name: scenario}))


def test_drawn_layouts_replace_the_layout_of_a_share_of_worlds_and_change_nothing_else():
    """Drawn last: a world that draws a layout is the world it was with none but for its landmarks
    and room size (the CI seed and the documented slow seeds keep their objects, starts and noise)."""
    none = dataclasses.replace(RANDOMIZER, drawn_layout=dataclasses.replace(P, share=0.0))
    drawn = 0
    for seed in range(40):
        world, plain = random_world(seed, RANDOMIZER), random_world(seed, none)
        if world.layout.startswith("drawn"):
            drawn += 1
            assert world.layout.split()[1] in KINDS
            landmarks = load_landmark_map(world.landmark_path)
            assert str(world.config.landmark_path) == world.landmark_path
            half = world.config.room.half_size
            assert P.half_size[0] <= half <= P.half_size[1] and landmarks.landmarks
            assert max(abs(world.start[0]), abs(world.start[1])) < half - 0.1  # the robot starts in the room
            world = _painted_as(world, plain)
            world = dataclasses.replace(world, layout=plain.layout, landmark_path=plain.landmark_path,
                                        config=dataclasses.replace(world.config, landmarks=plain.config.landmarks,
                                                                   room=plain.config.room))
        assert world == plain, seed
    assert abs(drawn - 40 * P.share) <= 3.0 * math.sqrt(40 * P.share * (1.0 - P.share))  # the configured share


def test_a_one_wall_layout_keeps_the_most_marked_wall_alone_and_the_world_is_otherwise_the_same():
    """``one_wall`` keeps the landmarks of one wall, the wall with the most of them, unchanged; a
    world drawn with ``one_wall_only`` is the same world (object, start, noise, room) with that map."""
    for layout in LAYOUTS[:60]:
        cut = one_wall(layout)
        counts = collections.Counter(_wall(lm.position, layout.half_size)[0] for lm in layout.landmarks.landmarks)
        kept = {_wall(lm.position, cut.half_size)[0] for lm in cut.landmarks.landmarks}
        assert len(kept) == 1 and len(cut.landmarks.landmarks) == max(counts.values())
        assert set(cut.landmarks.landmarks) <= set(layout.landmarks.landmarks)
        assert cut.kind == {"aruco": "aruco", "color": "colour"}[cut.landmarks.landmarks[0].kind]
    for seed in range(6):
        world, cut = random_world(seed, RANDOMIZER), random_world(seed, RANDOMIZER, one_wall_only=True)
        assert cut.layout.endswith(", one wall") and cut.layout.split()[1].rstrip(",") in KINDS
        landmarks = load_landmark_map(cut.landmark_path).landmarks
        assert len({_wall(lm.position, cut.config.room.half_size)[0] for lm in landmarks}) == 1
        cut = _painted_as(cut, world)
        same = dataclasses.replace(cut, layout=world.layout, landmark_path=world.landmark_path,
                                   config=dataclasses.replace(cut.config, landmarks=world.config.landmarks, room=world.config.room))
        assert same == world, seed


@pytest.mark.parametrize("told", [True, False])
def test_a_measured_map_moves_each_landmark_by_its_sigma_and_says_so_when_told(tmp_path, told):
    """``measured`` (the station's map in a world with ``map_error``): every landmark moved, the moves'
    spread the sigma asked (over the 300 drawn layouts' landmarks, within 5 %), markers turned and balls
    not; written by ``map_yaml``, the file loads and carries the sigmas only when told."""
    position_sigma, yaw_sigma = 0.005, 0.02
    moves, turns = [], []
    for k, layout in enumerate(LAYOUTS):
        moved = measured(layout.landmarks, position_sigma, yaw_sigma, np.random.default_rng(k), told)
        for exact, lm in zip(layout.landmarks.landmarks, moved.landmarks):
            moves.append(np.subtract(lm.position, exact.position))
            if lm.kind == "aruco":
                turns.append(lm.yaw - exact.yaw)
            else:
                assert lm.yaw == exact.yaw
    assert np.std(moves, axis=0) == pytest.approx([position_sigma] * 3, rel=0.05)
    assert np.std(turns) == pytest.approx(yaw_sigma, rel=0.05)
    path = tmp_path / "measured.yaml"
    path.write_text(map_yaml(moved, "# measured\n"))
    loaded = load_landmark_map(path)
    assert loaded == moved
    assert (loaded.position_sigma, loaded.yaw_sigma) == ((position_sigma, yaw_sigma) if told else (0.0, 0.0))
