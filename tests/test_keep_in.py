"""The walls the landmark map shows (agent/keep_in.py): half-planes against known rooms, and the
planner keeping off them in the 2-D closed loop."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from agent.ekf import load_ekf_params
from agent.keep_in import KeepIn
from agent.coverage import bin_angles
from agent.planner import Planner, load_planner_params
from nao_core.config import CONFIG_DIR
from nao_core.landmark_map import Landmark, LandmarkMap, load_landmark_map
from nao_core.robot_model import load_robot_model
from nao_sim.sim2d import SimRobot, simulate

PARAMS = dataclasses.replace(load_planner_params(), omnidirectional=False)
EKF = load_ekf_params()
MODEL = load_robot_model()
HFOV = 2.0 * math.atan(0.5 * 640 / MODEL.camera.intrinsics("vga").fx)
ROBOT = SimRobot(MODEL.walk, HFOV, MODEL.head.yaw, MODEL.camera.offset[0])


def markers_on_walls(half_size: float, per_wall: int = 5) -> LandmarkMap:
    """ArUco markers on the four walls of a square room, facing in."""
    landmarks, along = [], np.linspace(-0.8, 0.8, per_wall) * half_size
    for wall, (nx, ny) in enumerate([(-1, 0), (0, -1), (1, 0), (0, 1)]):
        for i, a in enumerate(along):
            x, y = (-nx * half_size, a) if nx else (a, -ny * half_size)
            landmarks.append(Landmark(id=wall * per_wall + i, kind="aruco", dictionary="DICT_4X4_50", size=0.1,
                                      position=(x, y, 0.4), yaw=math.atan2(ny, nx)))
    return LandmarkMap(tuple(landmarks))


def wall_distance(points: np.ndarray, half_size: float) -> np.ndarray:
    return half_size - np.max(np.abs(points), axis=-1)


def test_markers_on_walls_give_the_room():
    keep_in = KeepIn(markers_on_walls(1.5))
    rng = np.random.default_rng(0)
    points = rng.uniform(-2.0, 2.0, (500, 2))
    nearest = np.min(keep_in.distances(points), axis=-1)
    np.testing.assert_allclose(nearest, wall_distance(points, 1.5), atol=1e-12)  # inside and outside


def test_balls_on_walls_approximate_the_room_and_never_cut_its_middle():
    """config/landmarks/colours.yaml (balls every 0.6 m on the walls of a 4 x 4 m room): where the robot
    walks (1.6 m of the centre) the nearest half-plane is at most 5 cm beyond the true wall and at
    most 20 cm inside it (a slanted plane cuts in beside its ball), and a point beyond a wall is outside."""
    keep_in = KeepIn(load_landmark_map(CONFIG_DIR / "landmarks" / "colours.yaml"))
    rng = np.random.default_rng(1)
    inner = rng.uniform(-1.6, 1.6, (500, 2))
    inner = inner[np.hypot(*inner.T) <= 1.6]
    error = np.min(keep_in.distances(inner), axis=-1) - wall_distance(inner, 1.99)
    assert np.all(error <= 0.05) and np.all(error >= -0.2)
    beyond = np.array([[2.1, 0.0], [0.3, -2.1], [-2.05, 1.0]])
    assert np.all(np.min(keep_in.distances(beyond), axis=-1) < 0.0)


def test_balls_on_one_wall_face_the_object_and_leave_the_orbit_free():
    """Twelve balls on one wall x = 2.26 (a user's one-wall colour room, matrix one-wall worlds 502 and
    503): facing their centroid, on the wall, they faced along it and cut the floor to a band round
    the object, so the planner fled the orbit. Facing the object, its orbit is walkable and the wall
    is kept: the nearest plane to a point in front of the wall is the wall, within 2 cm, and a point
    beyond it is outside. Without the object, balls on one line enclose no floor."""
    balls = tuple(Landmark(id=f"green-{i}", kind="color", color="green", diameter=0.11, position=(2.26, y, 0.4))
                  for i, y in enumerate(np.linspace(-2.0, 2.0, 12)))
    keep_in = KeepIn(LandmarkMap(balls))
    x = np.array([0.0, 0.0, 0.05])
    walls = keep_in.walls(x)
    a = np.linspace(-math.pi, math.pi, 72)
    orbit = 1.2 * np.stack([np.cos(a), np.sin(a)], axis=-1)
    assert np.all(keep_in.distances(orbit, walls) >= PARAMS.wall_clearance)
    nearest = keep_in.nearest(np.array([1.8, 0.1]), x)
    assert nearest[0] == pytest.approx(0.46, abs=0.02) and nearest[1] == pytest.approx(-1.0, abs=0.05)
    assert np.min(keep_in.distances(np.array([2.4, 0.1]), walls)) < 0.0
    assert keep_in.distances(orbit).shape == (len(orbit), 0)


def test_a_half_plane_without_the_object_is_no_wall():
    """A marker on a box in the room, facing away from the object, is not a wall of this room."""
    room = markers_on_walls(1.5)
    box = Landmark(id=40, kind="aruco", dictionary="DICT_4X4_50", size=0.1, position=(0.6, 0.0, 0.2), yaw=0.0)
    keep_in = KeepIn(LandmarkMap(room.landmarks + (box,)))
    walls = keep_in.walls(np.array([0.0, 0.0, 0.05]))
    assert len(walls.offsets) == len(room.landmarks) and not np.any(np.isclose(walls.offsets, 0.6))  # the box's n . p
    nearest = keep_in.nearest(np.array([0.2, 1.4, 0.0]), np.array([0.0, 0.0, 0.05]))
    np.testing.assert_allclose(nearest, [0.1, 0.0, -1.0], atol=1e-12)  # the wall y = 1.5, facing -y


def test_bins_behind_a_near_wall_are_unreachable_and_the_rest_are():
    """An object in the middle of a 3 x 3 m room can be seen from all round; 0.5 m from the wall
    x = 1.5, the bins facing that wall cannot (no camera position keeps both clearances), the
    bins facing away can."""
    keep_in = KeepIn(markers_on_walls(1.5))
    planner = Planner(PARAMS, MODEL.walk, HFOV, MODEL.head.yaw, MODEL.camera.offset[0], EKF)
    assert planner.reachable_bins(np.array([0.0, 0.0, 0.05]), keep_in).all()
    reachable = planner.reachable_bins(np.array([1.0, 0.0, 0.05]), keep_in)
    normals = np.cos(bin_angles(PARAMS.coverage.bins))  # x component of each bin's normal
    assert not reachable[normals > 0.9].any() and reachable[normals < 0.0].all()


def test_the_planner_keeps_off_the_walls_where_its_orbit_would_not():
    """Objects 0.85 and 0.7 m from a wall of a 3 x 3 m room. At 0.85 m the robot goes round within
    wall_clearance of no wall (2 cm of the unicycle's discretization). At 0.7 m the free planner's
    orbit passes within 0.2 m of the wall; keeping off the walls it never comes nearer than
    wall_clearance, nor breaks the object clearance, and completes with the bins the walls leave
    reachable (the far side's are not)."""
    keep_in = KeepIn(markers_on_walls(1.5))
    for ox in (0.65, 0.8):
        truth, start = np.array([ox, 0.0, 0.05]), np.array([ox - 1.05, 0.0, 0.0])
        kept = simulate(truth, start, PARAMS, EKF, ROBOT, seed=3, keep_in=keep_in)
        assert np.min(wall_distance(kept.poses[:, :2], 1.5)) >= PARAMS.wall_clearance - 0.02
        assert np.min(np.hypot(*(kept.poses[:, :2] - truth[:2]).T) - truth[2]) >= PARAMS.clearance - 0.02
        assert kept.reason.startswith("complete") and kept.final_errors()[0] < 0.01
    free = simulate(truth, start, PARAMS, EKF, ROBOT, seed=3)
    assert free.reason.startswith("complete") and np.min(wall_distance(free.poses[:, :2], 1.5)) < 0.2
    assert kept.true_coverage[-1] < 0.9 <= free.true_coverage[-1]  # the far side unseen, kept; seen, at the wall
