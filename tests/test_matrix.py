"""Objects of real shapes, the world randomizer, and a CI sample of the mission matrix.

* A triangle mesh renders as the exact union of its projected triangles: every pixel where the
  rendered silhouette and ray-cast truth disagree lies on the truth's outline.
* ``Scenario.contains`` (the truth of IoU) against analytic solids.
* ``random_world`` draws every axis of the matrix inside its configured ranges, deterministically,
  and paints its rooms in no colour the perception looks for.
* Fixed-seed missions through the NAOqi stand-in (``tools.matrix.run_mission``) in worlds that
  differ in layout, object size and shape, and sway; each asserts the outcome, centre and radius
  error, model IoU, closest approach, the robot at rest at the end and how soon it was stopped.
  The full randomized matrix is a benchmark (``make matrix``, docs/benchmarks.md).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent.perception import PerceptionParams, color_mask
from agent.planner import load_planner_params
from agent.self_calibration import SelfCalibrationParams
from nao_bridge.bridge import BridgeParams
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import planar_transform
from nao_core.landmark_map import LandmarkMap, load_landmark_map
from nao_core.robot_model import load_robot_model, nao_to_optical
from nao_sim.meshes import PROCEDURAL, contains, ellipsoid, is_closed, ray_winding_numbers, winding_numbers
from nao_sim.randomize import RandomWorld, load_randomizer, random_world
from nao_sim.render import Renderer
from nao_sim.scenarios import load_sim_config
from tests.conftest import CI_SEED

pytestmark = pytest.mark.serial  # a whole mission through the NAOqi stand-in: run alone (Makefile test)

ROBOT = load_robot_model()
CONFIG = load_sim_config()
PERCEPTION = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")


def ray_cast_mask(scenario, intr, T_WC: np.ndarray, box: tuple) -> np.ndarray:
    """Truth silhouette at pixel centres inside ``box`` (x0, y0, x1, y1): a ray hits a triangle (Moller-Trumbore)."""
    x0, y0, x1, y1 = box
    v, u = np.mgrid[y0:y1, x0:x1].astype(float)
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1).reshape(-1, 3) @ T_WC[:3, :3].T
    origin = T_WC[:3, 3]
    hit = np.zeros(len(rays), bool)
    for part in scenario.parts:
        vertices, faces = part.world_mesh(scenario.position, scenario.yaw)
        a, b, c = (vertices[faces[:, k]] for k in range(3))
        e1, e2, s = b - a, c - a, origin - a
        q = np.cross(s, e1)
        for i in range(0, len(rays), 2048):
            d = rays[i : i + 2048]
            p = np.cross(d[:, None, :], e2[None])
            det = np.einsum("rfi,fi->rf", p, e1)
            with np.errstate(divide="ignore", invalid="ignore"):
                uu = np.einsum("rfi,fi->rf", p, s) / det
                vv = (d @ q.T) / det
                t = np.einsum("fi,fi->f", q, e2)[None] / det
            hit[i : i + 2048] |= ((uu >= 0) & (vv >= 0) & (uu + vv <= 1) & (t > 0)).any(axis=1)
    return hit.reshape(y1 - y0, x1 - x0)


@pytest.mark.parametrize("name", ["bunny"])
def test_a_mesh_renders_as_the_exact_union_of_its_triangles(name):
    scenario = CONFIG.scenario(name)
    intr = ROBOT.camera.intrinsics("qvga")
    empty = LandmarkMap(())
    quiet = dict(pixel_sigma=0.0, gain_sigma=0.0, seed=0)
    with_object = Renderer(intr, CONFIG.room, empty, scenario, **quiet)
    without = Renderer(intr, CONFIG.room, empty, dataclasses.replace(scenario, position=(40.0, 40.0)), **quiet)
    for azimuth in (0.3, 2.0, -2.5):
        ox, oy = scenario.position
        pose = (ox + 0.6 * math.cos(azimuth), oy + 0.6 * math.sin(azimuth), azimuth + math.pi)
        T_WC = planar_transform(*pose) @ nao_to_optical(ROBOT.camera_in_robot_nao(*ROBOT.look_at(pose, (ox, oy, 0.07))))
        diff = cv2.absdiff(with_object.render(T_WC, 0), without.render(T_WC, 0)).max(axis=2) > 0
        ys, xs = np.nonzero(diff)
        assert len(xs) > 500  # the object is in view and large
        box = (max(xs.min() - 3, 0), max(ys.min() - 3, 0), min(xs.max() + 4, intr.width), min(ys.max() + 4, intr.height))
        truth = ray_cast_mask(scenario, intr, T_WC, box)
        rendered = diff[box[1] : box[3], box[0] : box[2]]
        # the area-exact anti-aliasing covers a pixel partly where an edge crosses it, so a pixel may
        # differ from its centre's ray only next to the true outline (within one pixel of it)
        outline = cv2.dilate(truth.astype(np.uint8), np.ones((3, 3), np.uint8)) != cv2.erode(truth.astype(np.uint8), np.ones((3, 3), np.uint8))
        assert not (rendered != truth)[~outline].any()
        assert truth.sum() > 0.9 * rendered.sum()


def test_winding_number_is_one_inside_and_zero_outside_a_closed_mesh():
    radii = np.array([0.05, 0.03, 0.04])
    mesh = ellipsoid((0.1, -0.2, 0.05), radii, n_u=24, n_v=16)
    rng = np.random.default_rng(0)
    points = rng.uniform(-1.3, 1.3, (2000, 3))
    r = np.linalg.norm(points, axis=1)
    # the polygon lies between the ellipsoid and its inscribed shell: keep points 10 % clear of the surface
    clear = (r < 0.85) | (r > 1.05)
    points, r = points[clear], r[clear]
    world = points * radii + np.array([0.1, -0.2, 0.05])
    assert np.array_equal(contains(mesh, world), r < 1.0)
    w = winding_numbers(mesh, world)
    assert np.allclose(w[r < 1.0], 1.0, atol=1e-6) and np.allclose(w[r > 1.0], 0.0, atol=1e-6)


@pytest.mark.parametrize("name", ["bunny", "duck"])
def test_vertical_rays_count_the_same_winding_numbers_as_solid_angles(name):
    """The closed procedural meshes (overlapping ellipsoids): the signed crossings of vertical rays
    give each point's winding number exactly as the solid angles do, for points on a voxel grid
    (columns shared) and scattered ones; a mesh with a hole is left to the solid angles."""
    mesh = PROCEDURAL[name]()
    lo, hi = mesh[0].min(axis=0), mesh[0].max(axis=0)
    rng = np.random.default_rng(1)
    grid = np.stack(np.meshgrid(*(np.linspace(l, h, 17) for l, h in zip(lo, hi)), indexing="ij"), axis=-1).reshape(-1, 3)
    points = np.vstack([grid, rng.uniform(lo, hi, (1500, 3))])
    solid = winding_numbers(mesh, points)
    assert is_closed(mesh) and np.array_equal(ray_winding_numbers(mesh, points), np.round(solid))
    assert 0.1 < np.mean(solid >= 0.5) < 0.9  # both sides sampled
    assert not is_closed((mesh[0], mesh[1][1:]))  # one face fewer: open


@pytest.mark.parametrize("name", ["can", "remote", "mug", "figure"])
def test_scenario_contains_matches_its_parts(name):
    sc = CONFIG.scenario(name)
    c, s = math.cos(sc.yaw), math.sin(sc.yaw)
    centres = [(sc.position[0] + c * p.centre[0] - s * p.centre[1], sc.position[1] + s * p.centre[0] + c * p.centre[1], p.centre[2])
               for p in sc.parts]
    assert sc.contains(np.array(centres)).all()  # every part's centre, turned with the object
    far = np.array([[sc.position[0] + sc.radius + 0.01, sc.position[1], 0.01], [sc.position[0], sc.position[1], sc.height + 0.01]])
    assert not sc.contains(far).any()  # beyond the enclosing cylinder and above the top


def test_mean_half_breadth_is_the_radius_of_a_cylinder_and_cauchys_for_a_box():
    """What a cylinder fitted to apparent widths converges to, seen from all round: a can's radius;
    for the 15 x 8 cm box, half its mean caliper width (perimeter / pi, Cauchy), whatever its yaw;
    for any shape no more than the enclosing radius."""
    can, box = CONFIG.scenario("can"), CONFIG.scenario("flat_box")
    assert can.mean_half_breadth == pytest.approx(can.radius, rel=1e-3)
    a, b = box.parts[0].size[:2]
    assert box.mean_half_breadth == pytest.approx((a + b) / math.pi, rel=1e-6)
    turned = dataclasses.replace(box, yaw=box.yaw + 0.7)
    assert turned.mean_half_breadth == pytest.approx(box.mean_half_breadth, rel=1e-6)
    for name in CONFIG.scenarios:
        assert CONFIG.scenario(name).mean_half_breadth <= CONFIG.scenario(name).radius + 1e-9, name


@pytest.mark.parametrize("ranges", [(), (CONFIG_DIR / "stress.yaml",)], ids=["matrix", "stress"])
def test_random_worlds_stay_in_their_ranges_and_repeat_for_a_seed(ranges):
    r = load_randomizer(ranges)
    specs = [random_world(seed, r, CONFIG, ROBOT) for seed in range(40)]  # the configuration read once
    assert random_world(7, load_randomizer(ranges)) == specs[7]  # and read again: the same world
    if not ranges:
        assert random_world(7) == specs[7]  # read by random_world itself
    drawn = {s.layout for s in specs if s.layout.startswith("drawn")}  # users' layouts (tests/test_layouts.py)
    assert {s.layout for s in specs} - drawn == set(r.layouts) and drawn and {s.object_name for s in specs} == set(r.objects)
    assert 0 < sum(s.bare_naoqi for s in specs) < len(specs)  # some worlds are served by a bare NAOqi, not all
    configured = ROBOT.camera.intrinsics("qvga")
    for s in specs:
        assert r.start_distance[0] <= math.dist(s.start[:2], s.scenario.position) <= r.start_distance[1]
        bearing = math.remainder(math.atan2(s.scenario.position[1] - s.start[1], s.scenario.position[0] - s.start[0]) - s.start[2], math.tau)
        assert abs(bearing) <= r.start_bearing + 1e-9
        room = s.config.room.half_size
        assert max(abs(s.start[0]), abs(s.start[1])) < room and load_landmark_map(s.landmark_path).landmarks
        true = s.robot.camera.intrinsics("qvga")
        assert abs(true.fx / configured.fx - 1.0) == pytest.approx(r.focal_error)
        assert abs(true.cx - configured.cx) == pytest.approx(r.principal_error)
        # the lens: drawn within its ranges, the same at every resolution, and told the station as calibrated
        assert all(abs(k) <= bound for k, bound in zip(s.lens, (*r.lens_distortion, r.lens_distortion[2], 0.0)))
        assert {i.dist for i in s.robot.camera.resolutions.values()} == {s.lens} and s.lens[4] == 0.0
        told = s.station_overrides()["robot"]["camera"]["resolutions"]
        assert all(told[name]["dist"] == list(s.lens) for name in s.robot.camera.resolutions)
        assert s.station_robot().camera.intrinsics("qvga") == dataclasses.replace(configured, dist=s.lens)
        assert r.latency[0] <= s.config.noise.latency[0] <= s.config.noise.latency[1] <= r.latency[1]
        for name in ("pixel_sigma", "blur_sigma", "exposure", "shutter"):
            low, high = getattr(r, name)
            assert low <= getattr(s.config.noise, name) <= high, name
        looks = s.config.room
        assert looks.floor_color in r.floor_colors and looks.wall_color in r.wall_colors
        assert math.sin(r.light_elevation[0]) - 1e-9 <= looks.light[2] <= math.sin(r.light_elevation[1]) + 1e-9
        assert math.hypot(*looks.light) == pytest.approx(1.0) and r.ambient[0] <= looks.ambient <= r.ambient[1]
        balls = load_landmark_map(s.landmark_path).ball_colors
        assert s.object_color not in balls and s.scenario.color == tuple(r.object_colors[s.object_color])
        assert s.config.scenarios[s.object_name] == s.scenario  # what the simulator renders
    assert {s.object_color for s in specs} == set(r.object_colors)
    for i, bound in enumerate(r.lens_distortion):  # each coefficient of either sign, and some near its bound
        k = np.array([s.lens[i] for s in specs])
        assert k.min() < 0.0 < k.max() and np.abs(k).max() > 0.8 * bound, (i, k)
    assert len({s.config.room for s in specs}) == len(specs)  # every world looks different
    assert {s.config.room.floor_color for s in specs} == set(r.floor_colors)
    world = RandomWorld(specs[0])
    assert world.true_pose() == pytest.approx(specs[0].start) and world.truth()["odom_origin"] == pytest.approx(list(specs[0].start))


def test_the_tone_curve_is_told_the_station_or_not(tmp_path):
    """A world's tone curve is drawn within its range and rendered either way; told (the matrix), the
    station's camera holds it (``station_overrides``, ``station_robot``); untold (``response_gamma_told``
    false: a user who never ran ``station calibrate``), the station keeps the configured linear camera."""
    untold_file = tmp_path / "untold.yaml"
    untold_file.write_text("randomizer:\n  response_gamma: [0.45, 0.45]\n  response_gamma_told: false\n")
    r, untold = load_randomizer(), load_randomizer([untold_file])
    for seed in range(5):
        told_spec, untold_spec = random_world(seed, r, CONFIG, ROBOT), random_world(seed, untold, CONFIG, ROBOT)
        gamma = told_spec.config.noise.response_gamma
        assert r.response_gamma[0] <= gamma <= r.response_gamma[1]
        assert told_spec.station_overrides()["robot"]["camera"]["response_gamma"] == gamma
        assert told_spec.station_robot().camera.response_gamma == gamma
        assert untold_spec.config.noise.response_gamma == 0.45  # rendered ...
        assert "response_gamma" not in untold_spec.station_overrides().get("robot", {}).get("camera", {})  # ... not told
        assert untold_spec.station_robot().camera.response_gamma == ROBOT.camera.response_gamma == 1.0


def test_the_stress_ranges_reach_beyond_the_matrix_ranges():
    """config/stress.yaml is harsher: each range it sets reaches at least the matrix's worst end (the top;
    for the start distance, the bottom too: nearer), and a scalar is larger."""
    matrix, stress = load_randomizer(), load_randomizer([CONFIG_DIR / "stress.yaml"])
    widened = [f.name for f in dataclasses.fields(matrix) if getattr(matrix, f.name) != getattr(stress, f.name)]
    assert len(widened) >= 10
    for name in widened:
        low, high = getattr(matrix, name), getattr(stress, name)
        if name == "drawn_layout":
            assert high.share > low.share and dataclasses.replace(high, share=low.share) == low
        elif name == "objects":
            assert set(high) > set(low)  # the matrix's objects and more
        elif isinstance(low, tuple):
            assert low[1] <= high[1] and high != low and (name != "start_distance" or high[0] < low[0]), name
        else:
            assert high > low, name


def test_a_malformed_ranges_file_is_refused_by_name(tmp_path, capsys):
    """``--ranges`` with a wrong range: exit 2 naming the file, the key and the rule, and no mission run."""
    from tools.matrix import main

    bad = tmp_path / "ranges.yaml"
    bad.write_text("randomizer:\n  start_distance: [2.0, 1.0, 3.0]\n")
    with pytest.raises(SystemExit) as stop:
        main(["--ranges", str(bad), "--count", "1", "--out", str(tmp_path / "runs"), "--doc", str(tmp_path / "doc.md")])
    assert stop.value.code == 2
    assert f"{bad}: randomizer.start_distance: expected a list of 2 items" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "doc.md").exists()


def test_a_lens_range_whose_model_folds_inside_the_image_is_refused(tmp_path, capsys):
    """k1 = -0.25 with k2 = -0.1: OpenCV's polynomial turns back before the image's corner (its largest
    radius 0.66 < 0.68), so no undistortion exists there and the renderer could not draw the frame."""
    from tools.matrix import main

    bad = tmp_path / "ranges.yaml"
    bad.write_text("randomizer:\n  lens_distortion: [0.25, 0.1, 0.0]\n")
    with pytest.raises(SystemExit) as stop:
        main(["--ranges", str(bad), "--count", "1", "--out", str(tmp_path / "runs"), "--doc", str(tmp_path / "doc.md")])
    assert stop.value.code == 2
    assert "lens_distortion [0.25, 0.1, 0.0]: a lens of k1 = -0.25, k2 = -0.1 folds back" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_a_ranges_file_naming_an_unknown_object_is_refused_by_name(tmp_path, capsys):
    """An object that is no scenario of config/sim.yaml: exit 2 naming the file and the object before any
    mission, not a KeyError when a world draws it."""
    from tools.matrix import main

    bad = tmp_path / "ranges.yaml"
    bad.write_text("randomizer:\n  objects: [can, teapot]\n")
    with pytest.raises(SystemExit) as stop:
        main(["--ranges", str(bad), "--count", "1", "--out", str(tmp_path / "runs"), "--doc", str(tmp_path / "doc.md")])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "randomizer.objects: 'teapot' is not a scenario of config/sim.yaml" in err
    assert not (tmp_path / "runs").exists()


def test_one_wall_worlds_and_stress_ranges_are_not_mixed(tmp_path, capsys):
    """``--one-wall`` and ``--ranges`` write different sections: both at once is refused, no mission run."""
    from tools.matrix import main

    with pytest.raises(SystemExit) as stop:
        main(["--one-wall", "--ranges", "config/stress.yaml", "--count", "1", "--out", str(tmp_path / "runs"),
              "--doc", str(tmp_path / "doc.md")])
    assert stop.value.code == 2 and "--one-wall and --ranges" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "doc.md").exists()


@pytest.mark.parametrize("paint", ["floor_colors", "wall_colors"])
def test_the_randomized_rooms_are_painted_in_no_colour_the_perception_looks_for(paint):
    """A floor or wall in the object's colour, or a landmark's, is a room the colour segmentation
    cannot work in (docs/perception.md): every paint, from the darkest shade the randomized light and
    exposure give it to the brightest, stays out of every colour class."""
    r = load_randomizer()
    darkest = r.ambient[0] * r.exposure[0]
    for bgr in getattr(r, paint):
        shades = np.clip(np.outer(np.linspace(darkest, r.exposure[1], 64), bgr), 0, 255).astype(np.uint8)
        hsv = cv2.cvtColor(shades.reshape(1, -1, 3), cv2.COLOR_BGR2HSV)
        taken = [name for name, colour in PERCEPTION.colors.items() if color_mask(hsv, colour).any()]
        assert not taken, (bgr, taken)


def test_every_object_paint_stays_in_its_colour_class_from_the_darkest_room_to_the_brightest():
    """The object's paint (``object_colors``) is seen by its class in every light the randomizer
    draws: from the shade of a side turned away from the light in the dimmest room (ambient times
    exposure, lowest) to a lit side in the brightest, so the silhouette keeps its whole width."""
    r = load_randomizer()
    darkest = r.ambient[0] * r.exposure[0]
    for name, bgr in r.object_colors.items():
        shades = np.clip(np.outer(np.linspace(darkest, r.exposure[1], 64), bgr), 0, 255).astype(np.uint8)
        hsv = cv2.cvtColor(shades.reshape(1, -1, 3), cv2.COLOR_BGR2HSV)
        assert color_mask(hsv, PERCEPTION.colors[name]).all(), name


# --- missions -------------------------------------------------------------------------------------

BRIDGE = load(BridgeParams, [CONFIG_DIR / "bridge.yaml"], section="bridge")
SELF_CALIBRATION = load(SelfCalibrationParams, [CONFIG_DIR / "self_calibration.yaml"], section="self_calibration")
# Worlds (docs/benchmarks.md, matrix section; docs/testing.md): in the default suite seed 23,
# coloured balls on the walls (four colours, six of each) and the bunny mesh, 2 deg of sway roll, 6 %
# of frames dropped: unlike the configured world of tests/test_station_mission.py in layout, object
# shape and size, sway and resolution. Slow: seed 36 a drawn room of balls (4.6 m, 40 balls) and a
# 6.6 x 12 cm soda can, seed 11 a drawn room of markers (3.6 m, 21 markers) and the soda can, seed 1
# the low ring and the figure, seed 0 a drawn mixed room (5 m, 46 landmarks) and the bunny, seed 2
# wall markers and a TV remote lying flat, seed 4 the sparse layout and a bucket, seed 12 the small
# 3 x 3 m room and the remote (drawn rooms: nao_sim/layouts.py).
# The bounds below are derived from each world's object, not from a run.
SLOW_SEEDS = [36, 11, 1, 0, 2, 4, 12]


@pytest.fixture(scope="module", params=[CI_SEED] + [pytest.param(s, marks=pytest.mark.slow) for s in SLOW_SEEDS])
def mission(request, tmp_path_factory):
    """The mission in world ``request.param`` at the station's resolution; the default suite's (tests/conftest.py) is shared."""
    from tools.matrix import run_mission

    if request.param == CI_SEED:
        return request.getfixturevalue("ci_mission")
    return run_mission(request.param, tmp_path_factory.mktemp(f"matrix{request.param}"))


def test_matrix_mission_completes_accurately_and_stops(mission):
    r = mission
    spec = random_world(r.seed)
    assert r.outcome == "completed", f"{r.world}: {r.reason}"
    # a quarter of the object's radius (the smallest enclosing cylinder's): the estimated centre lies
    # well inside the object; the estimated cylinder is the object's size seen from all round (its
    # mean half-breadth, tools/matrix.py), for any shape
    assert r.centre_error <= 0.25 * spec.scenario.radius, r.world  # the carved model's centroid (docs/result.md)
    assert r.filter_centre_error <= 0.25 * spec.scenario.radius, r.world
    assert abs(r.radius_error) <= 0.25 * spec.scenario.mean_half_breadth, r.world  # against the apparent-width radius
    assert r.iou >= 0.5, r.world  # more of the model is object than not
    result = json.loads((Path(r.out) / "run" / "result.json").read_text())
    assert result["status"] == "success" and result["coverage"] >= 0.90
    # the centre is the carved model's centroid (station/result.py), the filter's is kept beside it
    estimate = result["object"]
    assert estimate["centre_source"] == "model"
    assert [estimate["x"], estimate["y"]] == result["model"]["metrics"]["centroid"][:2] != [estimate["filter_x"], estimate["filter_y"]]
    for name in ("run.mcap", "model.ply", "model.glb", "voxels.npz", "trajectory.png", "cameras.png", "progress.png"):
        assert (Path(r.out) / "run" / name).stat().st_size > 0, name
    # issue 12: never nearer than 0.35 m (the planner keeps 0.45 m from the estimated surface)
    assert r.min_clearance >= 0.35, r.world
    # nor nearer a wall than the planner's wall clearance, or than it started (agent/keep_in.py), 5 cm of walking error
    start_wall = spec.config.room.half_size - max(abs(spec.start[0]), abs(spec.start[1]))
    assert r.min_wall_distance >= min(start_wall, load_planner_params().wall_clearance) - 0.05, r.world
    assert r.stopped
    # the stop reaches the robot within the bridge's deadman after the final decision (the station
    # sends a zero walk at once; the deadman stops the robot anyway); 1 s margin for a loaded machine
    assert r.stop_delay is not None and r.stop_delay <= BRIDGE.deadman_s + 1.0
    # a self-calibrated camera is within two of the focal-scale std it is applied at (0.3 %) of the
    # truth: 0.6 %, a little over the configured error of 0.5 % (an estimate from fixes made while the
    # head turned was 0.7 % off in seed 13, worse than none). Seed 23 (colours, a bunny, the camera
    # tilted on its mount) ends 0.06-0.53 % off across runs (0.42 % at a std of 0.28 % once; a CI run
    # on a slow day 0.53 %, over the configured error this bound was before); the matrix tracks the
    # median and the largest (docs/benchmarks.md: median 0.08 %, at most 0.45 % over 40 missions)
    assert not r.self_calibrated or r.focal_error < 2.0 * SELF_CALIBRATION.max_scale_std, r.focal_error
    # the camera's tilt on its mount learnt (agent/camera_tilt.py): within 0.3 deg on both axes, the
    # pitch against the mount's with the principal point's error (tools/matrix.py; the matrix at
    # 76a303c: median 0.02 deg, at most 0.11 deg over 39 missions)
    assert r.tilt_error is not None and max(r.tilt_error) <= math.radians(0.3), r.tilt_error


def test_an_empty_model_is_written_not_raised(tmp_path):
    """A mission whose carve kept no voxel (a 4 cm box carved away) still writes its model files:
    trimesh cannot write empty vertex colours, so an empty mesh is left uncoloured."""
    from agent.mesh import colour_vertices, occupancy_to_mesh, save_mesh

    mesh = colour_vertices(occupancy_to_mesh(np.zeros((4, 4, 4), bool), np.zeros(3), 0.01), [])
    for suffix in (".ply", ".glb"):
        assert save_mesh(mesh, tmp_path / f"model{suffix}").exists()
