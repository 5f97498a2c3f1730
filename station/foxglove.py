"""Foxglove messages for the run log, so that it opens in Foxglove Studio with no set-up.

Frames (``FrameTransforms``): ``world`` -> ``odom`` (the localization's correction of odometry),
``odom`` -> ``robot`` (odometry), ``robot`` -> ``camera`` (T_BC at capture, optical convention).
Scene entities live in ``world``: the object estimate (a cylinder) and its 3-sigma centre
ellipse, the landmarks, one frustum per keyframe, the carved model (GLB).

3-sigma ellipse of the 2x2 centre covariance P_xy = V diag(l1, l2) V^T::

    e(s) = o + 3 V diag(sqrt(l1), sqrt(l2)) (cos s, sin s),   s in [0, 2 pi)

The robot's trajectory is a ``PosesInFrame`` in ``world`` (one pose (x, y, theta) per localized
frame). Image annotations (``ImageAnnotations``, stamped like the image they belong to) are drawn
from the frame's records by projecting world points with the frame's T_WC, u ~ K T_CW X:

* the silhouette outline (its left and right edges, pixels as measured);
* the two tangent rays, bearings phi -+ delta / 2 from the camera centre C, sampled at the aim
  height h: X(d) = (C_x + d cos b, C_y + d sin b, h), d in [d_min, d_max];
* the landmarks the localizer used, at their map positions, labelled with their ids;
* the predicted object position, the estimate's centre (o_x, o_y, h).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Optional, Sequence, Tuple

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CircleAnnotation_pb2 import CircleAnnotation
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.ModelPrimitive_pb2 import ModelPrimitive
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.TextAnnotation_pb2 import TextAnnotation
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from scipy.spatial.transform import Rotation

from agent.camera import CameraModel
from nao_core.geometry import planar_transform
from nao_core.landmark_map import LandmarkMap
from station.mcap_log import to_ns

WORLD, ODOM, ROBOT, CAMERA = "world", "odom", "robot", "camera"


def stamp(t: float) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(to_ns(t))
    return ts


def pose(T: np.ndarray) -> Pose:
    qx, qy, qz, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    return Pose(position=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))


def compressed_image(t: float, jpeg: bytes) -> CompressedImage:
    return CompressedImage(timestamp=stamp(t), frame_id=CAMERA, data=jpeg, format="jpeg")


def camera_calibration(t: float, camera: CameraModel) -> CameraCalibration:
    K = camera.K
    P = np.hstack([K, np.zeros((3, 1))])
    return CameraCalibration(
        timestamp=stamp(t), frame_id=CAMERA, width=camera.width, height=camera.height,
        distortion_model="plumb_bob", D=list(map(float, camera.dist)), K=K.ravel().tolist(),
        R=np.eye(3).ravel().tolist(), P=P.ravel().tolist(),
    )


def frame_transforms(t: float, T_W_odom: np.ndarray, T_odom_B: np.ndarray, T_BC: np.ndarray) -> FrameTransforms:
    def tf(parent: str, child: str, T: np.ndarray) -> FrameTransform:
        p = pose(T)
        return FrameTransform(timestamp=stamp(t), parent_frame_id=parent, child_frame_id=child,
                              translation=p.position, rotation=p.orientation)

    return FrameTransforms(transforms=[tf(WORLD, ODOM, T_W_odom), tf(ODOM, ROBOT, T_odom_B), tf(ROBOT, CAMERA, T_BC)])


def _color(r: float, g: float, b: float, a: float = 1.0) -> Color:
    return Color(r=r, g=g, b=b, a=a)


def _entity(t: float, entity_id: str, **primitives) -> SceneEntity:
    return SceneEntity(timestamp=stamp(t), frame_id=WORLD, id=entity_id, **primitives)


def ellipse_points(center: Sequence[float], P_xy: np.ndarray, n_sigma: float = 3.0, n: int = 48) -> np.ndarray:
    """(n, 2) points of the n-sigma ellipse of a 2x2 covariance (module docstring)."""
    values, vectors = np.linalg.eigh(0.5 * (P_xy + P_xy.T))
    s = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    unit = np.stack([np.cos(s), np.sin(s)])
    return np.asarray(center)[:2] + (n_sigma * vectors @ np.diag(np.sqrt(np.maximum(values, 0.0))) @ unit).T


def object_estimate(t: float, x: np.ndarray, P: np.ndarray, height: float = 0.3) -> SceneUpdate:
    cylinder = CylinderPrimitive(
        pose=pose(_translation(x[0], x[1], 0.5 * height)),
        size=Vector3(x=2 * x[2], y=2 * x[2], z=height), bottom_scale=1.0, top_scale=1.0, color=_color(0.2, 0.6, 1.0, 0.5),
    )
    ring = [Point3(x=px, y=py, z=0.0) for px, py in ellipse_points(x, P[:2, :2])]
    ellipse = LinePrimitive(type=LinePrimitive.LINE_LOOP, pose=pose(np.eye(4)), thickness=0.005,
                            scale_invariant=False, points=ring, color=_color(1.0, 0.3, 0.1))
    return SceneUpdate(entities=[_entity(t, "object", cylinders=[cylinder], lines=[ellipse])])


def landmarks(t: float, landmark_map: LandmarkMap) -> SceneUpdate:
    cubes = []
    for lm in landmark_map.landmarks:
        size = lm.size if lm.kind == "aruco" else lm.diameter
        T = _translation(*lm.position)
        T[:3, :3] = Rotation.from_euler("z", lm.yaw).as_matrix()
        color = _color(0.1, 0.1, 0.1) if lm.kind == "aruco" else _color(0.9, 0.8, 0.1)
        cubes.append(CubePrimitive(pose=pose(T), size=Vector3(x=0.01, y=size, z=size), color=color))
    return SceneUpdate(entities=[_entity(t, "landmarks", cubes=cubes)])


def frusta(t: float, camera: CameraModel, poses_WC: Iterable[np.ndarray], depth: float = 0.25) -> SceneUpdate:
    """One pyramid per camera pose: apex at the centre, base at ``depth`` along the optical axis."""
    w, h = camera.width, camera.height
    rays = camera.pixels_to_rays(np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=float))
    base = depth * rays / rays[:, 2:3]
    segments = []
    for T in poses_WC:
        corners = base @ T[:3, :3].T + T[:3, 3]
        apex = T[:3, 3]
        for i in range(4):
            segments += [apex, corners[i], corners[i], corners[(i + 1) % 4]]
    points = [Point3(x=p[0], y=p[1], z=p[2]) for p in segments]
    lines = LinePrimitive(type=LinePrimitive.LINE_LIST, pose=pose(np.eye(4)), thickness=0.003,
                          scale_invariant=False, points=points, color=_color(0.3, 0.9, 0.3))
    return SceneUpdate(entities=[_entity(t, "keyframes", lines=[lines])])


def model(t: float, glb: bytes) -> SceneUpdate:
    """The carved model at the world origin: ``glb`` is y up (glTF), which Foxglove's 3-D panel turns
    z up, so the identity pose shows it upright in ``world``."""
    primitive = ModelPrimitive(pose=pose(np.eye(4)), scale=Vector3(x=1, y=1, z=1), color=_color(0.8, 0.8, 0.8),
                               override_color=False, media_type="model/gltf-binary", data=glb)
    return SceneUpdate(entities=[_entity(t, "model", models=[primitive])])


def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


ESTIMATE_SCHEMA = {
    "title": "station.Estimate", "type": "object", "additionalProperties": False,
    "description": "The object estimate (centre x, y and radius r, m) and its standard deviations sqrt(diag P), for plots",
    "properties": {k: {"type": "number"} for k in ("t", "x", "y", "r", "std_x", "std_y", "std_r")},
    "required": ["t", "x", "y", "r", "std_x", "std_y", "std_r"],
}


def estimate(t: float, x: Sequence[float], P: np.ndarray) -> dict:
    """The estimate and its standard deviations as one flat record (``ESTIMATE_SCHEMA``)."""
    std = np.sqrt(np.maximum(np.diag(np.asarray(P, dtype=float)), 0.0))
    return {"t": t, "x": float(x[0]), "y": float(x[1]), "r": float(x[2]),
            "std_x": float(std[0]), "std_y": float(std[1]), "std_r": float(std[2])}


def trajectory(t: float, poses: Sequence[Tuple[float, float, float]]) -> PosesInFrame:
    """The robot's localized poses (x, y, theta) so far, in ``world``."""
    return PosesInFrame(timestamp=stamp(t), frame_id=WORLD, poses=[pose(planar_transform(*p)) for p in poses])


@dataclass(frozen=True)
class FrameView:
    """What one frame's annotations show; all optional but the camera pose (module docstring)."""

    T_WC: np.ndarray  # 4x4 camera in world at capture
    outline: Optional[np.ndarray] = None  # (N, 2) silhouette outline pixels (u, v)
    bearings: Optional[Tuple[Tuple[float, float], float, float]] = None  # camera (x, y), phi, delta (None: cut)
    landmarks: Sequence[Tuple[str, Tuple[float, float, float]]] = ()  # (id, world position) of those used
    predicted: Optional[Tuple[float, float]] = None  # the estimate's centre (x, y)
    aim_height: float = 0.1  # height of the rays and the predicted position, m


def frame_view(pose, measurement, estimate: Optional[Tuple[float, float]], mask: Optional[np.ndarray],
               landmark_map: LandmarkMap, aim_height: float) -> FrameView:
    """A frame's view from the pilot's records (``station.outputs`` PoseRecord, MeasurementRecord or None),
    the latest estimate's centre and the keyframe's silhouette mask (None: not a keyframe)."""
    outline = None
    if mask is not None:
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        outline = max(contours, key=len).reshape(-1, 2) if contours else None
    used = [(str(lm.id), lm.position) for lm in landmark_map.landmarks] if pose.landmark_fix else []
    bearings = ((measurement.cam[0], measurement.cam[1]), measurement.phi, measurement.delta) if measurement else None
    return FrameView(T_WC=np.asarray(pose.T_WC, dtype=float).reshape(4, 4), outline=outline, bearings=bearings,
                     landmarks=used, predicted=estimate, aim_height=aim_height)


def image_annotations(stamp_s: float, camera: CameraModel, view: FrameView, ray_range: Tuple[float, float] = (0.15, 4.0)
                      ) -> ImageAnnotations:
    """The annotations of one frame (stamp = the image's capture time, so Foxglove pairs them)."""
    ts = stamp(stamp_s)
    points, circles, texts = [], [], []

    def project(X: np.ndarray) -> np.ndarray:
        uv, in_front = camera.project_world(X, view.T_WC)
        return uv[in_front]

    def strip(uv: np.ndarray, color: Color, kind: int = PointsAnnotation.LINE_STRIP) -> None:
        if len(uv) >= 2:
            points.append(PointsAnnotation(timestamp=ts, type=kind, outline_color=color, thickness=2.0,
                                           points=[Point2(x=float(u), y=float(v)) for u, v in uv]))

    def label(uv: np.ndarray, text: str, color: Color) -> None:
        circles.append(CircleAnnotation(timestamp=ts, position=Point2(x=float(uv[0]), y=float(uv[1])), diameter=10.0,
                                        thickness=2.0, outline_color=color))
        texts.append(TextAnnotation(timestamp=ts, position=Point2(x=float(uv[0]) + 6, y=float(uv[1]) - 6), text=text,
                                    font_size=12.0, text_color=color, background_color=_color(0, 0, 0, 0.5)))

    if view.outline is not None and len(view.outline):
        strip(np.asarray(view.outline, dtype=float), _color(0.1, 1.0, 0.2), PointsAnnotation.POINTS)
    if view.bearings is not None:
        (cx, cy), phi, delta = view.bearings
        d = np.linspace(*ray_range, 24)
        for b in ((phi - 0.5 * delta, phi + 0.5 * delta) if delta is not None else (phi,)):
            X = np.stack([cx + d * math.cos(b), cy + d * math.sin(b), np.full_like(d, view.aim_height)], axis=1)
            strip(project(X), _color(1.0, 0.6, 0.0))
    for landmark_id, position in view.landmarks:
        uv = project(np.asarray([position], dtype=float))
        if len(uv):
            label(uv[0], str(landmark_id), _color(0.2, 0.8, 1.0))
    if view.predicted is not None:
        uv = project(np.array([[view.predicted[0], view.predicted[1], view.aim_height]]))
        if len(uv):
            label(uv[0], "object (predicted)", _color(1.0, 0.2, 0.8))
    return ImageAnnotations(points=points, circles=circles, texts=texts)


def layout_topics(layout: dict) -> set:
    """Every topic a Foxglove layout names (image, calibration, annotations, 3-D topics, plot paths, log)."""
    topics = set()
    for config in layout["configById"].values():
        image = config.get("imageMode", {})
        topics |= {image[k] for k in ("imageTopic", "calibrationTopic") if k in image} | set(image.get("annotations", {}))
        topics |= set(config.get("topics", {}))
        topics |= {path["value"].split(".", 1)[0] for path in config.get("paths", [])}
        topics |= {config["topicToRender"]} if "topicToRender" in config else set()
    return topics
