"""Silhouettes and bearing/width measurements against ground truth: drawn cylinders with known
geometry, simulator renders with known poses, the Middlebury temple with its published box."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent import perception
from agent.camera import CameraModel, optical_axis_heading
from agent.perception import (
    ColorClass,
    ColourTally,
    ImageError,
    PerceptionParams,
    extract_silhouette,
    measure_object,
    outline_edges,
)
from agent.tone_curve import in_light
from nao_core.config import CONFIG_DIR, ConfigError, from_mapping, load
from nao_core.geometry import planar_transform, wrap_angle
from nao_sim.scenarios import load_sim_config
from nao_sim.world import SimWorld
from tools.benchmarks.bench_perception_width import renderer_fattening_px

from tests.conftest import MIDDLEBURY_TEMPLE as TEMPLE  # ../shared from the repository root
RED_BGR = (35, 35, 200)
GREY_BGR = (128, 128, 128)
SUPERSAMPLE = 8


@pytest.fixture(scope="module")
def params() -> PerceptionParams:
    return load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")


def camera_of(robot, resolution: str) -> CameraModel:
    intr = robot.camera.intrinsics(resolution)
    return CameraModel.from_intrinsics(intr)


def cylinder_coverage(camera: CameraModel, T_WC: np.ndarray, centre, radius: float, height: float) -> np.ndarray:
    """Fraction of each pixel covered by a vertical cylinder (8x supersampled exact polygon fill), H x W float."""
    a = np.linspace(0.0, 2.0 * math.pi, 720, endpoint=False)
    ring = np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)])
    points = np.vstack([np.column_stack([ring, np.zeros(len(a))]), np.column_stack([ring, np.full(len(a), height)])])
    uv, in_front = camera.project_world(points, T_WC)
    assert in_front.all()
    hull = cv2.convexHull(np.round((uv + 0.5) * SUPERSAMPLE * 16 - 0.5 * 16).astype(np.int32))
    fine = np.zeros((camera.height * SUPERSAMPLE, camera.width * SUPERSAMPLE), np.uint8)
    cv2.fillConvexPoly(fine, hull, 255, lineType=cv2.LINE_8, shift=4)
    return cv2.resize(fine, (camera.width, camera.height), interpolation=cv2.INTER_AREA) / 255.0


def draw_cylinder(camera: CameraModel, T_WC: np.ndarray, centre, radius: float, height: float) -> np.ndarray:
    """A red vertical cylinder on grey, by an ideal binary sensor: a pixel is red iff the cylinder
    covers at least half of it."""
    image = np.empty((camera.height, camera.width, 3), np.uint8)
    image[:] = GREY_BGR
    image[cylinder_coverage(camera, T_WC, centre, radius, height) >= 0.5] = RED_BGR
    return image


def draw_blurred_cylinder(camera: CameraModel, T_WC: np.ndarray, centre, radius: float, height: float,
                          blur: float, rng: np.random.Generator) -> np.ndarray:
    """Like a real camera: edge pixels mix the two colours by coverage (anti-aliasing), then a
    Gaussian blur of ``blur`` px (optics) and Gaussian noise of 2 grey levels."""
    c = cylinder_coverage(camera, T_WC, centre, radius, height)[..., None]
    image = (1.0 - c) * np.array(GREY_BGR, np.float32) + c * np.array(RED_BGR, np.float32)
    if blur > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur)
    return np.clip(np.round(image + rng.normal(0.0, 2.0, image.shape)), 0, 255).astype(np.uint8)


def cylinder_views(robot, centre, pitch_offsets=(-0.12, 0.0, 0.12)):
    """Camera poses T_WC with the cylinder across the image (five head yaws), at 0.7 and 1.1 m."""
    for pitch_offset in pitch_offsets:
        for yaw_offset in (-0.3, -0.1, 0.0, 0.15, 0.3):
            for distance in (0.7, 1.1):
                pose = (centre[0] - distance, centre[1] - 0.05, 0.1)
                yaw, pitch = robot.look_at(pose, (centre[0], centre[1], 0.1))
                yield planar_transform(*pose) @ robot.camera_in_robot(yaw + yaw_offset, pitch + pitch_offset)


def true_bearing_width(T_WC: np.ndarray, centre, radius: float):
    c = T_WC[:2, 3]
    d = math.hypot(centre[0] - c[0], centre[1] - c[1])
    phi = wrap_angle(math.atan2(centre[1] - c[1], centre[0] - c[0]) - optical_axis_heading(T_WC))
    return phi, 2.0 * math.asin(radius / d)


@pytest.mark.parametrize("pitch_offset", [-0.12, 0.0, 0.12])
def test_drawn_cylinder_bearing_and_width_within_a_tenth_of_a_degree(params, robot, pitch_offset):
    camera = camera_of(robot, "vga")
    centre, radius, height = (1.1, 0.2), 0.055, 0.20
    errors = []
    for T_WC in cylinder_views(robot, centre, (pitch_offset,)):
        silhouette = extract_silhouette(draw_cylinder(camera, T_WC, centre, radius, height), params)
        assert silhouette is not None and silhouette.width_valid
        m = measure_object(silhouette, camera, T_WC, params)
        phi, delta = true_bearing_width(T_WC, centre, radius)
        errors.append((abs(m.phi - phi), abs(m.delta - delta)))
    assert np.degrees(np.max(errors, axis=0)).tolist() == pytest.approx([0, 0], abs=0.1)


@pytest.mark.parametrize("resolution, blur", [("qvga", 0.0), ("qvga", 1.2), ("vga", 0.0), ("vga", 1.2)])
def test_antialiased_and_blurred_edges_give_an_unbiased_width(params, robot, resolution, blur):
    """Mixed edge pixels pass the colour threshold, so the mask is too wide (by 0.4 px anti-aliased,
    1 px blurred); the sub-pixel edges are unbiased (measured |mean| <= 0.04 px, max 0.09 px)."""
    camera = camera_of(robot, resolution)
    centre, radius, height = (1.1, 0.2), 0.055, 0.20
    rng = np.random.default_rng(0)
    mask_edges = dataclasses.replace(params, edge_window=0)
    subpixel, binary = [], []
    for T_WC in cylinder_views(robot, centre, (0.0, 0.12)):
        image = draw_blurred_cylinder(camera, T_WC, centre, radius, height, blur, rng)
        delta = true_bearing_width(T_WC, centre, radius)[1]
        for p, errors in ((params, subpixel), (mask_edges, binary)):
            errors.append(measure_object(extract_silhouette(image, p), camera, T_WC, p).delta - delta)
    subpixel_px, binary_px = np.array(subpixel) * camera.K[0, 0], np.array(binary) * camera.K[0, 0]
    assert abs(subpixel_px.mean()) < 0.08 and np.abs(subpixel_px).max() < 0.2
    assert binary_px.mean() > 0.3  # what the mask's edges would have given


@pytest.mark.parametrize("floor", [(60, 55, 55), (120, 125, 130), (90, 140, 185), (150, 180, 200)])
def test_an_object_darkening_towards_its_rim_has_its_edges_unmixed_in_place(params, floor):
    """A can's side turns away from the light towards its rims: its shade at the edge (0.55 here) is
    not the shade 3 px in. Rows area-sampled at 64 sub-pixels across edges at 30.3 and 70.7 px on a
    floor of the randomizer's paints: with the object's shade free the edges are within 0.02 px
    (measured 0.007); the projection that fixes the shade to the reference's put them 0.18 and 0.37 px
    inside on the dark carpet (docs/benchmarks.md, perception width per floor)."""
    left, right, width, fine = 30.3, 70.7, 100, 64
    u = (np.arange(width * fine) + 0.5) / fine - 0.5  # sub-pixel centres: pixel i spans [i - 1/2, i + 1/2]
    inside = (u >= left) & (u <= right)
    shade = 0.55 + 0.45 * np.sin(math.pi * np.clip((u - left) / (right - left), 0.0, 1.0))
    colour = np.where(inside[:, None], shade[:, None] * np.array(RED_BGR, float), np.array(floor, float))
    image = np.repeat(colour.reshape(width, fine, 3).mean(axis=1)[None], 8, axis=0).round().astype(np.uint8)
    rows, first, last = np.arange(8), np.full(8, 30), np.full(8, 70)
    edges = {m: outline_edges(image, rows, first, last, dataclasses.replace(params, edge_unmixing=m))
             for m in ("free_shade", "projection")}
    l, r = edges["free_shade"]
    assert np.abs(l[:, 0] - left).max() < 0.02 and np.abs(r[:, 0] - right).max() < 0.02
    assert np.array_equal(l[:, 1], rows)
    if floor == (60, 55, 55):
        l, r = edges["projection"]
        assert (r[:, 0] - l[:, 0]).max() < right - left - 0.3  # the baseline's width, 0.55 px short


@pytest.mark.parametrize("resolution, blur, dim", [("qvga", 0.0, False), ("vga", 0.0, False), ("qvga", 1.0, False),
                                                  ("vga", 1.0, False), ("vga", 0.0, True)])
def test_sim_render_bearing_and_width_match_truth(params, robot, resolution, blur, dim):
    """Simulator frames, sharp or blurred by 1 px (at VGA): bearing within 0.1 deg and width within
    0.3 px of the truth (the renderer's area-exact anti-aliased fill paints no edge outside its true
    place; over the floor's texture a 2 px unmixing window put a blurred can's edges 0.27 px inside).
    Dim: the matrix's darkest room (a low light from one side, ambient 0.4, exposure 0.6), where the
    can's shaded side is R = 48 (docs/perception.md "Colours": the class starting at value 50 lost it)."""
    config = load_sim_config()
    noise = dataclasses.replace(config.noise, blur_sigma=blur, exposure=0.6 if dim else config.noise.exposure)
    room = dataclasses.replace(config.room, light=(0.8, 0.3, 0.5), ambient=0.4) if dim else config.room
    world = SimWorld("can", robot, resolution, seed=3, config=dataclasses.replace(config, noise=noise, room=room))
    camera = camera_of(robot, resolution)
    assert renderer_fattening_px(polygons=20) == pytest.approx(0.0, abs=0.015)  # cv2 alone fills span ends inclusively: +1/16 px
    centre, radius = np.array(world.scenario.position), world.scenario.radius
    errors = []
    for distance, azimuth, turn in [(0.6, 0.3, 0.0), (1.0, 2.0, 0.25), (1.3, -1.5, -0.25), (0.9, -3.0, 0.1)]:
        pose = (centre[0] + distance * math.cos(azimuth), centre[1] + distance * math.sin(azimuth), azimuth + math.pi + turn)
        world.teleport(pose, robot.look_at(pose, (*centre, 0.1)))
        frame = world.render()
        T_WC = np.array(world.truth()["camera"]["T_WC"])
        m = measure_object(extract_silhouette(frame.image, params), camera, T_WC, params)
        phi, delta = true_bearing_width(T_WC, centre, radius)
        assert abs(m.phi - phi) < math.radians(0.1)
        errors.append(m.delta - delta)
    assert np.abs(errors).max() < 0.3 / camera.K[0, 0]


@pytest.mark.parametrize("gamma", [0.45, 1.6])
def test_a_camera_s_tone_curve_leaves_the_width_unbiased_through_its_inverse(params, robot, gamma):
    """Simulator frames (VGA, 1 px of blur) through a camera's tone curve (sRGB about 0.45): unmixed in
    pixel values, the edges' mixed pixels read as more object (gamma < 1) or less, and the can's width
    is off by a pixel (measured -0.9 to -1.07 px at 0.45, +0.46 to +0.49 at 1.6); the frame taken back
    to light (the inverse curve, as station/pilot.py reads frames; docs/frames.md "The camera's tone
    curve"), it is within 0.25 px, as a linear camera's (-0.14 to -0.21 px measured, -0.14 to -0.19)."""
    config = load_sim_config()
    noise = dataclasses.replace(config.noise, blur_sigma=1.0, response_gamma=gamma)
    world = SimWorld("can", robot, "vga", seed=3, config=dataclasses.replace(config, noise=noise))
    camera = camera_of(robot, "vga")
    centre, radius = np.array(world.scenario.position), world.scenario.radius
    encoded, linear = [], []
    for distance, azimuth, turn in [(0.6, 0.3, 0.0), (1.0, 2.0, 0.25), (1.3, -1.5, -0.25), (0.9, -3.0, 0.1)]:
        pose = (centre[0] + distance * math.cos(azimuth), centre[1] + distance * math.sin(azimuth), azimuth + math.pi + turn)
        world.teleport(pose, robot.look_at(pose, (*centre, 0.1)))
        image, T_WC = world.render().image, np.array(world.truth()["camera"]["T_WC"])
        delta = true_bearing_width(T_WC, centre, radius)[1]
        encoded.append(measure_object(extract_silhouette(image, params), camera, T_WC, params).delta - delta)
        light = in_light(image, gamma)  # as the station reads a frame (station/pilot.py)
        linear.append(measure_object(extract_silhouette(light, params), camera, T_WC, params).delta - delta)
    encoded_px, linear_px = np.array(encoded) * camera.K[0, 0], np.array(linear) * camera.K[0, 0]
    assert np.abs(encoded_px).min() > 0.4  # the bias the inverse curve removes
    assert np.abs(linear_px).max() < 0.25, linear_px


def test_coarse_colour_region_gives_the_full_frame_silhouette(params, robot, monkeypatch):
    """The mask is computed only where the frame reduced to 160 px shows the colour: on simulator
    frames (object near, far, cut by the border, absent) the result equals the whole frame's."""
    world = SimWorld("can", robot, "vga", seed=1)
    centre = np.array(world.scenario.position)
    images = []
    for distance, azimuth, head_yaw in [(0.6, 0.3, 0.0), (2.5, 2.0, 0.1), (1.0, -1.5, 0.45), (1.0, 1.0, -0.45), (1.0, 0.0, 2.0)]:
        pose = (centre[0] + distance * math.cos(azimuth), centre[1] + distance * math.sin(azimuth), azimuth + math.pi)
        yaw, pitch = robot.look_at(pose, (*centre, 0.1))
        world.teleport(pose, (yaw + head_yaw, pitch))
        images.append(world.render().image)
    coarse = [extract_silhouette(image, params) for image in images]
    monkeypatch.setattr(perception, "COARSE_WIDTH", 10**6)  # f = 1: the whole frame
    for image, found in zip(images, coarse):
        whole = extract_silhouette(image, params)
        assert (found is None) == (whole is None)
        if whole is not None:
            assert np.array_equal(found.mask, whole.mask) and found.bbox == whole.bbox
            assert np.array_equal(found.left_edge, whole.left_edge) and np.array_equal(found.right_edge, whole.right_edge)
    # near, far, cut by the right and by the left border, absent:
    assert sum(s is None for s in coarse) == 1 and sum(not s.width_valid for s in coarse if s is not None) == 2


def test_cut_by_a_side_border_gives_a_bearing_and_no_width(params, robot):
    camera = camera_of(robot, "vga")
    centre = (1.0, 0.0)
    for yaw in (0.5, -0.5):  # object cut by the right, then the left border
        T_WC = robot.camera_in_robot(yaw, 0.3)
        silhouette = extract_silhouette(draw_cylinder(camera, T_WC, centre, 0.06, 0.2), params)
        assert silhouette.touches_right == (yaw > 0) and silhouette.touches_left == (yaw < 0)
        m = measure_object(silhouette, camera, T_WC, params)
        assert m.delta is None and math.isfinite(m.phi) and not m.bearing_valid
        assert np.sign(m.phi) == np.sign(true_bearing_width(T_WC, centre, 0.06)[0])


@pytest.mark.parametrize("border, yaw_offset, pitch_offset", [
    (None, 0.0, 0.0), ("bottom", 0.0, -0.42), ("top", 0.0, 0.42), ("left", -0.55, 0.0), ("right", 0.55, 0.0)])
def test_rendered_silhouettes_cut_by_any_border_give_no_width(params, robot, border, yaw_offset, pitch_offset):
    """Issue 12: simulator frames of the can 0.8 m away with the head turned off it (offsets beyond
    half the field of view minus half the can's angular size) so that one border cuts it. Cut at
    the top or bottom: the bearing of the visible rows is still the cylinder's (its tangent planes
    are vertical), no width. Cut at a side: neither. Uncut: both, and the top and bottom rows are
    those of the projected can (within the renderer's anti-aliasing, 1.5 px)."""
    world = SimWorld("can", robot, "vga", seed=2)
    camera = camera_of(robot, "vga")
    centre, radius, height = np.array(world.scenario.position), world.scenario.radius, world.scenario.height
    pose = (centre[0] - 0.8, centre[1] + 0.02, 0.05)  # far enough for the pitch limits to aim at mid-height
    yaw, pitch = robot.look_at(pose, (*centre, 0.5 * height))
    T_WC = planar_transform(*pose) @ robot.camera_in_robot(yaw + yaw_offset, pitch + pitch_offset)  # the renderer takes any pose
    m = measure_object(extract_silhouette(world.renderer.render(T_WC, 1), params), camera, T_WC, params)
    assert m.cut == (() if border is None else (border,))
    assert (m.delta is None) == (border is not None)
    assert m.bearing_valid == (border not in ("left", "right"))
    phi, delta = true_bearing_width(T_WC, centre, radius)
    if m.bearing_valid:
        assert abs(m.phi - phi) < math.radians(0.1)
    if border is None:
        assert abs(m.delta - delta) < 0.5 / camera.K[0, 0]
        uv, _ = camera.project_world(world.scenario.world_points(), T_WC)
        assert abs(m.top_row - uv[:, 1].min()) < 1.5 and abs(m.bottom_row - uv[:, 1].max()) < 1.5
    elif border == "top":
        assert m.top_row == 0
    elif border == "bottom":
        assert m.bottom_row == camera.height - 1


def test_red_wraps_through_hue_zero_and_morphology_removes_speckle(params):
    hsv = np.zeros((120, 160, 3), np.uint8)
    hsv[..., 1:] = 200
    hsv[..., 0] = 100  # blue-ish background
    hsv[20:60, 20:60, 0] = 175  # red below 180 ...
    hsv[20:60, 60:100, 0] = 3  # ... and red above 0: one object
    hsv[100, 140, 0] = 0  # a single red speck
    image = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    s = extract_silhouette(image, params)
    assert s.bbox == (20, 20, 80, 40) and s.area == 80 * 40 - 4  # the 3 x 3 cross opening rounds corners
    assert s.mask.dtype == np.uint8 and set(np.unique(s.mask)) == {0, 255} and s.mask[100, 140] == 0
    assert s.left_px[0] == 20 and s.right_px[0] == 99 and s.centroid == pytest.approx((59.5, 39.5))
    assert not (s.touches_left or s.touches_right or s.touches_top or s.touches_bottom)


def test_component_choice_largest_or_nearest_the_prediction(params):
    image = np.full((120, 160, 3), 128, np.uint8)
    image[10:50, 10:50] = RED_BGR  # large, top left
    image[80:100, 120:140] = RED_BGR  # small, bottom right
    largest = dataclasses.replace(params, component="largest")
    nearest = dataclasses.replace(params, component="nearest")
    assert extract_silhouette(image, largest, predicted_uv=(130, 90)).bbox == (10, 10, 40, 40)
    assert extract_silhouette(image, nearest, predicted_uv=(130, 90)).bbox == (120, 80, 20, 20)
    assert extract_silhouette(image, nearest).bbox == (10, 10, 40, 40)
    assert np.count_nonzero(extract_silhouette(image, nearest, predicted_uv=(130, 90)).mask) == 400 - 4


def test_no_object_gives_none(params):
    assert extract_silhouette(np.full((240, 320, 3), 128, np.uint8), params) is None


@pytest.mark.parametrize(
    "garbage, message",
    [
        (None, "numpy array"),
        (b"\xff\xd8 not an image", "numpy array"),
        ([[1, 2, 3]], "numpy array"),
        (np.zeros((0, 0, 3), np.uint8), "too small"),
        (np.zeros((4, 4, 3), np.uint8), "too small"),
        (np.zeros((240, 320), np.uint8), "H x W x 3"),
        (np.zeros((240, 320, 4), np.uint8), "H x W x 3"),
        (np.zeros((240, 320, 3), np.float32), "dtype"),
        (np.zeros(1000, np.uint8), "H x W x 3"),
    ],
)
def test_garbage_images_raise_a_clear_image_error(params, garbage, message):
    with pytest.raises(ImageError, match=message):
        extract_silhouette(garbage, params)


def test_wrong_size_is_rejected_when_the_size_is_given(params):
    with pytest.raises(ImageError, match="camera's is 640 x 480"):
        extract_silhouette(np.zeros((240, 320, 3), np.uint8), params, size=(640, 480))
    assert issubclass(ImageError, ValueError)


def test_config_rejects_an_unknown_object_colour_and_bad_ranges(params):
    raw = {"colors": {"red": {"hue": [170, 8], "saturation": [100, 255], "value": [50, 255]}}, "object_color": "blue",
           **{f.name: getattr(params, f.name) for f in dataclasses.fields(params) if f.name not in ("colors", "object_color")}}
    with pytest.raises((ConfigError, ValueError), match="object_color"):
        from_mapping(PerceptionParams, raw)
    raw["object_color"] = "red"
    raw["colors"]["red"]["hue"] = [170, 300]
    with pytest.raises(ConfigError, match="hue"):
        from_mapping(PerceptionParams, raw)


def temple_views():
    for line in (TEMPLE / "templeSR_par.txt").read_text().splitlines()[1:]:
        if line.strip():
            name, *numbers = line.split()
            values = np.array(numbers, dtype=float)
            yield name, values[:9].reshape(3, 3), values[9:18].reshape(3, 3), values[18:21]


WIDTH_TOLERANCE = 0.005  # m: the model's width target (issue 13, docs/benchmarks.md "model")


@pytest.mark.usefixtures("middlebury_temple")  # a missing data set fails with its path
def test_temple_silhouettes_lie_inside_the_projected_bounding_box(params):
    """16 real views, near-black background: a 'bright' class (any hue, some saturation and light)."""
    bright = dataclasses.replace(
        params, colors={"bright": ColorClass(hue=(0, 179), saturation=(80, 255), value=(60, 255))},
        object_color="bright", component="largest", open_radius=2, close_radius=2,
    )
    lo, hi = np.array([-0.073568, 0.021728, -0.012445]), np.array([0.028855, 0.181892, 0.062736])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    views = list(temple_views())
    assert len(views) == 16
    for name, K, R, t in views:
        silhouette = extract_silhouette(cv2.imread(str(TEMPLE / name)), bright)
        assert silhouette is not None, name
        uv = (corners @ R.T + t) @ K.T
        box = np.zeros_like(silhouette.mask)
        cv2.fillConvexPoly(box, cv2.convexHull(np.round(uv[:, :2] / uv[:, 2:]).astype(np.int32)), 255)
        # A silhouette may overstate the object by no more than the model may (issue 13: width
        # within 5 mm, so 2.5 mm a side), seen at the box's nearest corner, plus the rounding of
        # the box polygon to whole pixels (half a pixel diagonal).
        allowed = 0.5 * WIDTH_TOLERANCE * K[0, 0] / (corners @ R.T + t)[:, 2].min() + math.sqrt(0.5)
        outside = cv2.distanceTransform(255 - box, cv2.DIST_L2, 5)[silhouette.mask > 0].max()
        assert outside <= allowed, f"{name}: silhouette reaches {outside:.1f} px outside the projected box (allowed {allowed:.1f})"
        assert silhouette.area > 0.3 * np.count_nonzero(box), f"{name}: silhouette too small"


def test_cleaning_in_the_masks_bounding_box_equals_full_frame_morphology(params):
    from agent.perception import _disc, clean_mask

    rng = np.random.default_rng(0)
    for _ in range(100):
        mask = np.zeros((120, 160), np.uint8)
        for _ in range(rng.integers(0, 4)):
            centre = (int(rng.integers(0, 160)), int(rng.integers(0, 120)))
            cv2.circle(mask, centre, int(rng.integers(1, 15)), 255, -1)
        mask[rng.random(mask.shape) < 0.002] = 255
        p = dataclasses.replace(params, open_radius=int(rng.integers(0, 3)), close_radius=int(rng.integers(0, 4)))
        full = mask
        if p.open_radius:
            full = cv2.morphologyEx(full, cv2.MORPH_OPEN, _disc(p.open_radius))
        if p.close_radius:
            full = cv2.morphologyEx(full, cv2.MORPH_CLOSE, _disc(p.close_radius))
        assert np.array_equal(clean_mask(mask, p), full)


def test_a_tally_names_the_free_colour_classes_that_filled_silhouettes_where_the_object_s_did_not(params):
    """``ColourTally``: every ``every``-th frame it is given, the classes neither the object's nor a
    ball's of the map are searched; a blue box in every frame (and a green one, the map's balls' colour)
    is named after ``min_frames`` searched frames, green never; frames of the bare floor add nothing."""
    floor = np.full((240, 320, 3), (120, 130, 140), np.uint8)
    frame = floor.copy()
    cv2.rectangle(frame, (40, 60), (80, 140), (200, 80, 30), -1)  # blue (BGR)
    cv2.rectangle(frame, (200, 60), (240, 140), (40, 200, 40), -1)  # green
    assert extract_silhouette(frame, params, color="blue") is not None and extract_silhouette(frame, params, color="green") is not None
    tally = ColourTally(params, taken={"green"}, every=2)
    assert "green" not in tally.free and params.object_color not in tally.free
    for first, second in [(floor, frame)] * 2 + [(frame, floor)] * 2:  # searched: the 2nd, 4th, 6th and 8th
        tally.look(first)
        tally.look(second)
    assert tally.note() == ""  # blue in 2 of the 4 searched frames, fewer than min_frames
    tally.look(floor)
    tally.look(frame)
    note = tally.note()
    assert note.startswith(f"silhouettes of other colour classes were seen where none of {params.object_color} was (blue in 3 of 5")
    assert "green" not in note
