"""Camera geometry against ground truth: rays, projections, azimuths, the NAO-to-optical conversion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.camera import CameraModel, optical_axis_heading
from nao_core.geometry import (
    camera_in_world,
    invert,
    planar_pose,
    planar_transform,
    wrap_angle,
)
from nao_core.robot_model import R_NAO_OPTICAL, load_robot_model, nao_to_optical
from tests.tangents import bearing_width_from_pixels

ROBOT = load_robot_model()


def distorted_camera() -> CameraModel:
    intr = ROBOT.camera.intrinsics("vga")
    return CameraModel(K=intr.K, dist=np.array([-0.08, 0.05, 0.001, -0.0005, 0.0]), width=640, height=480)


def test_wrap_angle_range_and_pi():
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    a = wrap_angle(np.linspace(-20, 20, 1001))
    assert np.all(a > -math.pi) and np.all(a <= math.pi)
    assert np.allclose(np.sin(a), np.sin(np.linspace(-20, 20, 1001)))


def test_nao_to_optical_axes():
    """Optical z is NAO's x (forward), optical x is NAO's -y (right), optical y is NAO's -z (down)."""
    assert np.allclose(R_NAO_OPTICAL @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R_NAO_OPTICAL @ [1, 0, 0], [0, -1, 0])
    assert np.allclose(R_NAO_OPTICAL @ [0, 1, 0], [0, 0, -1])
    T = nao_to_optical(np.eye(4))
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_head_kinematics_height_and_direction():
    T = ROBOT.camera_in_robot(0.0, 0.0)
    assert 0.45 < T[2, 3] < 0.55  # the camera is about 0.5 m above the floor
    assert np.allclose(T[:3, 2], [1, 0, 0])  # looking forward
    T = ROBOT.camera_in_robot(0.5, 0.3)  # yaw left, pitch down
    axis = T[:3, 2]
    assert math.atan2(axis[1], axis[0]) == pytest.approx(0.5)
    assert math.asin(-axis[2]) == pytest.approx(0.3)


@settings(max_examples=200, deadline=None)
@given(u=st.floats(5, 635), v=st.floats(5, 475))
def test_pixel_ray_roundtrip_with_distortion(u, v):
    cam = distorted_camera()
    ray = cam.pixels_to_rays(np.array([[u, v]]))
    assert np.linalg.norm(ray) == pytest.approx(1.0)
    assert np.allclose(cam.project(ray * 2.7), [[u, v]], atol=1e-3)


@settings(max_examples=100, deadline=None)
@given(u=st.floats(5, 635), v=st.floats(5, 475))
def test_undistorted_pixels_are_where_the_pinhole_of_k_sees_the_ray(u, v):
    cam = distorted_camera()
    pinhole = CameraModel(K=cam.K, dist=np.zeros(5), width=cam.width, height=cam.height)
    ray = cam.pixels_to_rays(np.array([[u, v]]))
    assert np.allclose(cam.undistort(np.array([[u, v]])), pinhole.project(ray), atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(u=st.floats(0, 639), v=st.floats(0, 479))
def test_distort_inverts_undistort_over_the_image(u, v):
    cam = distorted_camera()
    assert np.allclose(cam.distort(cam.undistort(np.array([[u, v]]))), [[u, v]], atol=1e-6)


def test_a_folding_lens_shows_nothing_beyond_its_field():
    """k1 = -0.12, k2 = -0.05: OpenCV's polynomial folds back beyond r = 1.19 and puts a point 57 deg
    off the axis inside the image's corner; no pixel shows it, and project_world says so."""
    cam = CameraModel(K=distorted_camera().K, dist=np.array([-0.12, -0.05, 0.0, 0.0, 0.0]), width=640, height=480)
    r = 1.55  # normalized radius: 57 deg off the axis, along the image's diagonal
    far = np.array([[r * 0.8, r * 0.6, 1.0]])
    folded = cam.project(far)[0]
    assert 0 <= folded[0] < 640 and 0 <= folded[1] < 480  # the fold is real
    uv, shown = cam.project_world(far, np.eye(4))
    assert not shown[0] and np.all(np.isnan(uv))
    assert np.all(np.isnan(cam.distort(cam.K[:2, :2] @ far[0, :2] + cam.K[:2, 2])))
    corner = cam.pixels_to_rays(np.array([[639.0, 479.0]]))  # the image's own corner stays in the field
    assert cam.project_world(corner * 2.0, np.eye(4))[1].all()


def test_no_points_give_no_pixels_not_an_error():
    """OpenCV's undistortPoints and projectPoints return None for no points: a frame without a landmark."""
    cam = distorted_camera()
    for result in (cam.normalized(np.zeros((0, 2))), cam.undistort(np.zeros((0, 2))), cam.project(np.zeros((0, 3))),
                   cam.pixels_to_rays(np.zeros((0, 2)))):
        assert result.shape[0] == 0


def test_project_world_marks_points_behind():
    cam = CameraModel.from_fov(640, 480, math.radians(57.2))
    T_WC = camera_in_world((0.0, 0.0, 0.0), ROBOT.camera_in_robot(0.0, 0.0))
    uv, front = cam.project_world(np.array([[2.0, 0.0, 0.5], [-2.0, 0.0, 0.5]]), T_WC)
    assert front.tolist() == [True, False]
    # Pinhole by hand: the head straight, the point 0.5 m high seen from the camera's centre
    # (x_c, 0, z_c) of the configured kinematic chain at elevation e, the optical axis tilted down by
    # the configured tilt (NAO's positive pitch): the point lies e + tilt above the axis.
    x_c, _, z_c = ROBOT.camera_in_robot_nao(0.0, 0.0)[:3, 3]
    elevation = math.atan2(0.5 - z_c, 2.0 - x_c)
    f = 320.0 / math.tan(math.radians(57.2) / 2.0)
    assert np.allclose(uv[0], [320.0, 240.0 - f * math.tan(elevation + ROBOT.camera.tilt)], atol=1e-6)


def test_planar_pose_roundtrip_and_inverse():
    T = planar_transform(1.2, -0.4, 2.5)
    assert planar_pose(T) == pytest.approx((1.2, -0.4, 2.5))
    assert np.allclose(invert(T) @ T, np.eye(4))


@settings(max_examples=100, deadline=None)
@given(
    ox=st.floats(0.5, 2.0), oy=st.floats(-0.6, 0.6), r=st.floats(0.02, 0.15),
    yaw=st.floats(-0.4, 0.4), pitch=st.floats(-0.1, 0.5), theta=st.floats(-0.3, 0.3),
    z_left=st.floats(0.0, 0.3), z_right=st.floats(0.0, 0.3),
)
def test_tangent_rays_give_exact_bearing_and_width(ox, oy, r, yaw, pitch, theta, z_left, z_right):
    """docs/estimation.md (tangent-ray measurement): the extreme rays of a vertical cylinder give delta and the centre azimuth
    exactly, whatever the camera pitch and the height at which the extreme pixels lie."""
    cam = distorted_camera()
    T_WC = camera_in_world((0.0, 0.0, theta), ROBOT.camera_in_robot(yaw, pitch))
    c = T_WC[:3, 3]
    d = math.hypot(ox - c[0], oy - c[1])
    a0 = math.atan2(oy - c[1], ox - c[0])
    half = math.asin(r / d)
    run = math.sqrt(d * d - r * r)
    left = [c[0] + run * math.cos(a0 + half), c[1] + run * math.sin(a0 + half), z_left]
    right = [c[0] + run * math.cos(a0 - half), c[1] + run * math.sin(a0 - half), z_right]
    uv, front = cam.project_world(np.array([left, right]), T_WC)
    if not front.all() or not np.all((uv >= 0) & (uv <= [cam.width, cam.height])):
        return  # only pixels the camera can see
    azimuth, phi, delta = bearing_width_from_pixels(cam, uv[0], uv[1], T_WC)
    assert math.degrees(abs(wrap_angle(azimuth - a0))) < 1e-4
    assert math.degrees(abs(delta - 2 * half)) < 1e-4
    assert phi == pytest.approx(wrap_angle(a0 - optical_axis_heading(T_WC)), abs=math.radians(1e-4))
