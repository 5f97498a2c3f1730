"""Station outputs against known geometry: Foxglove ellipses and frusta, result.json, report figures."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.camera import CameraModel
from agent.mission import Outcome
from nao_core.geometry import camera_in_world
from nao_core.protocol import State, Truth, encode, json_schema
from nao_core.protocol.messages import TruthObject
from nao_core.robot_model import load_robot_model
from station import foxglove
from station.mcap_log import LogError, McapLog, read_log
from station.report import write_report
from station.result import (
    EXIT_FAILURE,
    EXIT_SUCCESS,
    EXIT_TIME_LIMIT,
    build_result,
    exit_code,
    log_figures,
    status_of,
)
from station.topics import COVERAGE, EKF, KEYFRAME, MEASUREMENT, POSE, STATE, TRUTH


def test_three_sigma_ellipse_axes():
    angle = 0.6
    R = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    P = R @ np.diag([0.02**2, 0.01**2]) @ R.T
    ring = foxglove.ellipse_points((1.0, 2.0), P, n=400) - (1.0, 2.0)
    local = ring @ R  # back into the principal axes
    assert np.abs(local[:, 0]).max() == pytest.approx(0.06, rel=1e-3)
    assert np.abs(local[:, 1]).max() == pytest.approx(0.03, rel=1e-3)
    assert np.allclose((local[:, 0] / 0.06) ** 2 + (local[:, 1] / 0.03) ** 2, 1.0)


def test_frustum_base_corners_project_to_image_corners():
    camera = CameraModel.from_fov(320, 240, 1.0)
    T_WC = camera_in_world((1.0, -0.5, 0.7), load_robot_model().camera_in_robot(0.3, 0.2))
    lines = foxglove.frusta(0.0, camera, [T_WC]).entities[0].lines[0]
    points = np.array([[p.x, p.y, p.z] for p in lines.points])
    apex, corners = points[0], points[1::4][:4]  # segments: apex-c_i, c_i-c_i+1
    assert np.allclose(apex, T_WC[:3, 3])
    uv, in_front = camera.project_world(corners, T_WC)
    assert in_front.all()
    assert np.allclose(np.sort(uv[:, 0]), [0, 0, 320, 320], atol=1e-6)
    assert np.allclose(np.sort(uv[:, 1]), [0, 0, 240, 240], atol=1e-6)


@pytest.mark.parametrize("outcome", [o.value for o in Outcome] + ["error", "bridge_unavailable"])
def test_status_and_exit_code_tell_success_from_failure(outcome):
    expected = {"completed": ("success", EXIT_SUCCESS), "time_limit": ("incomplete", EXIT_TIME_LIMIT)}
    assert (status_of(outcome), exit_code(outcome)) == expected.get(outcome, ("failure", EXIT_FAILURE))


def state(t: float, x: float, y: float) -> bytes:
    return encode(State(stamp=t, odom=(x, y, 0.0), head_yaw=0.0, head_pitch=0.0, walking=True, fallen=False, battery=0.9,
                        cmd_age=0.0, watchdog="walking", rejected={}, ignored={}))


def truth(t: float) -> bytes:
    obj = TruthObject(kind="cylinder", centre=(0.2, -0.1), yaw=0.0, radius=0.05, height=0.2, parts=())
    return encode(Truth(scenario="can", seed=0, stamp=t, robot_pose=(1.0, 0.0, math.pi), odom_origin=(1.0, 0.0, math.pi),
                        odom=(0.0, 0.0, 0.0), speed_scale=(1.0, 1.0, 1.0), fallen=False, camera=None, object=obj))


@pytest.fixture
def synthetic_log(tmp_path):
    """A walk around a 1 m square (path length 4 m) with estimates converging on the true object."""
    path = tmp_path / "run.mcap"
    corners = [(0, 0), (1, 0), (1, 1), (0, 1), (0, 0)]
    t = 100.0
    cam = load_robot_model().camera_in_robot(0.0, 0.1)
    with McapLog(path) as log:
        for (x0, y0), (x1, y1) in zip(corners, corners[1:]):
            for s in np.linspace(0, 1, 10, endpoint=False):
                x, y = x0 + s * (x1 - x0), y0 + s * (y1 - y0)
                t += 0.1
                log.json(STATE, state(t, x, y), t, json_schema(State))
                log.json(TRUTH, truth(t), t, json_schema(Truth))
                T_WC = camera_in_world((x, y, 0.0), cam)
                log.json(POSE, {"t": t, "seq": 1, "stamp": t, "pose": [x, y, 0.0], "odom": [x, y, 0.0], "landmark_fix": True,
                                "T_WC": T_WC.ravel().tolist()}, t, {"type": "object"})
                err = 0.05 / (t - 99.0)
                log.json(EKF, {"t": t, "x": [0.2 + err, -0.1, 0.05 + err / 10], "P": (np.eye(3) * err**2).tolist(), "stats": {}}, t, {"type": "object"})
                log.json(MEASUREMENT, {"t": t, "cam": [x, y, 0.0], "phi": 0.1, "delta": 0.05}, t, {"type": "object"})
                log.json(COVERAGE, {"t": t, "fraction": min(1.0, t - 100.0)}, t, {"type": "object"})
        log.json(STATE, state(t + 0.1, 0.0, 0.0), t + 0.1, json_schema(State))
        log.json(KEYFRAME, {"t": t, "seq": 1, "azimuth": 0.0, "T_WC": T_WC.ravel().tolist()}, t, {"type": "object"})
    return path


def test_log_figures(synthetic_log):
    figures = log_figures(synthetic_log)
    assert figures["path_length"] == pytest.approx(4.0)
    assert figures["coverage"] == 1.0 and figures["keyframes"] == 1
    assert figures["truth"].object.centre == (0.2, -0.1)


def test_report_writes_every_figure(synthetic_log, tmp_path):
    written = write_report(synthetic_log, tmp_path / "report", progress=False)
    assert sorted(p.name for p in written) == ["cameras.png", "errors.png", "progress.png", "trajectory.png"]
    assert all(p.stat().st_size > 10_000 for p in written)


def test_a_damaged_log_costs_the_result_its_log_figures_only(synthetic_log, tmp_path):
    """A chunk damaged behind a valid summary: reading it back fails with one short line naming the
    log, and result.json still holds the mission's outcome and estimate, with the reason beside."""
    from mcap.reader import make_reader

    from station.run import RunSummary

    data = bytearray(synthetic_log.read_bytes())
    with open(synthetic_log, "rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[0]
    start = chunk.chunk_start_offset + chunk.chunk_length - chunk.compressed_size // 2  # inside the compressed data
    data[start:start + 64] = bytes(64)
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    with pytest.raises(LogError, match="damaged MCAP data") as error:
        list(read_log(damaged))
    assert str(damaged) in str(error.value) and len(str(error.value)) < 300 + len(str(damaged))
    x, P = np.array([0.2, -0.1, 0.05]), np.diag([1e-6, 1e-6, 1e-7])
    summary = RunSummary(Outcome.COMPLETED.value, "coverage reached", True, 10, 10, 1.0, None, None, x, P)
    result = build_result(summary, damaged, {}, "vga")
    assert result["status"] == "success" and result["object"]["x"] == pytest.approx(0.2)
    assert result["path_length"] is None and "damaged MCAP data" in result["files"]["log_error"]
    assert build_result(summary, synthetic_log, {}, "vga")["path_length"] == pytest.approx(4.0)


@pytest.mark.parametrize("outcome, source", [(Outcome.COMPLETED.value, "model"), (Outcome.TIME_LIMIT.value, "filter")])
def test_the_result_centre_is_the_models_once_completed_and_the_filters_kept_beside(outcome, source, tmp_path):
    """A completed mission's centre is its carved model's centroid (a model from fewer views than a
    completed mission's is not trusted for it); the filter's centre, radius and covariance stay."""
    from agent.carving import VoxelCarver, load_carving_params
    from station.run import RunSummary

    carver = VoxelCarver((0.1, 0.1, 0.0), (0.3, 0.3, 0.2), 0.02, load_carving_params())  # no view: the whole box
    x, P = np.array([0.25, 0.18, 0.06]), np.diag([1e-5, 1e-5, 1e-6])
    summary = RunSummary(outcome, "", outcome == Outcome.COMPLETED.value, 10, 10, 1.0, carver, None, x, P)
    estimate = build_result(summary, tmp_path / "missing.mcap", {}, "qvga")["object"]
    centre = (estimate["x"], estimate["y"])
    expected = carver.metrics().centroid[:2] if source == "model" else (0.25, 0.18)
    assert estimate["centre_source"] == source and centre == pytest.approx(expected)
    assert (estimate["filter_x"], estimate["filter_y"], estimate["r"]) == (0.25, 0.18, 0.06)
    assert estimate["covariance"] == P.tolist()
