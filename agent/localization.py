"""Robot pose (x, y, theta) from known landmarks in the top camera, carried by odometry between fixes.

Landmark points (image u_i <-> world X_i):

* ArUco markers (``cv2.aruco.ArucoDetector`` on an image reduced to at most ``aruco_detection_width``,
  corners refined on the full image by ``cv2.cornerSubPix``): the four corners of each marker of
  the map, in ``Landmark.aruco_corners()`` order. With a pose prior, only boxes around the markers'
  predicted projections are searched (each marker's box padded by its projected side plus
  ``aruco_track_margin`` px; overlapping boxes merged); the whole frame is searched when there is
  no prior or the boxes gave fewer than ``min_points`` corners (a wrong prior costs one full search).
* Colour markers: centroids of the blobs of each colour class (found at half resolution). Colours repeat, so a blob is
  associated with the landmark of its colour whose projection from the pose prior is nearest,
  within ``color_gate`` pixels, and only when no other landmark of that colour is within the gate
  (ambiguous blobs and doubly claimed landmarks are dropped). Without a prior, only colours that
  occur once in the map and once in the image are used. Discs are only looked for when the ArUco
  markers gave fewer than ``color_below_aruco_points`` corners: next to enough sub-pixel corners a
  disc centroid adds little, and the search costs about a millisecond at VGA.

Camera pose: T_CW from ``cv2.solvePnPRansac`` (SQPnP hypotheses) when there are >= ``ransac_min_points``
points, else ``cv2.solvePnP`` (SQPnP); with the camera-in-robot transform at capture time,

    T_WB = T_WC T_BC^-1,  T_WC = T_CW^-1                                   (DESIGN.md point 8)

and its planar part p = (x, y, theta) seeds a Gauss-Newton refinement of the 3-DOF planar pose on
the inliers (the robot stands on the floor: height, roll and pitch come from the kinematics):

    min_p sum_i || u_i - pi(K, T_BC^-1 T_WB(p)^-1 X_i) ||^2,   R_fix = s^2 (J^T J)^-1,
    s^2 = max(sigma_px^2, rms^2).

Gates: the 6-DOF solution's base must be upright (|z|, roll, pitch of T_WB small: rejects mirror
solutions); reprojection RMS <= ``max_reprojection_px``; a jump from the prior larger than
``jump_sigmas`` standard deviations (of P + R_fix) plus ``jump_floor`` is rejected, unless
``max_rejected_jumps`` fixes in a row disagree with the prior (then the prior is wrong: re-localize).

Odometry: the pose is W <- odometry-frame correction C composed with the odometry pose,
p = C (+) o. A forward odometry step d (in the robot frame, length l and turn |dtheta|) grows

    P <- F P F^T + G Q G^T,  Q = diag(k_t^2 l, k_t^2 l, k_r^2 (l + |dtheta|)),

and a fix is fused as a Kalman update with identity measurement: K = P (P + R)^-1,
p <- p + K wrap(z - p), P <- (I - K) P, then C = p (-) o_capture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple

import cv2
import numpy as np

from agent.camera import CameraModel
from agent.perception import PerceptionParams, blobs, check_image, color_mask
from nao_core.config import bounds
from nao_core.geometry import (
    Pose,
    camera_in_world,
    compose,
    invert,
    planar_pose,
    relative,
    wrap_angle,
)
from nao_core.landmark_map import Landmark, LandmarkMap


@dataclass(frozen=True)
class LocalizationParams:
    """PnP, gates and odometry noise (config/localization.yaml, section ``localization``)."""

    pnp_method: Literal["sqpnp", "iterative", "epnp"]
    ransac_min_points: int = field(metadata=bounds(4, 1000))  # use RANSAC from this many points
    ransac_reprojection_px: float = field(metadata=bounds(0.1, 50.0))  # RANSAC inlier threshold, px
    min_points: int = field(metadata=bounds(4, 1000))  # fewer landmark points -> no fix
    max_reprojection_px: float = field(metadata=bounds(0.01, 50.0))  # RMS gate on the final fit, px
    pixel_sigma: float = field(metadata=bounds(0.01, 10.0))  # image point noise, px
    max_tilt: float = field(metadata=bounds(0.0, 1.0))  # rad, roll/pitch of T_WB from the 6-DOF solution
    max_height: float = field(metadata=bounds(0.0, 1.0))  # m, |z| of T_WB from the 6-DOF solution
    jump_sigmas: float = field(metadata=bounds(0.0, 100.0))  # jump gate in standard deviations
    jump_floor: Tuple[float, float] = field(metadata=bounds(0.0, 10.0))  # (m, rad) always tolerated
    max_rejected_jumps: int = field(metadata=bounds(1, 1000))  # then the prior is wrong: accept
    color_gate: float = field(metadata=bounds(1.0, 1000.0))  # px, colour-landmark association gate
    color_below_aruco_points: int = field(metadata=bounds(0, 1000))  # colour landmarks only below this many ArUco corners
    odom_translation_noise: float = field(metadata=bounds(0.0, 1.0))  # k_t, m per sqrt(m)
    odom_rotation_noise: float = field(metadata=bounds(0.0, 1.0))  # k_r, rad per sqrt(m + rad)
    aruco_corner_refinement: Literal["none", "subpix", "contour"]
    aruco_detection_width: int = field(metadata=bounds(160, 10000))  # px, detect markers on an image at most this wide
    aruco_threshold_windows: Tuple[int, int, int] = field(metadata=bounds(3, 99))  # adaptive threshold (min, max, step), px
    aruco_track_margin: float = field(metadata=bounds(0.0, 1000.0))  # px around predicted markers searched with a prior


@dataclass(frozen=True)
class PoseFix:
    """A robot pose measured from landmarks in one frame (before fusion with the prior)."""

    pose: Pose
    covariance: np.ndarray  # 3 x 3, of (x, y, theta)
    rms_px: float  # reprojection RMS of the inliers
    landmark_ids: Tuple[object, ...]
    points: int  # inlier points used
    T_WC: np.ndarray  # camera pose of the 6-DOF PnP solution


_CORNER_REFINEMENT = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
}
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
_PNP_FLAGS = {"sqpnp": cv2.SOLVEPNP_SQPNP, "iterative": cv2.SOLVEPNP_ITERATIVE, "epnp": cv2.SOLVEPNP_EPNP}




class LandmarkDetector:
    """Image points of the map's landmarks in one frame: ArUco corners and associated colour blobs."""

    def __init__(self, params: LocalizationParams, landmark_map: LandmarkMap, perception: Optional[PerceptionParams]):
        self.params = params
        self.perception = perception
        self.aruco: Dict[str, Dict[int, np.ndarray]] = {}
        for lm in landmark_map.of_kind("aruco"):
            self.aruco.setdefault(str(lm.dictionary), {})[int(lm.id)] = lm.aruco_corners()
        self.aruco_corners = np.array([c for markers in self.aruco.values() for c in markers.values()]).reshape(-1, 3)
        detector_params = cv2.aruco.DetectorParameters()
        detector_params.cornerRefinementMethod = _CORNER_REFINEMENT[params.aruco_corner_refinement]
        (detector_params.adaptiveThreshWinSizeMin, detector_params.adaptiveThreshWinSizeMax,
         detector_params.adaptiveThreshWinSizeStep) = params.aruco_threshold_windows
        self.detectors = {
            name: cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)), detector_params)
            for name in self.aruco
        }
        self.colors: Dict[str, List[Landmark]] = {}
        if perception is not None:
            for lm in landmark_map.of_kind("color"):
                if lm.color not in perception.colors:
                    raise ValueError(f"landmark {lm.id!r}: colour {lm.color!r} is not a perception colour class")
                self.colors.setdefault(str(lm.color), []).append(lm)

    def aruco_points(
        self, gray: np.ndarray, boxes: Optional[List[Tuple[int, int, int, int]]] = None
    ) -> Tuple[List[object], List[np.ndarray], List[np.ndarray]]:
        """Map markers found in a grey image: ids, world corners (4 x 3 each), image corners (4 x 2 each).

        Detection runs on the image reduced by an integer factor f to at most
        ``aruco_detection_width`` wide, in the ``boxes`` (x0, y0, x1, y1; full-size pixels) if given,
        else everywhere; the corners, mapped back by (c + 1/2) f - 1/2, are refined on the full
        image with ``cv2.cornerSubPix``.
        """
        factor = max(1, -(-gray.shape[1] // self.params.aruco_detection_width))
        small = gray
        if factor > 1:
            small = cv2.resize(gray, (gray.shape[1] // factor, gray.shape[0] // factor), interpolation=cv2.INTER_AREA)
        regions = [(0, 0, small.shape[1], small.shape[0])] if boxes is None else [
            (x0 // factor, y0 // factor, -(-x1 // factor), -(-y1 // factor)) for x0, y0, x1, y1 in boxes
        ]
        found: Dict[Tuple[str, int], np.ndarray] = {}
        for name, detector in self.detectors.items():
            known = self.aruco[name]
            for x0, y0, x1, y1 in regions:
                corners, ids, _ = detector.detectMarkers(small[y0:y1, x0:x1])
                for c, marker_id in zip(corners, () if ids is None else ids.ravel()):
                    if int(marker_id) in known:
                        found[(name, int(marker_id))] = c.reshape(4, 2) + (x0, y0)
        ids_out: List[object] = [marker_id for _, marker_id in found]
        world: List[np.ndarray] = [self.aruco[name][marker_id] for name, marker_id in found]
        image: List[np.ndarray] = list(found.values())
        if factor > 1 and image:
            points = ((np.vstack(image) + 0.5) * factor - 0.5).astype(np.float32)
            window = (factor + 1, factor + 1)  # half-size: a (2f + 3)-pixel square around each corner
            points = cv2.cornerSubPix(gray, points.reshape(-1, 1, 2), window, (-1, -1), _SUBPIX_CRITERIA).reshape(-1, 2)
            image = list(points.reshape(-1, 4, 2))
        return ids_out, world, image

    def predicted_boxes(self, camera: CameraModel, T_WC: np.ndarray) -> List[Tuple[int, int, int, int]]:
        """Pixel boxes (x0, y0, x1, y1), clipped to the image, around the projections from T_WC of the
        map markers in front of the camera and facing it, each padded by half its projected side plus
        ``aruco_track_margin``; overlapping boxes are merged."""
        if len(self.aruco_corners) == 0:
            return []
        uv, in_front = camera.project_world(self.aruco_corners, T_WC)
        quads = uv.reshape(-1, 4, 2)[in_front.reshape(-1, 4).all(axis=1)]
        x, y = quads[..., 0], quads[..., 1]
        # Shoelace area (image y down): positive for a marker seen from the front in cv2.aruco's
        # corner order; a marker seen from behind is mirrored, one edge-on has none.
        facing = (x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1) > 0
        lo, hi = quads.min(axis=1), quads.max(axis=1)
        margin = self.params.aruco_track_margin
        size = np.array([camera.width, camera.height])
        near = np.all(hi >= -margin, axis=1) & np.all(lo <= size - 1 + margin, axis=1)  # in the image, or nearly
        pad = (0.5 * (hi - lo).max(axis=1) + margin)[:, None]
        lo = np.clip(np.floor(lo - pad), 0, size).astype(int)
        hi = np.clip(np.floor(hi + pad) + 1, 0, size).astype(int)
        boxes = [[*l, *h] for l, h in zip(lo[facing & near], hi[facing & near])]
        return _merge_boxes(boxes)

    def color_points(
        self, image_bgr: np.ndarray, camera: CameraModel, T_WC_prior: Optional[np.ndarray]
    ) -> Tuple[List[object], List[np.ndarray], List[np.ndarray]]:
        if not self.colors:
            return [], [], []
        assert self.perception is not None
        # Half resolution: 4x fewer pixels; a half-size pixel (i, j) is centred on full-size (2i + 1/2, 2j + 1/2).
        half = cv2.resize(image_bgr, (image_bgr.shape[1] // 2, image_bgr.shape[0] // 2), interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(half, cv2.COLOR_BGR2HSV)
        min_area = max(1, self.perception.landmark_min_area // 4)
        ids: List[object] = []
        world: List[np.ndarray] = []
        image: List[np.ndarray] = []
        for name, landmarks in self.colors.items():
            _, _, centroids = blobs(color_mask(hsv, self.perception.colors[name]), min_area)
            for lm, uv in self._associate(landmarks, 2.0 * centroids + 0.5, camera, T_WC_prior):
                ids.append(lm.id)
                world.append(np.asarray(lm.position, dtype=float).reshape(1, 3))
                image.append(uv.reshape(1, 2))
        return ids, world, image

    def _associate(self, landmarks: List[Landmark], centroids: np.ndarray, camera: CameraModel, T_WC: Optional[np.ndarray]):
        """(landmark, blob centroid) pairs that are unambiguous under the prior's projections."""
        if len(centroids) == 0:
            return []
        if T_WC is None:
            return [(landmarks[0], centroids[0])] if len(landmarks) == 1 and len(centroids) == 1 else []
        predicted, in_front = camera.project_world(np.array([lm.position for lm in landmarks]), T_WC)
        gate = self.params.color_gate
        distances = np.linalg.norm(centroids[:, None, :] - predicted[None, :, :], axis=2)
        distances[:, ~in_front] = np.inf
        within = distances <= gate
        pairs = []
        for b in range(len(centroids)):
            candidates = np.flatnonzero(within[b])
            # Unambiguous: one landmark within the gate of this blob, and this blob the only one near it.
            if len(candidates) == 1 and within[:, candidates[0]].sum() == 1:
                pairs.append((landmarks[candidates[0]], centroids[b]))
        return pairs


class RobotLocalizer:
    """Landmark fixes fused with odometry; ``pose`` is None until the first fix."""

    def __init__(
        self,
        params: LocalizationParams,
        landmark_map: LandmarkMap,
        camera: CameraModel,
        perception_params: Optional[PerceptionParams] = None,
    ):
        self.params = params
        self.camera = camera
        self.detector = LandmarkDetector(params, landmark_map, perception_params)
        self._correction: Optional[Pose] = None  # W <- odometry frame
        self.covariance = np.full((3, 3), np.nan)
        self.rejected_jumps = 0
        self._odom: Optional[Pose] = None
        self._stamp = -math.inf

    def reset(self) -> None:
        """Forget the pose (after a fall or a teleport): the next fix starts afresh."""
        self._correction = None
        self.covariance = np.full((3, 3), np.nan)
        self.rejected_jumps = 0

    @property
    def pose(self) -> Optional[Pose]:
        """Latest (x, y, theta) in W, or None before the first fix."""
        if self._correction is None or self._odom is None:
            return None
        return compose(self._correction, self._odom)

    def pose_at(self, odom: Pose) -> Optional[Pose]:
        """The pose at the time the odometry read ``odom`` (e.g. a frame's capture)."""
        return None if self._correction is None else compose(self._correction, tuple(map(float, odom)))

    def on_odometry(self, odom: Pose, stamp: float) -> None:
        """Carry the pose with a newer odometry reading; its covariance grows with the motion."""
        odom = _check_pose(odom, "odom")
        if stamp < self._stamp:
            return
        if self._odom is not None and self._correction is not None:
            dx, dy, dtheta = relative(self._odom, odom)
            heading = compose(self._correction, self._odom)[2]
            c, s = math.cos(heading), math.sin(heading)
            step_W = np.array([c * dx - s * dy, s * dx + c * dy])
            F = np.array([[1.0, 0.0, -step_W[1]], [0.0, 1.0, step_W[0]], [0.0, 0.0, 1.0]])
            G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            length = math.hypot(dx, dy)
            kt, kr = self.params.odom_translation_noise, self.params.odom_rotation_noise
            Q = np.diag([kt**2 * length, kt**2 * length, kr**2 * (length + abs(dtheta))])
            self.covariance = F @ self.covariance @ F.T + G @ Q @ G.T
        self._odom, self._stamp = odom, stamp

    def on_frame(self, image: np.ndarray, T_BC: np.ndarray, odom: Pose, stamp: float) -> Optional[PoseFix]:
        """A landmark fix from a frame (fused into the pose), or None when it gave none.

        Raises ``ImageError`` on a garbage image and ``ValueError`` on a malformed T_BC or odometry.
        """
        image = check_image(image, (self.camera.width, self.camera.height))
        T_BC = np.asarray(T_BC, dtype=float)
        if T_BC.shape != (4, 4) or not np.all(np.isfinite(T_BC)):
            raise ValueError(f"T_BC must be a finite 4 x 4 transform, got shape {T_BC.shape}")
        odom = _check_pose(odom, "odom")
        self.on_odometry(odom, stamp)
        prior = self.pose_at(odom)
        fix = self.measure(image, T_BC, prior)
        if fix is None:
            return None
        if prior is not None and not self._accept_jump(prior, fix):
            return None
        self._fuse(fix, prior, odom)
        return fix

    def measure(self, image: np.ndarray, T_BC: np.ndarray, prior: Optional[Pose] = None) -> Optional[PoseFix]:
        """The pose fix of one frame on its own (no jump gate, no fusion), or None."""
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        T_WC_prior = None if prior is None else camera_in_world(prior, T_BC)
        ids, world, pixels = [], [], []
        if T_WC_prior is not None:
            ids, world, pixels = self.detector.aruco_points(gray, self.detector.predicted_boxes(self.camera, T_WC_prior))
        if 4 * len(ids) < self.params.min_points:  # no prior, or it predicted the markers wrong: search everywhere
            ids, world, pixels = self.detector.aruco_points(gray)
        if 4 * len(ids) < self.params.color_below_aruco_points:  # discs add little to enough sub-pixel corners
            c_ids, c_world, c_pixels = self.detector.color_points(image, self.camera, T_WC_prior)
            ids, world, pixels = ids + c_ids, world + c_world, pixels + c_pixels
        if not world:
            return None
        X = np.vstack(world).astype(np.float64)
        u = np.vstack(pixels).astype(np.float64)
        if len(X) < self.params.min_points:
            return None
        T_CW, inliers = self._solve_pnp(X, u)
        if T_CW is None:
            return None
        T_WC = invert(T_CW)
        T_WB = T_WC @ invert(T_BC)
        if abs(T_WB[2, 3]) > self.params.max_height or math.acos(min(1.0, T_WB[2, 2])) > self.params.max_tilt:
            return None
        pose, rms, J = self._refine_planar(planar_pose(T_WB), T_BC, X[inliers], u[inliers])
        if rms > self.params.max_reprojection_px:
            return None
        scale = max(self.params.pixel_sigma, rms) ** 2
        try:
            covariance = scale * np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            return None
        return PoseFix(pose=pose, covariance=covariance, rms_px=rms, landmark_ids=tuple(ids), points=int(len(inliers)), T_WC=T_WC)

    def _solve_pnp(self, X: np.ndarray, u: np.ndarray) -> Tuple[Optional[np.ndarray], np.ndarray]:
        K, dist = self.camera.K, self.camera.dist
        flag = _PNP_FLAGS[self.params.pnp_method]
        if len(X) >= self.params.ransac_min_points:
            ok, rvec, tvec, inliers = cv2.solvePnPRansac(
                X, u, K, dist, reprojectionError=self.params.ransac_reprojection_px, flags=flag, iterationsCount=100
            )
            if not ok or inliers is None or len(inliers) < self.params.min_points:
                return None, np.empty(0, dtype=int)
            idx = inliers.ravel()
            rvec, tvec = cv2.solvePnPRefineLM(X[idx], u[idx], K, dist, rvec, tvec)
        else:
            ok, rvec, tvec = cv2.solvePnP(X, u, K, dist, flags=flag)
            if not ok:
                return None, np.empty(0, dtype=int)
            idx = np.arange(len(X))
        T_CW = np.eye(4)
        T_CW[:3, :3] = cv2.Rodrigues(rvec)[0]
        T_CW[:3, 3] = tvec.ravel()
        return T_CW, idx

    def _refine_planar(self, pose: Pose, T_BC: np.ndarray, X: np.ndarray, u: np.ndarray, iterations: int = 6):
        """Gauss-Newton on (x, y, theta) with the analytic Jacobian, in undistorted pixels.

        X_B = R(theta)^T (X_W - (x, y, 0)),  X_C = R_CB X_B + t_CB,  u = (f_x X_C.x / X_C.z + c_x, f_y X_C.y / X_C.z + c_y);
        dX_B/dx = (-c, s, 0), dX_B/dy = (-s, -c, 0), dX_B/dtheta = (X_B.y, -X_B.x, 0).
        Returns (pose, rms, J) with J the 2N x 3 Jacobian at the solution.
        """
        K = self.camera.K
        f, principal = np.array([K[0, 0], K[1, 1]]), K[:2, 2]
        target = cv2.undistortPoints(u.reshape(-1, 1, 2), K, self.camera.dist, P=K).reshape(-1, 2)
        T_CB = invert(T_BC)
        R_CB, t_CB = T_CB[:3, :3], T_CB[:3, 3]
        p = np.array(pose, dtype=float)
        for _ in range(iterations):
            c, s = math.cos(p[2]), math.sin(p[2])
            d = X - np.array([p[0], p[1], 0.0])
            X_B = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
            X_C = X_B @ R_CB.T + t_CB
            z = X_C[:, 2:3]
            r = (f * X_C[:, :2] / z + principal - target).ravel()
            dC_dxy = R_CB @ np.array([[-c, -s], [s, -c], [0.0, 0.0]])  # 3 x 2, the same for every point
            dC_dtheta = np.outer(X_B[:, 1], R_CB[:, 0]) - np.outer(X_B[:, 0], R_CB[:, 1])  # N x 3
            dC = np.concatenate([np.broadcast_to(dC_dxy, (len(X_B), 3, 2)), dC_dtheta[:, :, None]], axis=2)  # N x xyz x params
            # d(f a / z) = f (da z - a dz) / z^2 for a = x, y
            J = f[None, :, None] * (dC[:, :2, :] * z[:, :, None] - X_C[:, :2, None] * dC[:, 2:3, :]) / z[:, :, None] ** 2
            J = J.reshape(-1, 3)
            dp = np.linalg.solve(J.T @ J, -J.T @ r)
            p += dp
            if np.abs(dp).max() < 1e-8:  # m, rad: Gauss-Newton from the PnP seed gets there in 2-3 steps
                break
        rms = float(np.sqrt(np.mean(r**2) * 2.0))
        return (float(p[0]), float(p[1]), wrap_angle(float(p[2]))), rms, J

    def _accept_jump(self, prior: Pose, fix: PoseFix) -> bool:
        diff = _difference(fix.pose, prior)
        std = np.sqrt(np.diag(self.covariance + fix.covariance))
        floor = np.array([self.params.jump_floor[0], self.params.jump_floor[0], self.params.jump_floor[1]])
        if np.all(np.abs(diff) <= self.params.jump_sigmas * std + floor):
            self.rejected_jumps = 0
            return True
        self.rejected_jumps += 1
        if self.rejected_jumps >= self.params.max_rejected_jumps:
            self.rejected_jumps = 0
            self._correction = None  # the prior is wrong: restart from this fix
            return True
        return False

    def _fuse(self, fix: PoseFix, prior: Optional[Pose], odom: Pose) -> None:
        if self._correction is None or prior is None:
            pose, P = np.array(fix.pose), fix.covariance
        else:
            K = self.covariance @ np.linalg.inv(self.covariance + fix.covariance)
            pose = np.array(prior) + K @ _difference(fix.pose, prior)
            P = (np.eye(3) - K) @ self.covariance
        self.covariance = 0.5 * (P + P.T)
        fused = (float(pose[0]), float(pose[1]), wrap_angle(float(pose[2])))
        self._correction = compose(fused, relative(odom, (0.0, 0.0, 0.0)))


def _difference(a: Pose, b: Pose) -> np.ndarray:
    """a - b with the heading difference wrapped."""
    return np.array([a[0] - b[0], a[1] - b[1], wrap_angle(a[2] - b[2])])


def _merge_boxes(boxes: List[List[int]]) -> List[Tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1) with every overlapping pair replaced by their union, until none overlap."""
    merged: List[List[int]] = []
    for box in boxes:
        while True:
            overlapping = [m for m in merged if box[0] < m[2] and m[0] < box[2] and box[1] < m[3] and m[1] < box[3]]
            if not overlapping:
                break
            for m in overlapping:
                merged.remove(m)
                box = [min(box[0], m[0]), min(box[1], m[1]), max(box[2], m[2]), max(box[3], m[3])]
        merged.append(box)
    return [tuple(b) for b in merged]  # type: ignore[misc]


def _check_pose(pose: object, name: str) -> Pose:
    try:
        values = tuple(float(v) for v in pose)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (x, y, theta), got {pose!r}") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be three finite numbers (x, y, theta), got {pose!r}")
    return values  # type: ignore[return-value]
