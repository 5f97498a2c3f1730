"""``station carve LOG.mcap -o model.ply [--resolution M] [--tolerance K]``: offline carving.

The keyframes the run chose (``/agent/keyframe``: frame sequence number, T_WC and the predicted
object pixel that picked the blob) are carved again from the logged JPEGs: silhouette by the run's
perception parameters (in light through the camera's inverse tone curve, as the run read them),
pose the one the final carve used (``/station/keyframe_poses``,
agent/pose_smoother.py; logs without it: the keyframe's own), volume around the run's final object
estimate, the given voxel edge and tolerance (defaults: the run's). With the run's parameters this reproduces the run's model (carving does not depend on the order of views).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict, List, Optional, Union

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from tqdm import tqdm

from agent.camera import CameraModel
from agent.carving import VoxelCarver
from agent.perception import extract_silhouette
from agent.tone_curve import in_light
from nao_core.protocol import FrameMeta, decode
from station.carving_worker import View, carve_views
from station.mcap_log import LogError, read_log
from station.runlog import load_recorded
from station.topics import EKF, FRAME_IMAGE, FRAME_META, KEYFRAME, KEYFRAME_POSES


def keyframe_camera(camera: CameraModel, keyframe: Dict) -> CameraModel:
    """The camera a logged ``/agent/keyframe`` record was seen with: its self-calibrated K
    (agent/self_calibration.py), or ``camera`` in logs without one."""
    if keyframe.get("K") is None:
        return camera
    return dataclasses.replace(camera, K=np.asarray(keyframe["K"], dtype=float).reshape(3, 3))


def carve_log(log_path: Union[str, Path], resolution: Optional[float] = None, tolerance: Optional[int] = None,
              progress: bool = True) -> VoxelCarver:
    setup = load_recorded(log_path)
    config = setup.config
    params = config.carving if tolerance is None else dataclasses.replace(config.carving, tolerance=tolerance)
    camera = CameraModel.from_intrinsics(setup.info.intrinsics)
    gamma = setup.info.robot.camera.response_gamma  # frames read in light, as the run read them (station/pilot.py)
    wanted: Dict[int, Dict] = {}
    estimate = None
    smoothed: Dict[int, List[float]] = {}  # the final carve's poses (station/run.py), when the run logged them
    for message in read_log(log_path, topics={KEYFRAME, EKF, KEYFRAME_POSES}):
        payload = message.json()
        if message.topic == KEYFRAME:
            wanted[payload["seq"]] = payload
        elif message.topic == KEYFRAME_POSES:
            smoothed = {int(k["seq"]): k["T_WC"] for k in payload["keyframes"]}
        elif payload["x"] is not None:
            estimate = payload
    if not wanted or estimate is None:
        raise LogError(f"{log_path}: no keyframes or no object estimate: nothing to carve")
    views: List[View] = []
    images: List[np.ndarray] = []
    qualities: List[float] = []
    seq: Optional[int] = None
    with tqdm(total=len(wanted), desc="silhouettes", unit="view", disable=not progress) as bar:
        for message in read_log(log_path, topics={FRAME_META, FRAME_IMAGE}):
            if message.topic == FRAME_META:
                seq = decode(message.data, FrameMeta).seq
            elif seq in wanted:
                jpeg = message.proto(CompressedImage).data
                image = cv2.imdecode(np.frombuffer(jpeg, dtype=np.uint8), cv2.IMREAD_COLOR)
                image = in_light(image, gamma)
                keyframe = wanted.pop(seq)
                predicted = None if keyframe["predicted_uv"] is None else tuple(keyframe["predicted_uv"])
                silhouette = extract_silhouette(image, config.perception, predicted)  # the blob the run chose
                if silhouette is not None:
                    T_WC = smoothed.get(seq, keyframe["T_WC"])
                    views.append((silhouette.mask, keyframe_camera(camera, keyframe), np.asarray(T_WC, dtype=float).reshape(4, 4)))
                    images.append(image)
                    qualities.append(float(keyframe.get("quality", 1.0)))  # logs before agent/keyframes.py: all alike
                bar.update()
    x, P = np.asarray(estimate["x"]), np.asarray(estimate["P"])
    return carve_views(views, x, P, params, pitch=resolution, images=images, qualities=qualities)
