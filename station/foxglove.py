"""Foxglove messages for the run log, so that it opens in Foxglove Studio with no set-up.

Frames (``FrameTransforms``): ``world`` -> ``odom`` (the localization's correction of odometry),
``odom`` -> ``robot`` (odometry), ``robot`` -> ``camera`` (T_BC at capture, optical convention).
Scene entities live in ``world``: the object estimate (a cylinder) and its 3-sigma centre
ellipse, the landmarks, one frustum per keyframe, the carved model (GLB).

3-sigma ellipse of the 2x2 centre covariance P_xy = V diag(l1, l2) V^T::

    e(s) = o + 3 V diag(sqrt(l1), sqrt(l2)) (cos s, sin s),   s in [0, 2 pi)
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.CylinderPrimitive_pb2 import CylinderPrimitive
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.ModelPrimitive_pb2 import ModelPrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from scipy.spatial.transform import Rotation

from agent.camera import CameraModel
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
    primitive = ModelPrimitive(pose=pose(np.eye(4)), scale=Vector3(x=1, y=1, z=1), color=_color(0.8, 0.8, 0.8),
                               override_color=False, media_type="model/gltf-binary", data=glb)
    return SceneUpdate(entities=[_entity(t, "model", models=[primitive])])


def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T
