"""The image's own distance to the object (agent/clearance.py), and its floor contact starting the
object filter (agent/ekf.py), on rendered frames with known poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scipy.stats import chi2

from agent.camera import CameraModel, optical_axis_heading
from agent.clearance import floor_contact, floor_distance, image_distance, width_distance
from agent.ekf import ObjectEKF, load_ekf_params
from agent.perception import PerceptionParams, extract_silhouette, measure_object
from nao_core.config import CONFIG_DIR, load
from nao_core.geometry import camera_in_world
from nao_core.robot_model import load_robot_model
from nao_sim.world import SimWorld

ROBOT = load_robot_model()
PERCEPTION = load(PerceptionParams, [CONFIG_DIR / "perception.yaml"], section="perception")
EKF = load_ekf_params()


def views(name: str, distance: float, head_pitch_offset: float = 0.0):
    """(silhouette, measurement, T_WC, horizontal camera-to-centre distance, object radius) of views
    of ``name`` from ``distance`` all around it, the head aimed at its base (plus an offset, up < 0)."""
    world = SimWorld(name, ROBOT, "vga", seed=2)
    camera = CameraModel.from_intrinsics(ROBOT.camera.intrinsics("vga"))
    ox, oy = world.scenario.position
    out = []
    for az in np.linspace(-math.pi, math.pi, 12, endpoint=False):
        pose = (ox + distance * math.cos(az), oy + distance * math.sin(az), az + math.pi)
        yaw, pitch = ROBOT.look_at(pose, (ox, oy, 0.05))
        world.teleport(pose, ROBOT.head.clamp(yaw, pitch + head_pitch_offset))
        frame = world.render()
        T_WC = camera_in_world(pose, frame.T_BC)
        silhouette = extract_silhouette(frame.image, PERCEPTION)
        if silhouette is None:
            continue
        measurement = measure_object(silhouette, camera, T_WC, PERCEPTION)
        out.append((silhouette, measurement, T_WC, math.hypot(T_WC[0, 3] - ox, T_WC[1, 3] - oy), world.scenario.radius, camera))
    return out


def test_a_figure_wider_than_its_estimate_reads_at_its_true_distance():
    """A toy figure (arms out) 0.8 m away, its estimate a thin cylinder (r = 3.3 cm, what its
    narrowest views give): from the sides where it looks wide the apparent width alone puts it
    within the guard's limit; with its base in view the image gives the floor distance, within
    the object's own extent of the truth."""
    r_estimate = 0.033
    seen = views("figure", 0.8)
    assert len(seen) >= 10
    misread = 0
    for silhouette, measurement, T_WC, centre, radius, camera in seen:
        assert not silhouette.touches_bottom
        d = image_distance(silhouette, floor_distance(silhouette, camera, T_WC), measurement.delta, r_estimate)
        assert centre - radius - 0.03 <= d <= centre + 0.03, (d, centre, radius)
        width_only = width_distance(measurement.delta, r_estimate)
        misread += width_only is not None and width_only < 0.5
    assert misread >= 2  # the views that stalled a mission (docs/benchmarks.md): the width alone says "too near"


def test_with_its_base_cut_the_floor_is_an_upper_bound_and_the_width_the_distance():
    """Close to a can with the head up, the base below the image: the floor seen at the bottom row
    is further than the can (an upper bound); given the can's apparent width (a silhouette cut by a
    border measures none, so here the true one) the guard gets the width distance, the nearer."""
    seen = [v for v in views("can", 0.45, head_pitch_offset=-0.2) if v[0].touches_bottom]
    assert seen
    for silhouette, _, T_WC, centre, radius, camera in seen:
        surface = centre - radius
        assert image_distance(silhouette, floor_distance(silhouette, camera, T_WC), None, radius) > surface + 0.1  # the floor alone: too far
        d = image_distance(silhouette, floor_distance(silhouette, camera, T_WC), 2.0 * math.asin(radius / centre), radius)
        assert d == pytest.approx(surface, abs=1e-9)


@pytest.mark.parametrize("name", ["soda_can", "mug", "bunny", "figure"])
@pytest.mark.parametrize("distance", [0.8, 2.0])
def test_a_first_view_with_its_floor_contact_starts_the_filter_near_the_object(name, distance):
    """From every side, the filter started from one rendered view: with the base's floor contact
    the centre is within 12 % of the range (measured: 2-14 cm), 25 % for the figure (its thin
    feet, lost at 2 m: 42 cm), and inside its covariance's 99.7 % ellipse; from the radius prior alone (10 cm) a soda can's
    start is two to four times too far (docs/estimation.md, "Floor contact")."""
    truth = np.array(SimWorld(name, ROBOT, "vga", seed=2).scenario.position)
    gate, tolerance = chi2.ppf(0.997, 2), 0.25 if name == "figure" else 0.12
    unfloored = []
    for silhouette, measurement, T_WC, centre, _, camera in views(name, distance):
        floor = floor_contact(silhouette, floor_distance(silhouette, camera, T_WC), T_WC[2, 3])
        assert floor is not None and measurement.delta is not None
        cam = np.array([T_WC[0, 3], T_WC[1, 3], optical_axis_heading(T_WC)])
        ekf = ObjectEKF(EKF)
        assert ekf.initialize(cam, measurement.phi, measurement.delta, floor).accepted
        err = ekf.x[:2] - truth
        assert np.linalg.norm(err) < tolerance * centre
        assert err @ np.linalg.solve(ekf.P[:2, :2], err) < gate
        bare = ObjectEKF(EKF)
        bare.initialize(cam, measurement.phi, measurement.delta)
        unfloored.append(np.linalg.norm(bare.x[:2] - truth) / centre)
    if name == "soda_can":
        assert min(unfloored) > 1.0
