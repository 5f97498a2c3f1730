"""Robot pose (x, y, theta) from known landmarks in the top camera, carried by odometry between fixes.

Landmark points (image u_i <-> world X_i):

* ArUco markers (``cv2.aruco.ArucoDetector``): the four corners of each marker of the map, in
  ``Landmark.aruco_corners()`` order, refined by ``cv2.cornerSubPix`` on the full image with a
  half-window of side / 8 (2-6 px; at least f + 1 after a reduction by f), then re-estimated as the
  crossings of the marker's edge lines (agent/marker_corners.py: cornerSubPix alone pulls a blurred
  convex corner 0.2-0.4 px inwards). Detection
  runs on the image reduced by an integer factor f to at most ``aruco_detection_width`` wide. With a
  pose prior, only boxes around the markers' predicted projections are searched (padded by half the
  projected side plus ``aruco_track_margin`` px; overlapping boxes merged), each at the largest
  factor that keeps its smallest predicted marker ``aruco_min_side_px`` wide, and again at full size
  when that found fewer markers than predicted in it. Without a prior, or
  when the boxes gave fewer than ``min_points`` corners, the whole reduced frame is searched, and
  the whole full-size frame too when that found fewer than ``aruco_full_resolution_below`` markers
  (small, far markers vanish in the reduced image). With a prior and ``track_smear_factors`` given
  (off by default: the missions' poses were worse with it, docs/landmarks.md "Markers under smear"),
  a marker predicted in view (side >= ``track_min_side_px``) that the detector missed, smeared by
  the camera's turn, is tracked (agent/marker_tracking.py): its centre, where a template of it smeared by shares
  ``track_smear_factors`` of the predicted smear correlates best (>= ``track_min_correlation``,
  within ``aruco_track_margin`` px of its prediction), is one more point of its own group. A fit that
  uses one has the covariance floor of ``track_pixel_sigma``, and its fix (``PoseFix.tracked``) is
  fused only within the jump gate: found where the prior put it, it never re-localizes, nor counts
  for the prior against fixes that would (in a replayed stress mission, two tracked centres fitted
  exactly, 0.15 px assumed, re-localized a pose 6 mm off to 34 cm off).
  Markers a frame shows that the map does not hold are counted for the failure reasons
  (``LandmarkDetector.diagnosis``): ids of the map's dictionaries as they are detected, and, every
  ``FOREIGN_EVERY``-th frame that shows none of the map's markers, markers of the other dictionaries.
  A map with wrong ids or the wrong dictionary then says so, where "landmarks detected in 0 frames"
  left a user looking at markers in plain view.
* Colour markers: the centres of the balls of each colour class: found at half resolution, each
  ball's lit cap with its shaded side (the same hue and saturation, darker), the centroid of its
  outline at full resolution (``_balls``, ``_ball_centre``; balls touching the border are dropped,
  their centroid is biased). Colours repeat, so a blob is associated with the
  landmark of its colour whose projection from a pose (the prior, or the markers' pose) is
  nearest, within ``color_gate`` px, and only when no other landmark of that colour is within the
  gate. Associated by the prior, ``min_points_with_prior`` blobs give a fix (the prior is the
  extra constraint). With no pose to predict from, or when the predicted association gives no fix,
  a hypothesis search finds the correspondences from a cold start (below).

Planar model. The robot stands on the floor: height, roll and pitch come from the kinematics
(T_BC), but the torso's roll is known only to a few tenths of a degree (it sways while walking and
the joint sensors lag), so the camera is modelled as T_BC' = Rx(delta) Ry(epsilon) T_BC with delta
a small unknown roll, held by a prior of std ``roll_sigma`` while walking and ``roll_sigma_still``
when the odometry moved less than ``still_motion`` per reading for ``still_settle`` s (standing: no sway;
a walk's odometry can pause for a reading while the torso still rolls;
far markers all at one height do not tell roll from position, so a loose prior would cost precision
for nothing), and epsilon a small unknown pitch, held by ``pitch_sigma``. The pitch cannot be left
to T_BC: 0.1 deg of it (a head pitch sensor's resolution, the sway's bob) shifts every point by a
pixel, which a fit of (x, y, theta) alone turns into a range error (measured on rendered frames of
the project's room: fixes 7 cm off; 0.3 deg: 20 cm off or none). All points shift together under a
pitch, so the markers' rows observe it and the loose prior costs precision only where the markers
are all at one range. The camera's own constant tilt on its mount (what getTransform omits) is
learnt from standing fixes (agent/camera_tilt.py): T_BC is first corrected by its estimate, and
the prior on t = (delta, epsilon) is N(0, Sigma_t), Sigma_t = diag(sigma_roll^2, sigma_pitch^2) +
A P A^T, the estimate's covariance P as the head angle maps it onto the torso's roll and pitch
(a turned head's camera pitch is the torso's roll). A fit that needs |epsilon| > ``max_roll_sigmas``
sqrt(Sigma_t,pitch) is no fix (the kinematics or the correspondences are wrong: points all on one
ray fit any pose with a large pitch). A point projects as

    X_B = R(theta)^T (X_W - (x, y, 0)),  X_C = R_CB Ry(-epsilon) Rx(-delta) X_B + t_CB,  u = pi(K, X_C).

Linear seed (no PnP, no 6-DOF ambiguity). With a = cos theta, b = sin theta,
p = -(a x + b y), q = b x - a y, X_B = (a X + b Y + p, -b X + a Y + q, Z) is linear in
v = (a, b, p, q), and so is X_C at delta = 0; the normalised image point (x_n, y_n) gives two
linear equations per point, x_n X_C.z - X_C.x = 0 and y_n X_C.z - X_C.y = 0. Least squares on all
points gives v (two points determine it exactly); then theta = atan2(b, a), and |(a, b)| = 1 is
the consistency check a minimal set is scored by. A rank-deficient system (one point, points on
one ray) gives no fix.

Refinement: Gauss-Newton on (x, y, theta, delta, epsilon) on every inlier point, delta and epsilon
held to their prior:

    min sum_i || u_i - pi(X_C,i) ||^2 + sigma_px^2 t^T Sigma_t^-1 t,
    R_fix = s^2 [(J^T J)^-1]_{xyθ},  s^2 = max(sigma_px^2, sum_i ||r_i||^2 / (2N - 3)),

with the analytic Jacobian dX_B/dx = (-c, s, 0), dX_B/dy = (-s, -c, 0), dX_B/dtheta =
(X_B.y, -X_B.x, 0), d(Rx(-delta) X_B)/d delta = (0, Z', -Y') (then turned by Ry(-epsilon)),
d(Ry(-epsilon) W)/d epsilon = (-W''.z, 0, W''.x) with W'' = Ry(-epsilon) W. The joint fit of
several markers starts from the planar part of the 6-DOF PnP of all points (``cv2.SOLVEPNP_SQPNP``,
free of T_BC's tilt: with far markers a 0.3 deg pitch puts the linear seed metres off, into a wrong
minimum), then from the prior, then from the linear seed, and keeps the first fit every marker
agrees with (below) at an RMS within ``max_reprojection_px``. A singular J^T J, a
point behind the camera or a non-finite residual ends the refinement with "no fix" and a reason.

Pivot. Rx(delta) Ry(epsilon) turns the camera about the body origin on the floor, as the torso
sways: it moves the camera by omega x c, omega = (delta, epsilon, 0), c = T_BC's translation, so
by (c_z epsilon, -c_z delta) on the floor. The camera's tilt on its mount and the head pitch
sensor's error turn it about itself (the neck is 9 cm away). The torso's share of t has the prior
Sigma_s = diag(sigma_roll^2, (``pitch_sigma`` sigma_roll / ``roll_sigma``)^2): walking, the frame's
whole prior is the sway's; standing (``roll_sigma_still``), the torso is still and the frame's pitch
is the head's. Widened with the roll below. The rest of t, t_m = K t, K = I - Sigma_s Sigma_t^-1
(the mount's tilt not yet learnt, a standing head's pitch), turns the camera in place, and the body
is moved back by what the fit moved the camera for it:

    (x, y) <- (x, y) + R(theta) c_z J t_m,   J (delta, epsilon) = (epsilon, -delta),

the camera's pose unchanged. The covariance is G C G^T + R c_z J (K Sigma_s) J^T R^T c_z, with G
that linear map on (x, y, theta, delta, epsilon), C its covariance and K Sigma_s the split's own
variance; a predicted fix is the same at t = 0. Turned about the floor, a standing fix in a room
whose camera sat 1 deg down on its mount was 8.8 mm off, with a std of 0.8 mm in that direction.
A first split, the sway's pitch share held to its roll's (a quarter of ``pitch_sigma``^2 walking),
moved walking fixes for the sway's pitch: the matrix's first eight missions took 5 s longer.

Robust gate (markers): the joint solution of all markers is kept when every marker's corners
reproject within ``ransac_reprojection_px``; otherwise each marker alone is a hypothesis, markers
within ``hypothesis_gate_px`` of its prediction are its consensus, and the largest consensus is
refined jointly and re-gated. A single marker has two planar solutions that nearly explain its
corners (turned either way about the line of sight, IPPE's two solutions): both seed the
refinement; the best wins when the other's squared residuals are larger by at least
``solution_evidence`` pixel variances (or fail ``max_reprojection_px``), else the one the
prior's Mahalanobis distance prefers; when neither decides, there is no fix.

Cold start with repeated colours: of the ``max_search_blobs`` largest blobs (round-robin over the
colours; clutter of a landmark colour must not make the search explode), every pair of blobs and
every pair of distinct landmarks of their colours is a minimal hypothesis (the linear seed on two
points), kept when |(a, b)| is within ``pair_scale_tolerance`` of 1. The pair ranges by the points'
rows, so it fails for far balls near the camera's height: their elevation (0.1 deg at 3 m) is below
the pitch T_BC misses (0.3 deg), and no pair's scale comes near 1 (docs/benchmarks.md, drawn colour
room). Every three of the first ``max_triple_blobs`` blobs and three distinct landmarks of their
colours is a hypothesis too, solved from the bearings alone (three-blob resection), which pitch
hardly moves. A blob's ray in the body frame, d = R_BC K^-1 (u, v, 1), seen from the camera centre
c = T_BC's translation, has the horizontal direction (d_x, d_y) (normalised); the landmark lies on it
when the cross product vanishes,

    (X_B.x - c_x) d_y - (X_B.y - c_y) d_x = 0,
    a (X d_y - Y d_x) + b (Y d_y + X d_x) + p d_y - q d_x = c_x d_y - c_y d_x,

linear in v = (a, b, p, q). Three rows M v = r leave a line v = v0 + t n (v0 the least-norm
solution, n the null vector of M); |(a, b)| = 1 on it is a quadratic in t, so up to two poses,
kept when every landmark lies ahead on its ray (not behind the camera on the same line). A rank below
three (repeated or collinear landmarks) or no real root is no hypothesis. Every hypothesis
with a landmark out of ``max_range`` or behind the camera, or the robot more than
``max_outside_balls`` outside the floor the map's balls enclose (agent/keep_in.py: a wrong one placed
the robot 2 m behind a wall, matrix seed 30), is dropped; the rest are scored by the blobs whose
nearest landmark of their colour is predicted within ``color_gate`` px (each landmark claimed once).
The distinct poses within one blob of the best consensus (of at least ``min_points``) are refined;
the one with the most points and then the least cost (squared residuals plus the tilt prior's
p_t^T Sigma_t^-1 p_t in pixel variances: a wrong triple at one height fits its bearings exactly and
its rows only with the camera tilted) wins, unless a pose more than ``ambiguity_distance`` away has as
many points and a cost within ``solution_evidence`` pixel variances: then there is no fix (the layout
is symmetric from here).

Gates on the final fit: reprojection RMS <= ``max_reprojection_px`` (a NaN fails); a torso roll
|delta| > ``max_roll_sigmas`` max(``roll_sigma``, sqrt(Sigma_t,roll)) (the walking prior, also while
standing) says the roll prior was wrong: the covariance is computed with Sigma_t's roll variance
widened to delta^2. A standing fix that is fused also teaches the tilt: the information of its data
alone on t (the Schur complement of J^T J onto t) and the vector it gives (agent/camera_tilt.py). With markers low in one band the
lateral position, the heading and delta trade against each other and the pose covariance then says
so (the jump gate, the precision gate and the fusion weigh it); with markers at several heights
delta is observed and the pose stays precise. Position std
(larger eigenvalue of R_fix's (x, y) block) <= ``max_position_std`` (far or bunched landmarks), or
``max_position_std_with_prior`` with a prior (the Kalman update weighs an imprecise fix); a jump from the
prior larger than ``jump_sigmas`` standard deviations (of P + R_fix) plus ``jump_floor``, or whose
squared Mahalanobis distance d^T (P + R_fix + F)^-1 d exceeds ``jump_chi2`` (F = diag of
``gate_floor_std``^2: both covariances are near singular, a position-heading combination known to a
tenth of a millimetre, and miss the errors frames share; the per-axis test alone let a fix 8 std off
in that combination through, and its fusion threw a standing robot's pose 39 cm, matrix seed 0), is
rejected, unless ``max_rejected_jumps`` fixes in a row disagree with the prior and agree with each
other: each rejected fix's correction C_k = fix_k (+) o_k^-1 lies within the same gate (of R_k +
R_k-1) of the previous rejected one's (then the prior is wrong: re-localize). Rejected fixes that
scatter (far, low markers whose lateral offset trades against an unmodelled torso roll) are noise,
and never overturn a prior they all disagree with. Every frame without a fix leaves its reason in ``no_fix_reason``.

Odometry: the pose is W <- odometry-frame correction C composed with the scaled odometry pose,
p = C (+) o'. The walk's speed and turn are off by scales s = (s_x, s_y, s_w) (a few percent on a NAO,
the same for a whole walk: the surface, the gait), so each odometry step d = (dx, dy, dtheta) (robot
frame, length l) is integrated as S d = (s_x dx, s_y dy, s_w dtheta) into o', and s is estimated with
the pose: the state is (p, s), its covariance P_a = [[P, P_ps], [P_sp, P_s]], with the prior
P_s = diag(k_s^2, k_s^2, k_w^2) (``odom_scale_error``, ``odom_turn_scale_error``). A step grows

    P_a <- Phi P_a Phi^T + diag(G Q G^T, Q_s),   Phi = [[F, B], [0, I]],
    F = [[1, 0, -Dy], [0, 1, Dx], [0, 0, 1]],   B = dp/ds = [[c dx, -s dy, 0], [s dx, c dy, 0], [0, 0, dtheta]],
    Q = diag(k_t^2 l (twice), k_r^2 (l + |dtheta|)),   Q_s = k_d^2 (l + |dtheta|) I,

with (Dx, Dy) = R(theta) (s_x dx, s_y dy) the step in W, (c, s) of the heading theta, G = R(theta):
the random walk (k_t, k_r) grows the variance linearly, the scale error (through B, summed over the
walk) the std linearly, so P after L metres from a first fix holds k_t^2 L + k_s^2 L^2 and
``position_std()`` says what dead reckoning is worth; the scale drifts by k_d per sqrt(m + rad)
(``odom_scale_drift``: it is not the same on every floor and gait). A fix measures p alone, so
whatever it does to p (the Kalman update or the conditioned fix below: prior P, posterior P+ and
shift dp) it does to s through their correlation, L = P_sp P^-1:

    s <- s + L dp,   P_sp <- L P+,   P_s <- P_s - L (P - P+) L^T,

which is the Kalman update of the whole state with the gain [K; L K]. Successive fixes with a walk
between them teach s: the dead reckoning between sparse fixes, whose error the object filter
cannot average out (docs/benchmarks.md, stress world 315), then drifts by the random walk and what
is left of the scale error. s is kept within ``SCALE_BOUNDS``.

and a fix is fused as a Kalman update with identity measurement and the covariance the gate
judged it by, R + F: K = P (P + R + F)^-1, p <- p + K wrap(z - p), P <- (I - K) P, then
C = p (-) o_capture (the first fix: p = z, P = R + F). With R alone, two near-singular covariances
whose thin directions nearly agree meet far from both: in stress world 303 a standing robot's
prior (thinnest std 0.03 mm) and a fix 10 cm off it (squared Mahalanobis distance 5001 without F,
34 with it: within the gate) fused 14 cm beyond the prior, away from the fix, and the object filter
took the pose's jumps for parallax (``object_lost``); with R + F the update moves it 1 mm.

Conditioned fixes. A frame can leave a direction of the pose unobserved: two balls (four equations
for the pose and the tilt), one far marker, markers bunched far away. Its fix alone is then imprecise
(std 0.5-1 m along that direction in the colours room) and its estimate wanders along a curved
valley, where a Kalman update linearized at the fix would take the valley's tangent there for a
precise measurement across it. Above ``max_position_std_with_prior``, with the prior's covariance P
known (``on_frame``; ``measure``'s ``prior_covariance``), the frame's points are fitted again from
the prior with the prior as a term of the cost (a MAP fit, the iterated Kalman update linearized at
the posterior): the information sigma_px^2 G^T P^-1 G on p, mean (prior, 0, 0) (G p is the pose,
Pivot). The fit's pose and covariance are the posterior; its points must still reproject within the
gates, and the fit's whole cost (squared residuals and prior term, in pixel variances: the
normalized innovation squared, chi-square with 2N dof) stay within its ``conditioned_confidence``
quantile: a prior 0.5 m off that says 4 cm otherwise meets two balls' bearings by turning the
heading 8 deg. It is fused as what it is, with the data's information I_d = R_post^-1 - P^-1 (negative
eigenvalues clipped: the smear's and the pivot's terms are not of the data's information form),
P <- (P^-1 + I_d)^-1, K = P I_d, and accepted only within the jump gate of P alone; it never
re-localizes and never teaches the camera tilt (its information is the prior's too).

The intrinsics' share. A focal length 0.5 % off scales every marker range alike, frame after
frame: fixes share that error, and P, which takes them as independent, shrinks below it (measured
in the sparse layout: P said 7 mm, the poses were 19 mm off, NEES ~800). So does the markers' edge
shift e (a tone curve the station is not told moves every marker edge alike: agent/marker_corners.py),
which the localizer takes out of the detected corners as estimated (``edge_shift``). With c = (s_x,
s_y, d_u, d_v, e) the intrinsics' error and what is left of e (agent/self_calibration.py; covariance
Sigma, ``intrinsics_covariance``: the prior, or the applied estimate's), a fix is z = p + G c + v
with G = dp/dc = -H^-1 J_p^T J_c (the fit's normal matrix H, J_c = ``PlanarModel.intrinsics_jacobian``).
``total_covariance`` P_t and the cross-covariance X = Cov(pose error, c) follow c as a consider
parameter (Schmidt) under the same gain K, whose pose estimates are unchanged:

    first fix:  P_t = R + G Sigma G^T,  X = G Sigma
    odometry:   P_t <- F P_t F^T + G Q G^T,  X <- F X
    fix:        A = I - K,  P_t <- A P_t A^T + A X (K G)^T + K G X^T A^T + K G Sigma G^T K^T + K R K^T,
                X <- A X + K G Sigma

each with the scales' rows (Phi for F, [K; L K] for K: P_t and X are kept for (p, s) as P_a is).

P_t is what the object filter weighs the camera pose by (docs/estimation.md, "Pose uncertainty");
P, what more fixes can reduce, drives the landmark lookout.

Map error. A user's map is measured with a tape: each landmark's centre a few millimetres off, a
marker's facing a degree or so. A fit that holds the map exact is off by several times that: the joint
fit reads the markers' places relative to each other, which the map's errors distort, and trades them
against the tilt and the heading (rendered still frames, the map 5 mm off along the walls: median error
1.3 -> 60 mm in the ring, 2.5 -> 29 mm on the walls; docs/landmarks.md "Writing the map"). Each landmark
m is moved as a whole by N(0, sigma_p^2 I_3) (``LandmarkMap.position_sigma``) and, a marker, turned about
the vertical through its centre by N(0, sigma_psi^2) (``yaw_sigma``), which moves its points' pixels by
D_m (2 k_m x 4: d u / d X_W d_mk, d_mk a unit axis or z x (X_i - X_bar_m) for the turn; d u / d X_W =
f (I_2 / z, -(x, y) / z^2) R_CW, ``PlanarModel.point_jacobian``). The fit is then generalized least
squares: each landmark's residuals and Jacobian rows are whitened by A_m,

    A_m^T A_m = sigma_px^2 (sigma_px^2 I + D_m S D_m^T)^-1,   S = diag(sigma_p^2 (three), sigma_psi^2),

at every Gauss-Newton step (``PlanarModel.whitener``), so a marker's own shape counts for its pose and its
mapped place only as much as the map is worth; H, the residuals the gates and the covariance read, the
smear's and the intrinsics' columns are all the whitened ones, and predicted fixes are likewise. Told
the map's sigmas, the fixes are better and honest (tests/test_localization.py's Monte Carlo, 5 mm and
1 deg: median error 16.5 -> 6.6 mm, NEES 170 -> 2.8, every frame a fix). The map file says how well it
is measured; a simulated room's says 0 (exact, A = I), and a file that does not say is held exact with a
warning (nao_core/landmark_map.py: taken as a tape's instead, a one-wall room lost its first fix).

Smear. A camera turning at omega (rad/s, its optical frame) during an exposure T smears the image
by s = T (-f_x omega_y, f_y omega_x) px, the rotation flow at the principal point
(agent/marker_tracking.py ``rotation_flow``; a turn about the optical axis is neglected). The frame's
stamp is set to the exposure's middle (docs/frames.md "Exposure"), so the smear's mean is right, but
a marker's outline is not: its width along s is read off by a share of |s|, and one small marker's
viewing angle, which its width carries, with it (rendered frames of a drawn room, the body turning at
0.2 rad/s, a 30 ms shutter, the kinematics at the exposure's middle: 38 of 70 one-marker fixes more
than 3.7 sigma off, up to 3.3 m; fixes of three or more markers stayed consistent, NEES ~1).
Each marker m with four corners gets a nuisance w_m ~ N(0, (``smear_width_sigma`` |s|)^2), a
stretch of w_m px along s about its centroid, d u_i / d w_m = s_hat (s_hat . (u_i - u_bar_m)) / e_m
(e_m its corners' extent along s_hat), considered (not estimated) in the fix covariance:

    C_fix += G (sum_m g_m g_m^T (sigma_w |s|)^2) G^T,   g_m = H^-1 J^T d u / d w_m.

It is large for one far marker (its viewing angle rests on its width) and small for several (their
layout holds the pose), so the precision gate and the jump gate drop what the smear made unreliable.
omega comes from consecutive frames (``on_frame``: the rotation between their R_OC = Rz(odometry
heading) R_BC over their stamps' difference, when at most ``rate_max_gap`` apart; else the camera is
taken as still), and T is ``exposure``, the NAO's longest indoor exposure (the real one is not
reported): sharp frames of a turning camera then lose their one-marker fixes too (the same room
without a shutter: one-marker fixes 17 → 3 of 1015 frames, all fixes 1015 → 968), and the lookout
stands when fixes stop (station/pilot.py).

Stamp error, not considered. A frame's stamp may be off the instant its image shows (docs/frames.md),
so while the camera turns at omega its T_BC is off by a turn omega dt, which the fix's heading
absorbs: the robot's heading is off by it, the camera's, which the image gives, is not. The object's
bearing in the same frame shares that T_BC, so the camera's heading (the fused pose times T_BC) is
what it needs. Considering the stamp's error in the fix (C_fix += G g g^T G^T, g = H^-1 J^T (d u /
d e) omega sigma_s, d X_C = X_C x e) made the fixes consistent as robot poses (the ring's views, the
head turning at 0.2 rad/s, T_BC of an instant N(0, 20 ms) off: NEES mean 24 → 1.2), but the fused
pose then kept its heading while T_BC turned, and the pilot's object estimate followed the late
kinematics: in tests/test_pilot.py's sweep with frames 70 ms late, it moved 23 mm instead of 5
(told nothing) and 5.1 mm instead of 1.2 (told 0.1 s). The object filter weighs the stamp's error in
its bearings instead, on every frame (station/pilot.py).

Predicted precision (for the pilot and ``station check-layout``): from a pose and T_BC, the
landmark points that would be detected (in the image where the lens shows them, with a margin, in
front, facing the camera,
at least ``aruco_min_side_px`` / a disc of ``landmark_min_area``) give J and the fix covariance
sigma_px^2 (J^T J)^-1 the measurement would have; ``best_landmark_view`` scans the head's range
for the direction with the smallest predicted position std.
"""

from __future__ import annotations

import collections
import itertools
import math
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Dict, Iterable, Iterator, List, Literal, Optional, Sequence, Tuple

import cv2
import numpy as np
from scipy.linalg import solve_triangular
from scipy.special import chdtri  # inverse chi-square survival: chi2.ppf(p, k) = chdtri(k, 1 - p)

from agent.camera import CameraModel
from agent.camera_tilt import CameraTilt
from agent.keep_in import KeepIn
from agent.marker_corners import edge_shift_jacobian, refine_corners
from agent.marker_tracking import marker_texture, rotation_flow, track_marker
from agent.perception import ColorClass, PerceptionParams, check_image, color_mask
from agent.pose_smoother import TrackPoint, smooth_track
from nao_core.config import bounds
from nao_core.geometry import (
    Pose,
    camera_in_world,
    compose,
    invert,
    relative,
    rot_x,
    rot_y,
    rot_z,
    wrap_angle,
)
from nao_core.landmark_map import ARUCO_DICTIONARIES, Landmark, LandmarkMap


@dataclass(frozen=True)
class LocalizationParams:
    """Detection, planar solve, gates and odometry noise (config/localization.yaml, section ``localization``)."""

    ransac_reprojection_px: float = field(metadata=bounds(0.1, 50.0))  # a marker's corners within this of the joint fit are inliers, px
    hypothesis_gate_px: float = field(metadata=bounds(0.1, 200.0))  # consensus gate around a one-marker hypothesis, px
    min_points: int = field(metadata=bounds(2, 1000))  # fewer landmark points -> no fix
    min_points_with_prior: int = field(metadata=bounds(2, 1000))  # ... when the prior associated them (it is the extra constraint)
    max_reprojection_px: float = field(metadata=bounds(0.01, 50.0))  # RMS gate on the final fit, px
    pixel_sigma: float = field(metadata=bounds(0.01, 10.0))  # image point noise, px
    exposure: float = field(metadata=bounds(0.0, 0.2))  # s, the exposure the camera's motion smear is reckoned with
    smear_width_sigma: float = field(metadata=bounds(0.0, 10.0))  # a marker's width along the smear is uncertain by this share of it
    rate_max_gap: float = field(metadata=bounds(0.0, 10.0))  # s: the camera's rate from two frames at most this far apart, else unknown
    roll_sigma: float = field(metadata=bounds(1e-5, 0.2))  # rad, prior std of the torso roll missing from T_BC (walking)
    roll_sigma_still: float = field(metadata=bounds(1e-6, 0.2))  # rad, the same when odometry did not move since the last reading
    pitch_sigma: float = field(metadata=bounds(1e-5, 0.2))  # rad, prior std of the camera pitch missing from T_BC
    camera_tilt_sigma: Tuple[float, float] = field(metadata=bounds(1e-5, 0.2))  # rad, (roll, pitch) of the camera on its mount, before learning
    camera_tilt_floor: float = field(metadata=bounds(1e-6, 0.2))  # rad, the learnt tilt's std never drops below this
    still_motion: float = field(metadata=bounds(0.0, 0.1))  # m and rad: odometry moving less than this per reading is standing (sensor jitter)
    still_settle: float = field(metadata=bounds(0.0, 10.0))  # s: ... once it has not moved for this long (a walk's odometry pauses between readings)
    max_search_blobs: int = field(metadata=bounds(2, 100))  # the cold-start search uses at most this many blobs (largest first)
    max_triple_blobs: int = field(metadata=bounds(3, 100))  # ... its three-blob hypotheses the first this many of them
    pair_scale_tolerance: float = field(metadata=bounds(0.0, 1.0))  # |(cos, sin)| of a two-blob hypothesis within this of 1
    solution_evidence: float = field(metadata=bounds(0.0, 1000.0))  # squared-residual gap (pixel variances) that decides two poses explaining the same points
    ambiguity_distance: float = field(metadata=bounds(0.0, 10.0))  # m: rival hypotheses further apart than this are distinct
    max_range: float = field(metadata=bounds(0.1, 100.0))  # m: a hypothesis placing a landmark further than this from the camera is rejected
    max_outside_balls: float = field(metadata=bounds(0.0, 100.0))  # m: ... or the robot further than this outside the floor the balls enclose
    jump_sigmas: float = field(metadata=bounds(0.0, 100.0))  # jump gate in standard deviations
    max_roll_sigmas: float = field(metadata=bounds(0.5, 100.0))  # roll beyond this many prior std widens the covariance; pitch beyond it is no fix
    jump_floor: Tuple[float, float] = field(metadata=bounds(0.0, 10.0))  # (m, rad) always tolerated
    jump_chi2: float = field(metadata=bounds(0.0, 1e9))  # squared Mahalanobis distance of a jump
    gate_floor_std: Tuple[float, float] = field(metadata=bounds(0.0, 1.0))  # (m, rad) added to P + R_fix in it
    conditioned_confidence: float = field(metadata=bounds(0.5, 0.999999))  # chi-square quantile a conditioned fit's NIS must be within
    max_rejected_jumps: int = field(metadata=bounds(1, 1000))  # then the prior is wrong: accept
    color_gate: float = field(metadata=bounds(1.0, 1000.0))  # px, colour-landmark association gate
    color_below_aruco_points: int = field(metadata=bounds(0, 1000))  # colour landmarks only below this many ArUco corners
    ball_shade_floor: float = field(metadata=bounds(0.0, 1.0))  # a ball's shaded side: its class's value floor times this
    odom_translation_noise: float = field(metadata=bounds(0.0, 1.0))  # k_t, m per sqrt(m)
    odom_rotation_noise: float = field(metadata=bounds(0.0, 1.0))  # k_r, rad per sqrt(m + rad)
    odom_scale_error: float = field(metadata=bounds(0.0, 1.0))  # k_s, std of the walk's speed scale error
    odom_turn_scale_error: float = field(metadata=bounds(0.0, 1.0))  # k_w, std of the turn scale error
    odom_scale_drift: float = field(metadata=bounds(0.0, 1.0))  # k_d, the scales' random walk per sqrt(m + rad)
    aruco_corner_refinement: Literal["none", "subpix", "contour"]
    aruco_edge_refinement: bool  # corners as the intersections of the marker's edge lines (agent/marker_corners.py)
    aruco_detection_width: int = field(metadata=bounds(160, 10000))  # px, detect markers on an image at most this wide
    aruco_min_side_px: float = field(metadata=bounds(4.0, 200.0))  # px, smallest marker side the detector is asked to find (in its image)
    aruco_full_resolution_below: int = field(metadata=bounds(0, 1000))  # markers found reduced: below this, search full size too
    aruco_threshold_windows: Tuple[int, int, int] = field(metadata=bounds(3, 99))  # adaptive threshold (min, max, step), px
    aruco_error_correction: float = field(metadata=bounds(0.0, 1.0))  # cv2 errorCorrectionRate: share of the dictionary's correctable bits
    aruco_track_margin: float = field(metadata=bounds(0.0, 1000.0))  # px around predicted markers searched with a prior
    track_smear_factors: Tuple[float, ...] = field(metadata=bounds(0.0, 2.0))  # undetected predicted markers tracked with these shares of the smear (empty: none)
    track_min_side_px: float = field(metadata=bounds(4.0, 200.0))  # px: ... when their predicted side is at least this
    track_min_correlation: float = field(metadata=bounds(0.0, 1.0))  # ... and kept when the template correlates at least this well
    track_template_blur: float = field(metadata=bounds(0.0, 10.0))  # px, Gaussian blur of the tracking template (the lens, the resampling)
    track_pixel_sigma: float = field(metadata=bounds(0.01, 10.0))  # px, a tracked centre's noise: the fix covariance's floor when a fit uses one
    view_margin_px: float = field(metadata=bounds(0.0, 100.0))  # predicted points this close to the border are not counted
    max_position_std: float = field(metadata=bounds(1e-4, 10.0))  # m: a fix less precise than this is no fix
    max_position_std_with_prior: float = field(metadata=bounds(1e-4, 10.0))  # m: the same with a prior (the fusion weighs it)


@dataclass(frozen=True)
class PoseFix:
    """A robot pose measured from landmarks in one frame (before fusion with the prior)."""

    pose: Pose
    covariance: np.ndarray  # 3 x 3, of (x, y, theta)
    rms_px: float  # reprojection RMS of the inliers
    landmark_ids: Tuple[object, ...]
    points: int  # inlier points used
    T_WC: np.ndarray  # camera pose of the fit (with the estimated torso roll and pitch)
    roll: float = 0.0  # rad, torso roll the fit found missing from T_BC
    inliers: Optional[Tuple[np.ndarray, np.ndarray]] = None  # (world N x 3, pinhole pixels N x 2) the fit used
    inlier_groups: Optional[np.ndarray] = None  # N: their landmark (four points a marker, in corner order)
    edge_shift: float = 0.0  # px, the markers' edge shift its corners were corrected by (agent/marker_corners.py)
    T_BC: Optional[np.ndarray] = None  # the kinematics it was fitted with (corrected by the camera tilt learnt then)
    T_BC_reported: Optional[np.ndarray] = None  # the same as reported, before that correction (None: T_BC is)
    roll_sigma: float = 0.0  # rad, the roll prior it was fitted with
    tilt_information: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))  # I_d: the data's on (delta, epsilon), rad^-2
    tilt_evidence: np.ndarray = field(default_factory=lambda: np.zeros(2))  # I_d t_d (agent/camera_tilt.py)
    intrinsics_gain: np.ndarray = field(default_factory=lambda: np.zeros((3, N_INTRINSICS)))  # G = d(x, y, theta)/d(s_x, s_y, d_u, d_v, e)
    conditioned: bool = False  # pose and covariance are the frame's data and the prior's together (module docstring)
    tracked: int = 0  # markers among its landmarks that were tracked from the prior (agent/marker_tracking.py)


@dataclass(frozen=True)
class LandmarkView:
    """A head direction and the fix it would give (``best_landmark_view``)."""

    yaw: float
    pitch: float
    points: int
    position_std: float  # m, sqrt of the larger eigenvalue of the predicted (x, y) covariance
    heading_std: float  # rad


class NoFix(Exception):
    """A frame gives no fix; the message is the reason."""


class _Ambiguous(NoFix):
    """One marker with two planar solutions: other landmarks (colour blobs) may tell them apart."""

    def __init__(self, reason: str, points: "_Points", poses: List[np.ndarray]):
        super().__init__(reason)
        self.points, self.poses = points, poses


_CORNER_REFINEMENT = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
}
Box = Tuple[int, int, int, int, float, int]  # x0, y0, x1, y1 (full-size px), smallest predicted marker side, markers predicted
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
N_INTRINSICS = 5  # (s_x, s_y, d_u, d_v, e): the intrinsics' error and the markers' edge shift (agent/self_calibration.py)
SCALE_BOUNDS = (0.7, 1.3)  # the odometry scales s are kept within these (a NAO's walk is off by a few percent)
MIN_DEPTH = 0.05  # m: a landmark point closer to the camera plane than this is behind it, for the fit


@dataclass
class _Points:
    """Correspondences: world points (N x 3), observed pixels (N x 2), landmark id and group per point."""

    X: np.ndarray
    u: np.ndarray
    ids: List[object]
    group: np.ndarray  # points of one marker share a group; a colour blob is its own

    @classmethod
    def empty(cls) -> "_Points":
        return cls(np.empty((0, 3)), np.empty((0, 2)), [], np.empty(0, dtype=int))

    def __len__(self) -> int:
        return len(self.X)

    def take(self, mask: np.ndarray) -> "_Points":
        return _Points(self.X[mask], self.u[mask], [i for i, m in zip(self.ids, mask) if m], self.group[mask])

    def __add__(self, other: "_Points") -> "_Points":
        offset = self.group.max() + 1 if len(self) else 0
        return _Points(np.vstack([self.X, other.X]), np.vstack([self.u, other.u]), self.ids + other.ids,
                       np.concatenate([self.group, other.group + offset]))

    @property
    def landmark_ids(self) -> Tuple[object, ...]:
        return tuple(dict.fromkeys(self.ids))


class PlanarModel:
    """Projection of world points by a robot pose on the floor, with T_BC and the camera intrinsics."""

    def __init__(self, camera: CameraModel, T_BC: np.ndarray, map_error: Tuple[float, float, float] = (0.0, 0.0, 1.0)):
        """``map_error``: (position_sigma m, yaw_sigma rad, pixel_sigma px) of the map and the image points
        (module docstring, Map error); the map exact (the default), ``whitener`` is the identity."""
        self.camera = camera
        self.T_BC = T_BC
        self.map_error = map_error
        T_CB = invert(T_BC)
        self.R_CB, self.t_CB = T_CB[:3, :3], T_CB[:3, 3]
        K = camera.K
        self.f, self.c = np.array([K[0, 0], K[1, 1]]), K[:2, 2]

    def to_camera(self, p: np.ndarray, X: np.ndarray) -> np.ndarray:
        """X_C (N x 3) for p = (x, y, theta[, delta[, epsilon]])."""
        c, s = math.cos(p[2]), math.sin(p[2])
        d = X - np.array([p[0], p[1], 0.0])
        X_T = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]]) @ _tilt(p).T
        return X_T @ self.R_CB.T + self.t_CB

    def to_cameras(self, poses: np.ndarray, X: np.ndarray) -> np.ndarray:
        """X_C (H x N x 3) of world points X (H x N x 3, or N x 3 for all) from planar poses (H x 3), untilted."""
        return _in_bodies(poses, X) @ self.R_CB.T + self.t_CB

    def project(self, p: np.ndarray, X: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Undistorted pixels (N x 2, NaN behind the camera) and depths z_C (N)."""
        X_C = self.to_camera(p, X)
        return _pixels(self, X_C), X_C[:, 2]

    def jacobian(self, p: np.ndarray, X: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(uv N x 2, z N, J N x 2 x len(p)) at p = (x, y, theta, delta[, epsilon])."""
        c, s = math.cos(p[2]), math.sin(p[2])
        R_roll = rot_x(-p[3])[:3, :3]
        R_pitch = rot_y(-p[4] if len(p) > 4 else 0.0)[:3, :3]
        tilt = R_pitch @ R_roll
        d = X - np.array([p[0], p[1], 0.0])
        X_B = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
        X_R = X_B @ R_roll.T
        X_T = X_R @ R_pitch.T
        X_C = X_T @ self.R_CB.T + self.t_CB
        zero = np.zeros(len(X))
        dB = np.zeros((len(X), 3, len(p)))  # d(Ry(-epsilon) Rx(-delta) X_B) / dp
        dB[:, :, 0] = tilt @ np.array([-c, s, 0.0])
        dB[:, :, 1] = tilt @ np.array([-s, -c, 0.0])
        dB[:, :, 2] = np.column_stack([X_B[:, 1], -X_B[:, 0], zero]) @ tilt.T
        dB[:, :, 3] = np.column_stack([zero, X_R[:, 2], -X_R[:, 1]]) @ R_pitch.T
        if len(p) > 4:
            dB[:, :, 4] = np.column_stack([-X_T[:, 2], zero, X_T[:, 0]])
        dC = np.einsum("ij,njk->nik", self.R_CB, dB)
        z = X_C[:, 2]
        # d(f a / z) = f (da z - a dz) / z^2 for a = x, y
        J = self.f[None, :, None] * (dC[:, :2, :] * z[:, None, None] - X_C[:, :2, None] * dC[:, 2:3, :]) / z[:, None, None] ** 2
        uv = self.f * X_C[:, :2] / z[:, None] + self.c
        return uv, z, J

    def point_jacobian(self, p: np.ndarray, X: np.ndarray) -> np.ndarray:
        """d(u, v)/d X_W (N x 2 x 3) of world points X at p = (x, y, theta, delta, epsilon): the camera's
        rotation from the world, R_CB Ry(-epsilon) Rx(-delta) Rz(theta)^T, then the projection's
        f (I_2 / z, -(x, y) / z^2)."""
        R_CW = self.R_CB @ _tilt(p) @ rot_z(p[2])[:3, :3].T
        X_C = self.to_camera(p, X)
        z = X_C[:, 2]
        dproj = np.zeros((len(X), 2, 3))
        dproj[:, 0, 0], dproj[:, 1, 1] = self.f[0] / z, self.f[1] / z
        dproj[:, :, 2] = -self.f * X_C[:, :2] / z[:, None] ** 2
        return dproj @ R_CW

    def whitener(self, p: np.ndarray, X: np.ndarray, group: Optional[np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
        """The map taking rows (2N x k: residuals or their derivatives, points in order) to A rows, A the
        block-diagonal whitening of the points' errors at p: per landmark of ``group``,
        A_m^T A_m = s^2 (s^2 I + D_m S D_m^T)^-1, D_m its points' pixel moves under its own translation
        (three axes) and, a marker, turn about the vertical (module docstring, Map error), S their
        variances, s the pixel sigma. The identity with an exact map or no groups; NoFix when a C_m has
        no Cholesky factor."""
        position_sigma, yaw_sigma, pixel_sigma = self.map_error
        if group is None or (position_sigma == 0.0 and yaw_sigma == 0.0) or not len(X):
            return lambda rows: rows
        dU = self.point_jacobian(p, X)
        factors = []  # (the landmark's rows, L_m with L_m L_m^T = C_m)
        for g in np.unique(group):
            mine = np.flatnonzero(group == g)
            moves, variances = [np.tile(axis, (len(mine), 1)) for axis in np.eye(3)], [position_sigma**2] * 3
            if len(mine) >= 4:  # a marker: its facing
                arm = X[mine] - X[mine].mean(axis=0)
                moves.append(np.column_stack([-arm[:, 1], arm[:, 0], np.zeros(len(mine))]))
                variances.append(yaw_sigma**2)
            D = np.column_stack([np.einsum("nij,nj->ni", dU[mine], move).ravel() for move in moves])
            try:
                L = np.linalg.cholesky(pixel_sigma**2 * np.eye(2 * len(mine)) + (D * variances) @ D.T)
            except np.linalg.LinAlgError as exc:
                raise NoFix(f"the map's error does not whiten at this pose ({exc})") from None
            factors.append((np.ravel(np.column_stack([2 * mine, 2 * mine + 1])), L))

        def whiten(rows: np.ndarray) -> np.ndarray:  # A rows = s L_m^-1 rows, landmark by landmark
            out = np.array(rows, dtype=float, copy=True)
            for rows_of, L in factors:
                out[rows_of] = pixel_sigma * solve_triangular(L, out[rows_of], lower=True, check_finite=False)  # NaN flows to the fit's checks
            return out

        return whiten

    def intrinsics_jacobian(self, uv: np.ndarray, group: np.ndarray, K0: Optional[np.ndarray] = None) -> np.ndarray:
        """d(u, v)/d(s_x, s_y, d_u, d_v, e) (N x 2 x ``N_INTRINSICS``) at projections ``uv`` (N x 2) of points
        grouped by ``group`` (four a marker), for the intrinsics f_x' = f0_x (1 + s_x), f_y' = f0_y (1 + s_y),
        c' = c + d of agent/self_calibration.py and the markers' edge shift e (agent/marker_corners.py):
        du/ds_x = f0_x x/z = f0_x (u - c_x) / f_x, dv/ds_y likewise, du/dd_u = dv/dd_v = 1, d u/d e =
        ``edge_shift_jacobian``. ``K0``: the K the scales are relative to (default this model's)."""
        f0 = self.f if K0 is None else np.array([K0[0, 0], K0[1, 1]])
        J = np.zeros((len(uv), 2, N_INTRINSICS))
        J[:, 0, 0] = f0[0] * (uv[:, 0] - self.c[0]) / self.f[0]
        J[:, 1, 1] = f0[1] * (uv[:, 1] - self.c[1]) / self.f[1]
        J[:, 0, 2] = 1.0
        J[:, 1, 3] = 1.0
        J[:, :, 4] = edge_shift_jacobian(uv, group)
        return J

    def linear_seed(self, X: np.ndarray, target: np.ndarray) -> Tuple[np.ndarray, float]:
        """(x, y, theta) and |(a, b)| of the linear planar solve (module docstring); raises NoFix when degenerate."""
        n = (target - self.c) / self.f  # normalised image coordinates
        rows, rhs = _linear_rows(X, n, self.R_CB, self.t_CB)
        if len(rows) < 4:
            raise NoFix(f"{len(X)} point(s): a planar pose needs two")
        scale = np.linalg.norm(rows, axis=1, keepdims=True)  # equilibrate: far points have larger rows
        scale[scale == 0] = 1.0
        v, _, rank, sv = np.linalg.lstsq(rows / scale, rhs / scale.ravel(), rcond=None)
        if rank < 4 or not np.all(np.isfinite(v)) or sv[-1] < 1e-9 * sv[0]:
            raise NoFix("degenerate point set (collinear with the camera or repeated): the planar pose is undetermined")
        return _pose_of(v), float(math.hypot(v[0], v[1]))

    def refine(self, p0: Sequence[float], X: np.ndarray, target: np.ndarray, prior: np.ndarray,
               iterations: int = 8, mean: Optional[np.ndarray] = None,
               group: Optional[np.ndarray] = None) -> Tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        """Gauss-Newton on (x, y, theta, delta, epsilon) with the prior N(``mean``, information ``prior``)
        (5 x 5, pixel units; the tilt's alone, ``tilt_information``, has mean 0), the residuals whitened by
        the map's error per landmark of ``group`` (``whitener``): (p, rms, per-point error N, J^T J + prior),
        the errors whitened too. Raises NoFix."""
        p = np.zeros(5)
        p[: len(p0)] = p0[:5]
        mean = np.zeros(5) if mean is None else mean
        for _ in range(iterations):
            uv, z, J = self.jacobian(p, X)
            if np.any(z < MIN_DEPTH):
                raise NoFix(f"{int(np.sum(z < MIN_DEPTH))} landmark point(s) behind the camera at the fit")
            whitened = self.whitener(p, X, group)(np.column_stack([(uv - target).ravel(), J.reshape(-1, 5)]))
            r, Jr = whitened[:, 0], whitened[:, 1:]
            H = Jr.T @ Jr + prior
            g = Jr.T @ r + prior @ _from_mean(p, mean)
            if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
                raise NoFix("non-finite residuals in the planar fit")
            if np.linalg.cond(H) > 1e12:
                raise NoFix("singular normal equations in the planar fit (points do not constrain the pose)")
            dp = -np.linalg.solve(H, g)
            p += dp
            p[2] = wrap_angle(p[2])
            if np.abs(dp).max() < 1e-8:  # m, rad: from the linear seed 3-4 steps get there
                break
        uv, z, J = self.jacobian(p, X)
        if np.any(z < MIN_DEPTH):
            raise NoFix("landmark point(s) behind the camera at the fit")
        whitened = self.whitener(p, X, group)(np.column_stack([(uv - target).ravel(), J.reshape(-1, 5)]))
        err = np.linalg.norm(whitened[:, 0].reshape(-1, 2), axis=1)
        Jr = whitened[:, 1:]
        H = Jr.T @ Jr + prior
        rms = float(np.sqrt(np.mean(err**2)))
        if not math.isfinite(rms):
            raise NoFix("non-finite reprojection error")
        return p, rms, err, H


def _planar_seeds(model: PlanarModel, rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray]) -> List[np.ndarray]:
    """(x, y, theta) of the robot under each PnP camera pose (T_WB = T_WC T_BC^-1), the finite ones."""
    seeds = []
    for rvec, tvec in zip(rvecs, tvecs):
        T_CW = np.eye(4)
        T_CW[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=float))[0]
        T_CW[:3, 3] = np.ravel(tvec)
        T_WB = invert(T_CW) @ invert(model.T_BC)
        if np.all(np.isfinite(T_WB)):
            seeds.append(np.array([T_WB[0, 3], T_WB[1, 3], math.atan2(T_WB[1, 0], T_WB[0, 0])]))
    return seeds


def _in_bodies(poses: np.ndarray, X: np.ndarray) -> np.ndarray:
    """X_B = R(theta)^T (X - (x, y, 0)) (H x N x 3) of world points X (H x N x 3, or N x 3 for all) from planar poses (H x 3)."""
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    dx, dy = X[..., 0] - poses[:, 0:1], X[..., 1] - poses[:, 1:2]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, np.broadcast_to(X[..., 2], dx.shape)], axis=-1)


def _pixels(model: PlanarModel, X_C: np.ndarray) -> np.ndarray:
    """Pinhole pixels (... x 2) of camera points (... x 3), NaN behind the camera."""
    z = X_C[..., 2:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = model.f * X_C[..., :2] / z + model.c
    return np.where(z > 1e-9, uv, np.nan)


def _triple_poses(model: PlanarModel, X: np.ndarray, u: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(x, y, theta) of every three-point hypothesis (H x 3 x 3, H x 3 x 2) from the points' bearings
    alone, and its points (module docstring, "three-blob resection"): up to two poses each."""
    n = (u - model.c) / model.f
    d_B = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], axis=-1) @ model.R_CB  # R_BC d_C, row vectors
    d = d_B[..., :2] / np.linalg.norm(d_B[..., :2], axis=-1, keepdims=True)
    c = model.T_BC[:2, 3]
    M = np.stack([X[..., 0] * d[..., 1] - X[..., 1] * d[..., 0], X[..., 1] * d[..., 1] + X[..., 0] * d[..., 0],
                  d[..., 1], -d[..., 0]], axis=-1)
    r = c[0] * d[..., 1] - c[1] * d[..., 0]
    U, S, Vt = np.linalg.svd(M)
    ok = S[:, 2] > 1e-9 * S[:, 0]
    v0 = np.einsum("hij,hi->hj", Vt[:, :3], np.einsum("hji,hj->hi", U, r) / np.where(ok[:, None], S, 1.0))  # least norm
    null = Vt[:, 3]
    # |(a, b)| = 1 on the line v0 + t null: A t^2 + B t + C = 0
    A = null[:, 0] ** 2 + null[:, 1] ** 2
    B = 2.0 * (v0[:, 0] * null[:, 0] + v0[:, 1] * null[:, 1])
    C = v0[:, 0] ** 2 + v0[:, 1] ** 2 - 1.0
    disc = B**2 - 4.0 * A * C
    ok &= (A > 1e-12) & (disc >= 0.0)
    root = np.sqrt(np.where(ok, disc, 0.0))
    A = np.where(ok, A, 1.0)
    v = np.concatenate([v0 + ((-B + root) / (2 * A))[:, None] * null, v0 + ((-B - root) / (2 * A))[:, None] * null])
    poses, points, rays = _pose_of(v), np.concatenate([X, X]), np.concatenate([d, d])
    # the landmarks ahead on their rays, not behind the camera on the same lines
    ahead = np.all(np.einsum("hnk,hnk->hn", _in_bodies(poses, points)[..., :2] - c, rays) > 0.0, axis=1)
    keep = np.concatenate([ok, ok]) & ahead
    return poses[keep], points[keep]


def camera_rotation(odom: Pose, T_BC: np.ndarray) -> np.ndarray:
    """R_OC: the camera's orientation in the odometry frame, Rz(odometry heading) R_BC."""
    return rot_z(odom[2])[:3, :3] @ np.asarray(T_BC, dtype=float)[:3, :3]


def angular_velocity(R_OC_before: np.ndarray, R_OC: np.ndarray, dt: float) -> np.ndarray:
    """rad/s, the camera's angular velocity in its own axes from two orientations ``dt`` s apart."""
    return cv2.Rodrigues(R_OC_before.T @ R_OC)[0].ravel() / dt


def tilt_information(pixel_sigma: float, covariance: np.ndarray) -> np.ndarray:
    """The 5 x 5 information (pixel units) a prior N(0, ``covariance``) on (delta, epsilon) adds to
    J^T J of (x, y, theta, delta, epsilon)."""
    prior = np.zeros((5, 5))
    prior[3:, 3:] = pixel_sigma**2 * np.linalg.inv(covariance)
    return prior


def head_pivot(p: np.ndarray, height: float, tilt_covariance: np.ndarray, sway_covariance: np.ndarray
               ) -> Tuple[np.ndarray, np.ndarray]:
    """(G 3 x 5, its own 3 x 3 covariance): the body pose G p of a fit p = (x, y, theta, delta, epsilon)
    whose tilt t turned the camera, at ``height`` above the floor, about the body origin, once the part
    of t beyond the torso's sway (prior ``sway_covariance`` of ``tilt_covariance``) turns it about itself
    (module docstring, Pivot); G is linear in p at its theta."""
    c, s = math.cos(p[2]), math.sin(p[2])
    share = np.eye(2) - sway_covariance @ np.linalg.inv(tilt_covariance)  # K
    swap = np.array([[0.0, 1.0], [-1.0, 0.0]])  # J: (delta, epsilon) -> (epsilon, -delta)
    move = height * np.array([[c, -s], [s, c]]) @ swap  # R(theta) c_z J
    G = np.zeros((3, 5))
    G[:, :3] = np.eye(3)
    G[:2, 3:] = move @ share
    share_variance = share @ sway_covariance
    own = np.zeros((3, 3))
    own[:2, :2] = move @ (0.5 * (share_variance + share_variance.T)) @ move.T
    return G, own


def _tilt(p: Sequence[float]) -> np.ndarray:
    """Ry(-epsilon) Rx(-delta): a body point as the camera's kinematics see it under the torso's
    unmodelled roll delta and pitch epsilon (0 when p has no such entries)."""
    delta = p[3] if len(p) > 3 else 0.0
    epsilon = p[4] if len(p) > 4 else 0.0
    return rot_y(-epsilon)[:3, :3] @ rot_x(-delta)[:3, :3]


def _linear_rows(X: np.ndarray, n: np.ndarray, R_CB: np.ndarray, t_CB: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Two rows per point of M v = rhs, v = (a, b, p, q) (module docstring)."""
    N = len(X)
    A = np.zeros((N, 3, 4))  # X_B = A v + (0, 0, Z)
    A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = X[:, 0], X[:, 1], 1.0
    A[:, 1, 0], A[:, 1, 1], A[:, 1, 3] = X[:, 1], -X[:, 0], 1.0
    M = np.einsum("ij,njk->nik", R_CB, A)  # X_C = M v + m0
    m0 = X[:, 2:3] * R_CB[:, 2][None, :] + t_CB
    rows = np.concatenate([n[:, 0:1] * M[:, 2] - M[:, 0], n[:, 1:2] * M[:, 2] - M[:, 1]], axis=0)
    rhs = np.concatenate([m0[:, 0] - n[:, 0] * m0[:, 2], m0[:, 1] - n[:, 1] * m0[:, 2]])
    return rows, rhs


def _pose_of(v: np.ndarray) -> np.ndarray:
    """(x, y, theta) from v = (a, b, p, q), (a, b) normalised (works on stacks ... x 4)."""
    norm = np.hypot(v[..., 0], v[..., 1])
    c, s = v[..., 0] / norm, v[..., 1] / norm
    x = -c * v[..., 2] + s * v[..., 3]
    y = -s * v[..., 2] - c * v[..., 3]
    return np.stack([x, y, np.arctan2(s, c)], axis=-1)


def check_ball_colours(landmark_map: LandmarkMap, perception: PerceptionParams) -> None:
    """ValueError naming the first colour landmark whose colour is no perception class, or the
    object's: its ball would be taken for the object (docs/landmarks.md, "Colours")."""
    for lm in landmark_map.of_kind("color"):
        if lm.color not in perception.colors:
            raise ValueError(f"landmark {lm.id!r}: colour {lm.color!r} is not a perception colour class "
                             f"({sorted(perception.colors)})")
        if lm.color == perception.object_color:
            raise ValueError(f"landmark {lm.id!r}: colour {lm.color!r} is the object's (perception.object_color): "
                             "its ball would be taken for the object; use another colour")


FOREIGN_EVERY = 10  # frames without a map marker between looks for markers of other dictionaries (``look_for_unmapped``)
UNMAPPED_FRAMES = 3  # frames a marker the map does not hold is seen in before a failure's reason names it


class LandmarkDetector:
    """Image points of the map's landmarks in one frame: ArUco corners and colour blobs."""

    def __init__(self, params: LocalizationParams, landmark_map: LandmarkMap, perception: Optional[PerceptionParams]):
        self.params = params
        self.perception = perception
        self.aruco: Dict[str, Dict[int, np.ndarray]] = {}
        for lm in landmark_map.of_kind("aruco"):
            self.aruco.setdefault(str(lm.dictionary), {})[int(lm.id)] = lm.aruco_corners()
        self.aruco_corners = np.array([c for markers in self.aruco.values() for c in markers.values()]).reshape(-1, 3)
        self._marker_keys = [(name, marker_id) for name, markers in self.aruco.items() for marker_id in markers]  # ... their order
        self.aruco_normals = np.array([lm.normal for lm in landmark_map.of_kind("aruco")]).reshape(-1, 3)
        detector_params = cv2.aruco.DetectorParameters()
        detector_params.cornerRefinementMethod = _CORNER_REFINEMENT[params.aruco_corner_refinement]
        (detector_params.adaptiveThreshWinSizeMin, detector_params.adaptiveThreshWinSizeMax,
         detector_params.adaptiveThreshWinSizeStep) = params.aruco_threshold_windows
        detector_params.errorCorrectionRate = params.aruco_error_correction
        self.detector_params = detector_params
        self.dictionaries = {name: cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)) for name in self.aruco}
        # markers the map does not hold, for the failure reasons: (dictionary, id) -> searches that found it
        self.unmapped: collections.Counter = collections.Counter()
        self._foreign = {name: cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
                         for name in ARUCO_DICTIONARIES if name not in self.aruco} if self.aruco else {}
        self._frames_without_markers = 0
        self._textures: Dict[Tuple[str, int], Tuple[np.ndarray, np.ndarray]] = {}  # tracking templates, made when first needed
        self.colors: Dict[str, List[Landmark]] = {}
        if perception is not None:
            check_ball_colours(landmark_map, perception)
            for lm in landmark_map.of_kind("color"):
                self.colors.setdefault(str(lm.color), []).append(lm)
        self.color_landmarks = [lm for lms in self.colors.values() for lm in lms]
        self.shaded: Dict[str, ColorClass] = {}  # each class with its value floor lowered to a ball's shade (``_balls``)
        for name in self.colors:
            color = perception.colors[name]
            self.shaded[name] = replace(color, value=(int(color.value[0] * params.ball_shade_floor), color.value[1]))

    def _detect(self, image: np.ndarray, min_side: float, unmapped: Optional[set] = None,
                dictionaries: Optional[Dict[str, Any]] = None) -> List[Tuple[str, int, np.ndarray]]:
        """(dictionary, id, corners 4 x 2) of the map's markers found in ``image``; the (dictionary, id) of the
        others go to ``unmapped``. ``dictionaries``: search these instead (default the map's)."""
        found = []
        self.detector_params.minMarkerPerimeterRate = max(1e-3, min(1.0, 4.0 * min_side / max(image.shape[:2])))
        for name, dictionary in (self.dictionaries if dictionaries is None else dictionaries).items():
            corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, self.detector_params).detectMarkers(image)
            for c, marker_id in zip(corners, () if ids is None else ids.ravel()):
                if int(marker_id) in self.aruco.get(name, ()):
                    found.append((name, int(marker_id), c.reshape(4, 2)))
                elif unmapped is not None:
                    unmapped.add((name, int(marker_id)))
        return found

    def look_for_unmapped(self, gray: np.ndarray, found: int) -> None:
        """Count the markers a frame shows that the map does not hold (``unmapped``): ids of its dictionaries
        (counted by ``aruco_points``) and, every ``FOREIGN_EVERY``-th frame of a map with markers that found
        none of them (``found``), markers of the other dictionaries, at full size (far wall markers vanish
        reduced; 3-5 ms a dictionary at VGA)."""
        self._frames_without_markers = 0 if found else self._frames_without_markers + 1
        if not self._foreign or self._frames_without_markers % FOREIGN_EVERY != 1:
            return
        seen: set = set()
        self._detect(gray, self.params.aruco_min_side_px, seen, self._foreign)
        self.unmapped.update(seen)

    def diagnosis(self, min_frames: int = UNMAPPED_FRAMES) -> str:
        """What the frames showed that the map does not hold, for a failure's reason ("" when nothing was
        seen in ``min_frames`` searches or more): the dictionaries and ids of those markers."""
        seen: Dict[str, List[int]] = {}  # the map's dictionaries first: their ids are the likelier mistake
        for (name, marker_id), frames in sorted(self.unmapped.items(), key=lambda item: (item[0][0] not in self.aruco, item[0])):
            if frames >= min_frames:
                seen.setdefault(name, []).append(marker_id)
        if not seen:
            return ""
        listed = "; ".join(f"{name} ids {', '.join(map(str, ids[:8]))}{', ...' if len(ids) > 8 else ''}" for name, ids in seen.items())
        return (f"ArUco markers the map does not hold were seen ({listed}; the map's: "
                f"{', '.join(sorted(self.aruco)) or 'none'}): check its ids and dictionary (docs/landmarks.md)")

    def aruco_points(self, gray: np.ndarray, boxes: Optional[List[Box]] = None) -> _Points:
        """Map markers found in a grey image (their corners, refined on the full image).

        ``boxes``: (x0, y0, x1, y1, smallest predicted marker side, markers predicted), full-size
        pixels; each searched at the largest integer reduction f <= the frame's that keeps that side
        >= ``aruco_min_side_px``, and again at full size when that found fewer markers than predicted
        (a marker at the limit can vanish in the reduced box). Without boxes: the whole frame reduced,
        then at full size when that found too few.
        """
        frame_factor = max(1, -(-gray.shape[1] // self.params.aruco_detection_width))
        min_side = self.params.aruco_min_side_px
        found: Dict[Tuple[str, int], Tuple[np.ndarray, int]] = {}
        unmapped: set = set()

        def search(x0: int, y0: int, x1: int, y1: int, factor: int) -> None:
            roi = gray[y0:y1, x0:x1]
            if factor > 1:
                roi = cv2.resize(roi, (max(1, roi.shape[1] // factor), max(1, roi.shape[0] // factor)), interpolation=cv2.INTER_AREA)
            if min(roi.shape[:2]) < 8:
                return
            for name, marker_id, c in self._detect(roi, min_side, unmapped):
                key = (name, marker_id)
                if key not in found or found[key][1] > factor:
                    found[key] = ((c + 0.5) * factor - 0.5 + (x0, y0), factor)

        if boxes is None:
            search(0, 0, gray.shape[1], gray.shape[0], frame_factor)
            if frame_factor > 1 and len(found) < self.params.aruco_full_resolution_below:
                search(0, 0, gray.shape[1], gray.shape[0], 1)
        else:
            for x0, y0, x1, y1, side, predicted in boxes:
                factor = int(max(1, min(frame_factor, side // min_side)))
                before = len(found)
                search(x0, y0, x1, y1, factor)
                if factor > 1 and len(found) - before < predicted:
                    search(x0, y0, x1, y1, 1)
        self.unmapped.update(unmapped)
        points = _Points.empty()
        for (name, marker_id), (corners, factor) in found.items():
            corners = subpix_corners(gray, corners, factor)
            if self.params.aruco_edge_refinement:
                corners = refine_corners(gray, corners, self.dictionaries[name].markerSize + 2)
            points = points + _Points(self.aruco[name][marker_id], corners.astype(float), [marker_id] * 4, np.zeros(4, dtype=int))
        return points

    def predicted_boxes(self, camera: CameraModel, T_WC: np.ndarray) -> List[Box]:
        """Pixel boxes (x0, y0, x1, y1, smallest marker side in it), clipped to the image, around the
        projections from T_WC of the map markers in front of the camera and facing it, each padded by
        half its projected side plus ``aruco_track_margin``; overlapping boxes are merged."""
        if len(self.aruco_corners) == 0:
            return []
        quads, facing, side = self._predicted_quads(camera, T_WC)
        quads, side = quads[facing], side[facing]
        lo, hi = quads.min(axis=1), quads.max(axis=1)
        margin = self.params.aruco_track_margin
        size = np.array([camera.width, camera.height])
        near = np.all(hi >= -margin, axis=1) & np.all(lo <= size - 1 + margin, axis=1)  # in the image, or nearly
        pad = (0.5 * (hi - lo).max(axis=1) + margin)[:, None]
        lo = np.clip(np.floor(lo - pad), 0, size).astype(int)
        hi = np.clip(np.floor(hi + pad) + 1, 0, size).astype(int)
        return _merge_boxes([[*l, *h, s, 1] for l, h, s in zip(lo[near], hi[near], side[near])])

    def _predicted_quads(self, camera: CameraModel, T_WC: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every map marker's projected corners from T_WC (M x 4 x 2, ``aruco_corners`` order), whether it
        is in front of the camera and facing it, and its shortest projected side (px)."""
        uv, in_front = camera.project_world(self.aruco_corners, T_WC)
        quads = uv.reshape(-1, 4, 2)
        x, y = quads[..., 0], quads[..., 1]
        # Shoelace area (image y down): positive for a marker seen from the front in cv2.aruco's
        # corner order; a marker seen from behind is mirrored, one edge-on has none.
        facing = in_front.reshape(-1, 4).all(axis=1) & ((x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1) > 0)
        side = np.linalg.norm(quads - np.roll(quads, 1, axis=1), axis=2).min(axis=1)
        return quads, facing, side

    def tracked_points(self, gray: np.ndarray, camera: CameraModel, T_WC: np.ndarray, detected: Iterable[object],
                       rate: np.ndarray, exposure: float) -> _Points:
        """The centres (one point, one group each) of the map markers predicted in view from T_WC, facing
        the camera, at least ``track_min_side_px`` wide and not in ``detected``, tracked under the smear of
        a camera turning at ``rate`` (rad/s, optical frame) for ``exposure`` s (agent/marker_tracking.py)."""
        p = self.params
        points = _Points.empty()
        if not p.track_smear_factors or len(self.aruco_corners) == 0:
            return points
        quads, facing, side = self._predicted_quads(camera, T_WC)
        skip = set(detected)
        candidates = [i for i in np.flatnonzero(facing & (side >= p.track_min_side_px) & np.all(np.isfinite(quads), axis=(1, 2)))
                      if self._marker_keys[i][1] not in skip]
        if not candidates:
            return points
        centres = self.aruco_corners.reshape(-1, 4, 3)[candidates].mean(axis=1)
        uv, _ = camera.project_world(centres, T_WC)
        seen = np.all(np.isfinite(uv), axis=1)
        smears = np.zeros_like(uv)
        smears[seen] = exposure * rotation_flow(camera.normalized(uv[seen]), rate, (camera.K[0, 0], camera.K[1, 1]))
        for i, centre, centre_uv, smear in zip(np.array(candidates)[seen], centres[seen], uv[seen], smears[seen]):
            name, marker_id = self._marker_keys[i]
            if (name, marker_id) not in self._textures:
                self._textures[name, marker_id] = marker_texture(self.dictionaries[name], marker_id)
            found = track_marker(gray, *self._textures[name, marker_id], quads[i], smear, p.track_smear_factors,
                                 p.track_template_blur, p.aruco_track_margin)
            if found is not None and found.correlation >= p.track_min_correlation:
                points = points + _Points(centre[None], (centre_uv + found.shift)[None], [marker_id], np.zeros(1, dtype=int))
        return points

    def color_blobs(self, image_bgr: np.ndarray, camera: Optional[CameraModel] = None) -> Dict[str, np.ndarray]:
        """Ball centres (N x 2, full-size pixels) per colour class of the map, off the border (``_balls``);
        with ``camera``, each outline's centroid is moved to the projection of the ball's centre
        (``sphere_centre_pixels``)."""
        if not self.colors:
            return {}
        assert self.perception is not None
        # Half resolution: 4x fewer pixels; a half-size pixel (i, j) is centred on full-size (2i + 1/2, 2j + 1/2).
        half = cv2.resize(image_bgr, (image_bgr.shape[1] // 2, image_bgr.shape[0] // 2), interpolation=cv2.INTER_AREA)
        hsv = cv2.cvtColor(half, cv2.COLOR_BGR2HSV)
        min_area = max(1, self.perception.landmark_min_area // 4)
        out = {}
        for name in self.colors:
            color, shade = self.perception.colors[name], self.shaded[name]
            centres = []
            for (x, y, w, h), shaded in _balls(hsv, color, shade, min_area):  # largest first: the search keeps the first few
                if not _off_border((x, y, w, h), half.shape):
                    continue
                x0, y0 = max(0, 2 * x - 2), max(0, 2 * y - 2)  # the box at full size, padded by one half-size pixel
                roi = cv2.cvtColor(cv2.medianBlur(image_bgr[y0 : 2 * (y + h) + 2, x0 : 2 * (x + w) + 2], 3), cv2.COLOR_BGR2HSV)
                centre = _ball_centre(roi, color, shade, shaded)
                if centre is not None:
                    centres.append((x0 + centre[0], y0 + centre[1], centre[2]))
            found = np.array(centres, dtype=float).reshape(-1, 3)
            out[name] = found[:, :2] if camera is None else sphere_centre_pixels(camera, found[:, :2], found[:, 2])
        return out

    def associate(self, centroids: Dict[str, np.ndarray], model: PlanarModel, pose: np.ndarray, gate: float) -> _Points:
        """Blob <-> landmark pairs that are unambiguous under the projections from ``pose``."""
        points = _Points.empty()
        for name, uv in centroids.items():
            landmarks = self.colors[name]
            if len(uv) == 0:
                continue
            predicted, _ = model.project(pose, np.array([lm.position for lm in landmarks], dtype=float))
            distances = np.linalg.norm(uv[:, None, :] - predicted[None, :, :], axis=2)
            within = np.nan_to_num(distances, nan=np.inf) <= gate
            for b in range(len(uv)):
                candidates = np.flatnonzero(within[b])
                # Unambiguous: one landmark within the gate of this blob, and this blob the only one near it.
                if len(candidates) == 1 and within[:, candidates[0]].sum() == 1:
                    lm = landmarks[candidates[0]]
                    points = points + _Points(np.array([lm.position], dtype=float), uv[b : b + 1], [lm.id], np.zeros(1, dtype=int))
        return points


def subpix_corners(gray: np.ndarray, corners: np.ndarray, factor: int = 1) -> np.ndarray:
    """A marker's 4 x 2 corners refined by ``cv2.cornerSubPix`` on the full image, found on it reduced by ``factor``.

    Half-window: side / 8 (within the marker's outer black cells), at least the reduction's
    uncertainty f + 1, 2..6 px; a window reaching a neighbouring corner pulls the estimate."""
    side = float(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).min())
    half = int(min(6, max(2, side // 8, factor + 1 if factor > 1 else 0)))
    return cv2.cornerSubPix(gray, np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                            _SUBPIX_CRITERIA).reshape(4, 2)


_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
BALL_SHADE_REACH = 1.25  # a ball's shade reaches at most this many times its lit cap's enclosing radius


def _off_border(rect: Tuple[int, int, int, int], shape: Tuple[int, ...]) -> bool:
    x, y, w, h = rect
    return x > 0 and y > 0 and x + w < shape[1] and y + h < shape[0]


def _balls(hsv: np.ndarray, color: ColorClass, shade: ColorClass, min_area: int) -> List[Tuple[Tuple[int, int, int, int], bool]]:
    """Lit balls of a colour class in an HSV image, largest first: their (x, y, w, h) boxes, and
    whether their shade joined them.

    A lit ball's shaded side is its colour darkened: same hue, same saturation, a lower value, below
    the class's floor in a dim room, so the class's mask is a lit cap, often in pieces, whose
    centroid is pulled towards the light (7 px on rendered balls at a quarter of the light). Pixels in
    the class's hue and saturation down to ``ball_shade_floor`` times its value floor (``shade``;
    opened: no lone pixels) join the class's pixels they touch; a component with at least ``min_area`` of the class's
    pixels is a ball. The shade stays within the lit cap's enclosing circle, however thin the cap: a
    lit crescent's tips are where the terminator, a great circle, meets the outline, another one, so
    they are opposite ends of a diameter. A component reaching more than ``BALL_SHADE_REACH`` times
    that circle's radius (plus a pixel) holds a dark surface of the ball's colour touching it, and
    the class's pixels alone are the ball.
    """
    strict, loose = _ball_masks(hsv, color, shade)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(loose, connectivity=8)
    lit = np.bincount(labels[strict > 0], minlength=count)
    lit[0] = 0
    out = []
    for k in np.argsort(-lit, kind="stable"):
        if lit[k] < min_area:
            break
        x, y, w, h, _ = (int(v) for v in stats[k])
        ball = (labels[y : y + h, x : x + w] == k).astype(np.uint8)
        cap = ball & (strict[y : y + h, x : x + w] > 0)
        if _reach(ball) <= BALL_SHADE_REACH * _reach(cap) + 1.0:
            out.append(((x, y, w, h), True))
        else:
            x_, y_, w, h = cv2.boundingRect(cap)
            out.append(((x + x_, y + y_, w, h), False))
    return out


def _reach(mask: np.ndarray) -> float:
    """The radius of the circle enclosing a mask's pixels, px."""
    points = np.vstack(cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)[0]).reshape(-1, 2)
    return float(cv2.minEnclosingCircle(points.astype(np.float32))[1])


def _ball_masks(hsv: np.ndarray, color: ColorClass, shade: ColorClass) -> Tuple[np.ndarray, np.ndarray]:
    """The class's mask, and it with its shade (``_balls``)."""
    strict = color_mask(hsv, color)
    return strict, cv2.morphologyEx(color_mask(hsv, shade), cv2.MORPH_OPEN, _CROSS) | strict


def _outline(mask: np.ndarray) -> np.ndarray:
    return max(cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0], key=cv2.contourArea)


def _ball_centre(hsv: np.ndarray, color: ColorClass, shade: ColorClass, shaded: bool) -> Optional[Tuple[float, float, float]]:
    """The (u, v) centroid and the area (px) of the outer outline (a highlight's desaturated hole
    filled) of the largest ball in an HSV image around one, its shade joined or not (``_balls``). The image is
    median-filtered (3 x 3) first by the caller: pixel noise at a shaded side's low value swings hue
    and saturation out of the class and leaves the shade in speckles (centres 9 px off at 8 grey
    levels of noise, 0.5 px filtered), and a median moves no edge."""
    strict, loose = _ball_masks(hsv, color, shade)
    if not strict.any():
        return None
    labels = cv2.connectedComponents(loose if shaded else strict, connectivity=8)[1]
    mask = (labels == np.bincount(labels[strict > 0]).argmax()).astype(np.uint8)
    outline = _outline(mask)
    m = cv2.moments(outline)
    if m["m00"] <= 0:  # a line of pixels
        m = cv2.moments(mask, binaryImage=True)
    # the polygon through the outline's pixel centres is half a pixel short all round
    return m["m10"] / m["m00"], m["m01"] / m["m00"], m["m00"] + 0.5 * cv2.arcLength(outline, True) + 1.0


def sphere_centre_pixels(camera: CameraModel, uv: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """The projections of balls' centres (N x 2 pixels) from the centroids ``uv`` and areas (px) of
    their outlines.

    A sphere of angular radius alpha whose centre is theta off the optical axis projects to an
    ellipse centred on the radial line through the centre's projection, further out: in the
    normalized image plane, with rho = tan theta and tau = tan alpha,

        rho_e = (tan(theta + alpha) + tan(theta - alpha)) / 2 = rho (1 + tau^2) / (1 - rho^2 tau^2),
        rho = (sqrt((1 + tau^2)^2 + 4 rho_e^2 tau^2) - (1 + tau^2)) / (2 rho_e tau^2),

    and the ellipse's area is pi tau^2 / cos^3 theta (to first order in tau^2), which gives tau from
    the outline's area. A 14 cm ball 0.8 m away, 0.38 rad off the axis: 2.1 px at VGA; 3 m away, 0.15 px.
    """
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    if not len(uv):
        return uv
    rays = camera.pixels_to_rays(uv)
    n = rays[:, :2] / rays[:, 2:3]
    rho_e = np.linalg.norm(n, axis=1)
    tau2 = np.asarray(areas, dtype=float) / (camera.K[0, 0] * camera.K[1, 1]) / math.pi * (1.0 + rho_e**2) ** -1.5
    a = 1.0 + tau2
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(rho_e * tau2 > 1e-12, (np.sqrt(a * a + 4.0 * rho_e**2 * tau2) - a) / (2.0 * rho_e**2 * tau2), 1.0)
    return camera.project(np.column_stack([n * scale[:, None], np.ones(len(n))]))


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
        self.landmark_map = landmark_map
        self.perception = perception_params
        self.detector = LandmarkDetector(params, landmark_map, perception_params)
        # the floor the colour balls enclose (agent/keep_in.py): a cold hypothesis outside it is behind a wall
        self._balls = KeepIn(LandmarkMap(tuple(lm for lm in landmark_map.landmarks if lm.kind == "color")))
        self._correction: Optional[Pose] = None  # W <- scaled odometry frame
        self.scale = np.ones(3)  # (s_x, s_y, s_w) of the walk (module docstring, Odometry)
        k_s, k_w = params.odom_scale_error, params.odom_turn_scale_error
        # of (pose, scale): P_a, and the same with the intrinsics' share (module docstring)
        self._augmented = _unknown_pose(np.diag([k_s, k_s, k_w]) ** 2)
        self._augmented_total = self._augmented.copy()
        self._intrinsics_covariance = np.zeros((N_INTRINSICS, N_INTRINSICS))  # of (s_x, s_y, d_u, d_v, e): what the camera may be off by
        self._intrinsics_cross = np.zeros((6, N_INTRINSICS))  # Cov((pose, scale) error, intrinsics error)
        self.edge_shift = 0.0  # px, e: taken out of every detected marker corner (agent/self_calibration.py sets it)
        self.rejected_jumps = 0
        self._rejected: Optional[Tuple[Pose, np.ndarray]] = None  # last rejected fix's correction C_k and R_k
        self.no_fix_reason = ""
        self._roll_sigma = params.roll_sigma
        s = params.gate_floor_std
        self._floor = np.diag([s[0], s[0], s[1]]) ** 2  # F of (x, y, theta): what a fix's covariance misses (module docstring)
        self.tilt = CameraTilt(params.camera_tilt_sigma, params.camera_tilt_floor)  # the camera on its mount
        self._tilt_covariance = np.eye(2)  # the frame's prior on (delta, epsilon) (``_set_tilt_prior``)
        self._tilt_prior = np.zeros((5, 5))  # its information, pixel units
        self._reported_T_BC = np.eye(4)  # the frame's T_BC before the tilt correction
        self.landmarks_seen = 0  # map markers and landmark-coloured blobs in the last frame (for failure reasons)
        self._odom: Optional[Pose] = None  # the latest odometry reading
        self._scaled_odom: Optional[Pose] = None  # o' there
        self._stamp = -math.inf
        self._last_motion = -math.inf  # stamp of the last odometry reading that moved (a mission starts standing)
        self._last_camera: Optional[Tuple[float, np.ndarray]] = None  # (stamp, R_OC) of the last frame
        self.camera_rate: Optional[np.ndarray] = None  # rad/s, the camera's angular velocity at the last frame, its
        # optical axes (None: unknown, the first frame or one after a gap)
        self._smear = np.zeros(2)  # px, the frame's motion smear over ``exposure`` (module docstring, Smear)
        self.track: List[TrackPoint] = []  # every frame seen with a pose, for ``smoothed_track``
        self._segment = 0  # the track's unbroken stretch (``reset`` starts the next)

    @property
    def _moving(self) -> bool:
        """Odometry moved within ``still_settle`` of its latest reading."""
        return self._stamp - self._last_motion < self.params.still_settle

    def reset(self) -> None:
        """Forget the pose (after a fall or a teleport): the next fix starts afresh."""
        self._correction = None
        self._augmented = _unknown_pose(self._augmented[3:, 3:])  # the walk's scales stay what they were
        self._augmented_total = _unknown_pose(self._augmented_total[3:, 3:])
        self.rejected_jumps, self._rejected = 0, None
        self._last_camera, self.camera_rate = None, None  # the last frame's camera says nothing of the next one's rate
        self._segment += 1

    @property
    def pose(self) -> Optional[Pose]:
        """Latest (x, y, theta) in W, or None before the first fix."""
        if self._correction is None or self._odom is None:
            return None
        return compose(self._correction, self._scaled(self._odom))

    def pose_at(self, odom: Pose) -> Optional[Pose]:
        """The pose at the time the odometry read ``odom`` (e.g. a frame's capture)."""
        return None if self._correction is None else compose(self._correction, self._scaled(odom))

    @property
    def covariance(self) -> np.ndarray:
        """3 x 3 of the pose (x, y, theta): what more fixes can reduce (nan before the first fix)."""
        return self._augmented[:3, :3]

    @covariance.setter
    def covariance(self, value: np.ndarray) -> None:
        _set_pose_block(self._augmented, value)

    @property
    def total_covariance(self) -> np.ndarray:
        """3 x 3 of the pose with the intrinsics' share (module docstring): what the object filter weighs it by."""
        return self._augmented_total[:3, :3]

    @total_covariance.setter
    def total_covariance(self, value: np.ndarray) -> None:
        _set_pose_block(self._augmented_total, value)

    @property
    def scale_std(self) -> np.ndarray:
        """Std of the walk's scales (s_x, s_y, s_w)."""
        return np.sqrt(np.diag(self._augmented[3:, 3:]))

    def _scaled(self, odom: Pose) -> Pose:
        """o' at the odometry reading ``odom``: the latest o' and the scaled step from the latest reading to it."""
        odom = tuple(map(float, odom))
        if self._odom is None or self._scaled_odom is None:
            return odom
        return compose(self._scaled_odom, tuple(self.scale * np.array(relative(self._odom, odom))))

    def on_odometry(self, odom: Pose, stamp: float) -> None:
        """Carry the pose with a newer odometry reading; its covariance grows with the motion."""
        odom = _check_pose(odom, "odom")
        if not math.isfinite(stamp) or stamp < self._stamp:
            return
        if self._odom is None:
            self._odom, self._scaled_odom, self._stamp = odom, odom, stamp
            return
        d = np.array(relative(self._odom, odom))  # (dx, dy, dtheta) in the robot frame
        if np.any(np.abs(d) > self.params.still_motion):
            self._last_motion = stamp
        step = self.scale * d  # S d, the step of o'
        if self._correction is not None:
            dx, dy, dtheta = d
            heading = self.pose[2]
            c, s = math.cos(heading), math.sin(heading)
            G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
            step_W = np.array([c * dx * self.scale[0] - s * dy * self.scale[1], s * dx * self.scale[0] + c * dy * self.scale[1]])
            Phi = np.eye(6)
            Phi[:3, :3] = [[1.0, 0.0, -step_W[1]], [0.0, 1.0, step_W[0]], [0.0, 0.0, 1.0]]
            Phi[:3, 3:] = [[c * dx, -s * dy, 0.0], [s * dx, c * dy, 0.0], [0.0, 0.0, dtheta]]
            length = math.hypot(dx, dy)
            kt, kr, kd = self.params.odom_translation_noise, self.params.odom_rotation_noise, self.params.odom_scale_drift
            Q = np.zeros((6, 6))
            Q[:3, :3] = G @ np.diag([kt**2 * length, kt**2 * length, kr**2 * (length + abs(dtheta))]) @ G.T
            Q[3:, 3:] = np.eye(3) * kd**2 * (length + abs(dtheta))
            self._augmented = Phi @ self._augmented @ Phi.T + Q
            self._augmented_total = Phi @ self._augmented_total @ Phi.T + Q
            self._intrinsics_cross = Phi @ self._intrinsics_cross
        self._scaled_odom = compose(self._scaled(self._odom), tuple(step))
        self._odom, self._stamp = odom, stamp

    def position_std(self) -> float:
        """m, sqrt of the larger eigenvalue of the (x, y) covariance; inf before the first fix."""
        if self._correction is None or not np.all(np.isfinite(self.covariance)):
            return math.inf
        return float(math.sqrt(max(0.0, np.linalg.eigvalsh(self.covariance[:2, :2])[-1])))

    def on_frame(self, image: np.ndarray, T_BC: np.ndarray, odom: Pose, stamp: float) -> Optional[PoseFix]:
        """A landmark fix from a frame (fused into the pose), or None when it gave none (``no_fix_reason`` says why).

        Raises ``ImageError`` on a garbage image and ``ValueError`` on a malformed T_BC or odometry.
        """
        image = check_image(image, (self.camera.width, self.camera.height))
        T_BC = _check_transform(T_BC)
        odom = _check_pose(odom, "odom")
        self.on_odometry(odom, stamp)
        prior = self.pose_at(odom)
        R_OC = camera_rotation(odom, T_BC)
        self.camera_rate = None
        if self._last_camera is not None and 0.0 < stamp - self._last_camera[0] <= self.params.rate_max_gap:
            self.camera_rate = angular_velocity(self._last_camera[1], R_OC, stamp - self._last_camera[0])
        self._last_camera = (stamp, R_OC)
        fix = self.measure(image, T_BC, prior, self.params.roll_sigma if self._moving else self.params.roll_sigma_still,
                           np.zeros(3) if self.camera_rate is None else self.camera_rate, self.covariance)
        if fix is not None and prior is not None and not self._accept_jump(prior, fix, odom):
            self.no_fix_reason = f"jump of {math.hypot(fix.pose[0] - prior[0], fix.pose[1] - prior[1]):.2f} m from the prior rejected"
            fix = None
        if fix is not None:
            self._fuse(fix, prior, odom)
            if not self._moving:  # the sway is out of the fit: its tilt is the mount's
                frame = np.diag([self.params.roll_sigma_still, self.params.pitch_sigma]) ** 2
                self.tilt.update(self.tilt.correct(T_BC), fix.tilt_information, fix.tilt_evidence, frame)
        pose = self.pose_at(odom)
        if pose is not None:
            factor = fix is not None and not fix.conditioned  # a conditioned fix holds the prior's information too
            self.track.append(TrackPoint(stamp, odom, pose, self._segment, fix.pose if factor else None,
                                         fix.covariance + self._floor if factor else None))
        return fix

    def smoothed_track(self) -> np.ndarray:
        """The poses of ``track``'s frames smoothed over every fix and the odometry between them (N x 3,
        agent/pose_smoother.py), with the walk's scales as estimated now."""
        p = self.params
        return smooth_track(self.track, self.scale, p.odom_translation_noise, p.odom_rotation_noise)

    def heading_rate(self) -> Optional[float]:
        """rad/s: how fast the camera turned about the vertical at the last frame (``camera_rate`` in the
        odometry frame), None when unknown."""
        if self.camera_rate is None or self._last_camera is None:
            return None
        return abs(float((self._last_camera[1] @ self.camera_rate)[2]))

    def measure(self, image: np.ndarray, T_BC: np.ndarray, prior: Optional[Pose] = None,
                roll_sigma: Optional[float] = None, camera_rate: Sequence[float] = (0.0, 0.0, 0.0),
                prior_covariance: Optional[np.ndarray] = None) -> Optional[PoseFix]:
        """The pose fix of one frame on its own (no jump gate, no fusion), or None (``no_fix_reason`` says why).

        ``roll_sigma``: prior std of the torso roll T_BC misses (default ``params.roll_sigma``, walking);
        ``camera_rate``: the camera's angular velocity at capture in its own (optical) frame, rad/s (Smear);
        ValueError when it is not three finite numbers. ``prior_covariance`` (3 x 3, of ``prior``): a frame
        too imprecise alone gives a conditioned fix (module docstring); ignored unless finite and positive.
        """
        self.no_fix_reason = ""
        self.landmarks_seen = 0
        self._roll_sigma = self.params.roll_sigma if roll_sigma is None else float(roll_sigma)
        rate = _check_rate(camera_rate)
        self._smear = self._smear_of(rate)
        try:
            return self._measure(image, _check_transform(T_BC), prior, _positive_covariance(prior_covariance), rate)
        except NoFix as reason:
            self.no_fix_reason = str(reason)
            return None

    def _model(self, T_BC: np.ndarray) -> PlanarModel:
        """The planar model of a frame with T_BC, with the map's error (module docstring, Map error)."""
        m = self.landmark_map
        return PlanarModel(self.camera, T_BC, (m.position_sigma, m.yaw_sigma, self.params.pixel_sigma))

    def _smear_of(self, rate: np.ndarray) -> np.ndarray:
        """px, the smear at the principal point over ``exposure`` of a camera turning at ``rate`` (checked)
        (module docstring, Smear)."""
        return self.params.exposure * rotation_flow(np.zeros((1, 2)), rate, (self.camera.K[0, 0], self.camera.K[1, 1]))[0]

    def _frame_tilt_covariance(self, T_BC: np.ndarray, roll_sigma: float) -> np.ndarray:
        """Prior covariance of (delta, epsilon) at the corrected T_BC: the torso's and the tilt estimate's."""
        return np.diag([roll_sigma, self.params.pitch_sigma]) ** 2 + self.tilt.body_covariance(T_BC)

    def _sway_covariance(self, roll_sigma: float) -> np.ndarray:
        """Prior covariance of the torso's own sway in (delta, epsilon) (module docstring, Pivot)."""
        return np.diag([roll_sigma, self.params.pitch_sigma * min(1.0, roll_sigma / self.params.roll_sigma)]) ** 2

    def _set_tilt_prior(self, T_BC: np.ndarray, roll_sigma: float) -> np.ndarray:
        """The frame's T_BC corrected by the learnt camera tilt; sets the fit's prior on (delta, epsilon):
        the frame's torso roll and pitch and the tilt estimate's uncertainty (agent/camera_tilt.py)."""
        self._reported_T_BC = T_BC
        T_BC = self.tilt.correct(T_BC)
        self._tilt_covariance = self._frame_tilt_covariance(T_BC, roll_sigma)
        self._tilt_prior = tilt_information(self.params.pixel_sigma, self._tilt_covariance)
        return T_BC

    def _measure(self, image: np.ndarray, T_BC: np.ndarray, prior: Optional[Pose], prior_covariance: Optional[np.ndarray],
                 rate: np.ndarray) -> PoseFix:
        T_BC = self._set_tilt_prior(T_BC, self._roll_sigma)
        model = self._model(T_BC)
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        prior_p = None
        if prior is not None and all(math.isfinite(v) for v in prior):
            prior_p = np.array([*prior, 0.0])
        markers = None
        if prior_p is not None:
            T_WC = camera_in_world(prior, T_BC)
            markers = self.detector.aruco_points(gray, self.detector.predicted_boxes(self.camera, T_WC))
        if markers is None or len(markers) < self.params.min_points:  # no prior, or it predicted the markers wrong
            markers = self.detector.aruco_points(gray)
        self.detector.look_for_unmapped(gray, len(markers))
        if self.edge_shift:  # the edges' shift taken out of the detected corners (agent/marker_corners.py)
            markers = _Points(markers.X, markers.u - self.edge_shift * edge_shift_jacobian(markers.u, markers.group),
                              markers.ids, markers.group)
        tracked = _Points.empty()
        if prior_p is not None:  # the markers the smear hid from the detector
            tracked = self.detector.tracked_points(gray, self.camera, T_WC, markers.ids, rate, self.params.exposure)
            markers = markers + tracked
        markers = _Points(markers.X, model.camera.undistort(markers.u), markers.ids, markers.group)
        return self._solve(model, markers, lambda: self.detector.color_blobs(image, self.camera), prior_p, prior_covariance,
                           tracked.landmark_ids)

    def fit(self, world_points: np.ndarray, pixels: np.ndarray, T_BC: np.ndarray, prior: Optional[Pose] = None,
            groups: Optional[np.ndarray] = None, roll_sigma: Optional[float] = None,
            prior_covariance: Optional[np.ndarray] = None, camera_rate: Sequence[float] = (0.0, 0.0, 0.0)) -> Optional[PoseFix]:
        """The fix from given correspondences (N x 3 world, N x 2 pixels; ``groups``: marker of each
        point, default four points per marker; ``roll_sigma``, ``prior_covariance`` and ``camera_rate`` as
        for ``measure``), or None (``no_fix_reason`` says why). For tests and tools."""
        self.no_fix_reason = ""
        self._roll_sigma = self.params.roll_sigma if roll_sigma is None else float(roll_sigma)
        self._smear = self._smear_of(_check_rate(camera_rate))
        try:
            model = self._model(self._set_tilt_prior(_check_transform(T_BC), self._roll_sigma))
            X = np.asarray(world_points, dtype=float).reshape(-1, 3)
            u = np.asarray(pixels, dtype=float).reshape(-1, 2)
            group = np.arange(len(X)) // 4 if groups is None else np.asarray(groups, dtype=int).reshape(-1)
            if len(u) != len(X) or len(group) != len(X):
                raise ValueError(f"{len(X)} world points, {len(u)} pixels and {len(group)} groups do not match")
            finite = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(u), axis=1)
            points = _Points(X[finite], model.camera.undistort(u[finite]), list(group[finite]), group[finite])
            prior_p = None if prior is None or not all(math.isfinite(v) for v in prior) else np.array([*prior, 0.0])
            return self._solve(model, points, dict, prior_p, _positive_covariance(prior_covariance))
        except NoFix as reason:
            self.no_fix_reason = str(reason)
            return None

    def _solve(self, model: PlanarModel, markers: _Points, colour_blobs: Callable[[], Dict[str, np.ndarray]],
               prior_p: Optional[np.ndarray], prior_covariance: Optional[np.ndarray] = None,
               tracked_ids: Tuple[object, ...] = ()) -> PoseFix:
        """Markers fitted jointly, colour blobs added (or searched) when they are few (module docstring);
        ``prior_covariance`` (of ``prior_p``'s pose, checked) turns a fix too imprecise alone into a conditioned one;
        ``tracked_ids``: the markers among them tracked from the prior (agent/marker_tracking.py)."""
        self.landmarks_seen = len(np.unique(markers.group))
        reasons = []
        fit = None
        seeds: List[np.ndarray] = []  # poses to associate colour blobs from
        if len(markers):
            try:
                fit = self._fit_markers(model, markers, prior_p)
                seeds = [fit[1]]
            except _Ambiguous as ambiguous:
                reasons.append(f"markers: {ambiguous}")
                seeds = ambiguous.poses
            except NoFix as reason:
                reasons.append(f"markers: {reason}")
        if (fit is None or len(fit[0]) < self.params.color_below_aruco_points) and self.detector.colors:
            centroids = {k: model.camera.undistort(v) for k, v in colour_blobs().items()}
            n_blobs = sum(len(v) for v in centroids.values())
            self.landmarks_seen += n_blobs
            try:
                fit = self._fit_with_colours(model, markers if fit is None else fit[0], seeds, centroids, prior_p)
            except NoFix as reason:
                reasons.append(f"colour markers ({n_blobs} blobs): {reason}")
        if fit is None:
            if not len(markers) and not reasons:
                raise NoFix("none of the map's landmarks in view")
            raise NoFix("; ".join(reasons))
        points, p, rms, H = fit
        if not rms <= self.params.max_reprojection_px:  # a NaN fails too
            raise NoFix(f"reprojection RMS {rms:.2f} px above {self.params.max_reprojection_px} px")
        tilt_std = np.sqrt(np.diag(self._tilt_covariance))
        if abs(p[4]) > self.params.max_roll_sigmas * tilt_std[1]:
            raise NoFix(f"the fit needs the camera pitched {math.degrees(p[4]):+.1f} deg off T_BC's (more than "
                        f"{self.params.max_roll_sigmas:g} sigma): the kinematics or the correspondences are wrong")
        # per-axis residual variance: sum ||r_i||^2 = N rms^2 over 2N residuals, 3 degrees of freedom used
        tracked = sum(i in tracked_ids for i in points.landmark_ids)
        floor = self.params.track_pixel_sigma if tracked else self.params.pixel_sigma
        residual_var = max(floor**2, len(points) * rms**2 / max(1, 2 * len(points) - 3))
        information, evidence = _tilt_evidence(H - self._tilt_prior, self._tilt_prior, p, residual_var)
        tilt_covariance, sway_covariance = self._tilt_covariance, self._sway_covariance(self._roll_sigma)
        if abs(p[3]) > self.params.max_roll_sigmas * max(self.params.roll_sigma, tilt_std[0]):  # the roll prior was wrong: widen it to |delta|
            widening = np.diag([p[3] ** 2 - tilt_covariance[0, 0], 0.0])
            tilt_covariance, sway_covariance = tilt_covariance + widening, sway_covariance + widening
            H = H - self._tilt_prior + tilt_information(self.params.pixel_sigma, tilt_covariance)
        G, share_covariance = head_pivot(p, float(model.T_BC[2, 3]), tilt_covariance, sway_covariance)
        covariance, Jr, Jc = self._fix_covariance(model, points, p, H, G, share_covariance, residual_var)
        std = math.sqrt(np.linalg.eigvalsh(covariance[:2, :2])[-1])
        limit = self.params.max_position_std if prior_p is None else self.params.max_position_std_with_prior
        conditioned = std > limit
        if conditioned:
            if prior_p is None or prior_covariance is None:
                raise NoFix(f"fix too imprecise: position std {std * 100:.1f} cm above {limit * 100:.1f} cm "
                            f"({len(points.landmark_ids)} landmarks, far or bunched)")
            p, rms, H = self._conditioned_fit(model, points, prior_p, prior_covariance, G, tilt_covariance, std)
            G, share_covariance = head_pivot(p, float(model.T_BC[2, 3]), tilt_covariance, sway_covariance)
            covariance, Jr, Jc = self._fix_covariance(model, points, p, H, G, share_covariance, residual_var)
            information, evidence = np.zeros((2, 2)), np.zeros(2)  # the prior's information is not the data's
        T_WC = camera_in_world(tuple(p[:3]), rot_x(p[3]) @ rot_y(p[4]) @ model.T_BC)
        x, y, theta = G @ p
        pose = (float(x), float(y), wrap_angle(float(theta)))
        gain = -G @ np.linalg.solve(H, Jr.T @ Jc)
        return PoseFix(pose=pose, covariance=covariance, rms_px=rms, landmark_ids=points.landmark_ids,
                       points=len(points), T_WC=T_WC, roll=float(p[3]), inliers=(points.X, points.u),
                       inlier_groups=points.group, edge_shift=self.edge_shift, T_BC=model.T_BC, T_BC_reported=self._reported_T_BC,
                       roll_sigma=self._roll_sigma, tilt_information=information, tilt_evidence=evidence,
                       intrinsics_gain=gain, conditioned=conditioned, tracked=tracked)

    def _conditioned_fit(self, model: PlanarModel, points: _Points, prior_p: np.ndarray, prior_covariance: np.ndarray,
                         G: np.ndarray, tilt_covariance: np.ndarray, std: float) -> Tuple[np.ndarray, float, np.ndarray]:
        """(p, rms, H) of the frame's points fitted with the pose prior N(prior_p, prior_covariance) in the
        cost, the pose G p (module docstring, Conditioned fixes); NoFix when they disagree with the prior
        (NIS, reprojection gates). ``std``: the fix alone's, for the reason."""
        prior_information = (G.T @ (self.params.pixel_sigma**2 * np.linalg.inv(prior_covariance)) @ G
                             + tilt_information(self.params.pixel_sigma, tilt_covariance))
        mean = np.array([*prior_p[:3], 0.0, 0.0])
        p, rms, err, H = model.refine(prior_p, points.X, points.u, prior_information, mean=mean, group=points.group)
        offset = _from_mean(p, mean)
        nis = float(np.sum(err**2) + offset @ prior_information @ offset) / self.params.pixel_sigma**2
        if not (nis <= chdtri(2 * len(points), 1.0 - self.params.conditioned_confidence) and rms <= self.params.max_reprojection_px
                and np.all(_group_max(err, points.group) <= self.params.ransac_reprojection_px)):
            raise NoFix(f"fix too imprecise alone (position std {std * 100:.1f} cm), and its points disagree with the "
                        f"prior (NIS {nis:.1f}, reprojection RMS {rms:.2f} px)")
        return p, rms, H

    def _fix_covariance(self, model: PlanarModel, points: _Points, p: np.ndarray, H: np.ndarray, G: np.ndarray,
                        share_covariance: np.ndarray, residual_var: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the pose's 3 x 3 covariance, the residual Jacobian 2N x 5, d residuals / d intrinsics 2N x 4) of a
        fit p with normal matrix H, pivoted by G (module docstring: R_fix, Pivot, Smear), the Jacobians
        whitened by the map's error as the fit was (one whitening for all three)."""
        uv, _, J = model.jacobian(p, points.X)
        whiten = model.whitener(p, points.X, points.group)
        Jr = whiten(J.reshape(-1, 5))
        covariance = G @ (residual_var * np.linalg.inv(H) + self._smear_covariance(points, Jr, H, whiten)) @ G.T + share_covariance
        if not np.all(np.isfinite(covariance)) or np.any(np.diag(covariance) <= 0):
            raise NoFix("fix covariance not positive")
        return covariance, Jr, whiten(model.intrinsics_jacobian(uv, points.group).reshape(-1, N_INTRINSICS))

    def _smear_covariance(self, points: _Points, Jr: np.ndarray, H: np.ndarray,
                          whiten: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """The share of (x, y, theta, delta, epsilon)'s covariance from the markers' widths along the smear
        (module docstring, Smear): sum over markers of g_m g_m^T (sigma_w |s|)^2, with the fit's residual
        Jacobian ``Jr`` (2N x 5), normal matrix ``H`` and whitening (``PlanarModel.whitener``)."""
        length = float(np.linalg.norm(self._smear))
        if length * self.params.smear_width_sigma == 0.0:
            return np.zeros((5, 5))
        direction = self._smear / length
        stretches = []  # d u / d w_m of each marker: stretched by w_m px along the smear about its centroid
        for group in np.unique(points.group):
            mine = points.group == group
            if mine.sum() < 4:  # a colour blob: its centroid stays mid-smear
                continue
            along = (points.u[mine] - points.u[mine].mean(axis=0)) @ direction
            extent = float(along.max() - along.min())
            if extent > 0.0:
                stretch = np.zeros((len(points), 2))
                stretch[mine] = np.outer(along / extent, direction)
                stretches.append(stretch.ravel())
        if not stretches:
            return np.zeros((5, 5))
        gains = np.linalg.solve(H, Jr.T @ whiten(np.column_stack(stretches)))
        return (self.params.smear_width_sigma * length) ** 2 * gains @ gains.T

    # -- markers -------------------------------------------------------------------------------

    def _refine(self, model: PlanarModel, points: _Points, seed: Sequence[float]):
        return model.refine(seed, points.X, points.u, self._tilt_prior, group=points.group)

    def _fit_markers(self, model: PlanarModel, markers: _Points, prior: Optional[np.ndarray]):
        """(inlier points, p, rms, H): the joint fit of all markers, or the largest consensus (module docstring)."""
        groups = np.unique(markers.group)
        if len(groups) == 1:
            return self._single_marker(model, markers, prior)
        gate = self.params.ransac_reprojection_px
        for seed in self._joint_seeds(model, markers, prior):  # the first that every marker agrees with
            try:
                p, rms, err, H = self._refine(model, markers, seed)
            except NoFix:
                continue
            if np.all(_group_max(err, markers.group) <= gate) and rms <= self.params.max_reprojection_px:
                return markers, p, rms, H
        best: Optional[np.ndarray] = None
        for g in groups:  # one-marker hypotheses, scored by the markers they predict
            one = markers.take(markers.group == g)
            try:
                p, _, _, _ = self._refine(model, one, model.linear_seed(one.X, one.u)[0])
            except NoFix:
                continue
            uv, _ = model.project(p, markers.X)
            err = np.nan_to_num(np.linalg.norm(uv - markers.u, axis=1), nan=np.inf)
            inliers = np.isin(markers.group, groups[_group_max(err, markers.group) <= self.params.hypothesis_gate_px])
            if best is None or inliers.sum() > best.sum():
                best = inliers
        if best is None:
            raise NoFix(f"no marker of {len(groups)} gives a planar pose")
        consensus = markers.take(best)
        p, rms, err, H = self._refine(model, consensus, model.linear_seed(consensus.X, consensus.u)[0])
        keep = np.isin(consensus.group, np.unique(consensus.group)[_group_max(err, consensus.group) <= gate])
        if not keep.any():
            raise NoFix("no marker agrees with the joint fit")
        if not keep.all():
            consensus = consensus.take(keep)
            if len(np.unique(consensus.group)) == 1:
                return self._single_marker(model, consensus, prior)
            p, rms, err, H = self._refine(model, consensus, p)
        return consensus, p, rms, H

    def _joint_seeds(self, model: PlanarModel, points: _Points, prior: Optional[np.ndarray]) -> Iterator[np.ndarray]:
        """Starting poses of a joint fit, in order: the planar part of the 6-DOF PnP of all points
        (SQPnP: free of T_BC's pitch and roll errors, which throw the linear solve metres off with
        far markers, into a wrong minimum), the prior, the linear solve."""
        try:
            ok, rvec, tvec = cv2.solvePnP(points.X, points.u, self.camera.K, None, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                yield from _planar_seeds(model, [rvec], [tvec])
        except cv2.error:
            pass
        if prior is not None:
            yield prior[:3]
        try:
            yield model.linear_seed(points.X, points.u)[0]
        except NoFix:
            pass

    def _single_marker(self, model: PlanarModel, marker: _Points, prior: Optional[np.ndarray]):
        """Both planar solutions of one marker (linear seed and IPPE's two), told apart or no fix."""
        seeds = [model.linear_seed(marker.X, marker.u)[0]]
        seeds += self._ippe_seeds(model, marker)
        solutions: List[Tuple[np.ndarray, float, np.ndarray]] = []
        for seed in seeds:
            try:
                p, rms, _, H = self._refine(model, marker, seed)
            except NoFix:
                continue
            if all(math.hypot(*(p[:2] - q[:2])) > 1e-3 or abs(wrap_angle(p[2] - q[2])) > 1e-3 for q, _, _ in solutions):
                solutions.append((p, rms, H))
        if not solutions:
            raise NoFix("one marker: no planar solution")
        solutions.sort(key=lambda s: s[1])
        passing = [s for s in solutions if s[1] <= self.params.max_reprojection_px]
        # A rival is a different pose whose squared residuals exceed the best one's by less than
        # ``solution_evidence`` pixel variances (a likelihood ratio the corners cannot settle).
        n = 2 * len(marker)
        variance = max(self.params.pixel_sigma**2, n * passing[0][1] ** 2 / max(1, n - 3)) if passing else 1.0
        distinct = [s for s in passing[1:] if math.hypot(*(s[0][:2] - passing[0][0][:2])) > self.params.ambiguity_distance
                    and n * (s[1] ** 2 - passing[0][1] ** 2) < self.params.solution_evidence * variance]
        if passing and distinct:
            if prior is None:
                raise _Ambiguous("one marker: two planar solutions explain it and there is no prior to choose",
                                 marker, [s[0] for s in passing])
            P = self.covariance if np.all(np.isfinite(self.covariance)) else np.eye(3)
            scores = sorted((_mahalanobis(s[0], prior, P + self.params.pixel_sigma**2 * np.linalg.inv(s[2])[:3, :3]), k)
                            for k, s in enumerate(passing))
            if scores[1][0] < 4.0 * scores[0][0] + 9.0:  # the runner-up is not 3 sigma (and 2x) further from the prior
                raise _Ambiguous("one marker: the prior does not tell its two planar solutions apart", marker,
                                 [s[0] for s in passing])
            chosen = passing[scores[0][1]]
        else:
            chosen = solutions[0]
        return marker, chosen[0], chosen[1], chosen[2]

    def _ippe_seeds(self, model: PlanarModel, marker: _Points) -> List[np.ndarray]:
        """Planar poses of IPPE's two solutions for one marker."""
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(marker.X, marker.u, self.camera.K, None, flags=cv2.SOLVEPNP_IPPE)
        except cv2.error:
            return []
        return _planar_seeds(model, rvecs[:n], tvecs[:n])

    # -- colour markers ------------------------------------------------------------------------

    def _fit_with_colours(self, model: PlanarModel, markers: _Points, seeds: List[np.ndarray],
                          centroids: Dict[str, np.ndarray], prior: Optional[np.ndarray]):
        """Blobs associated from the markers' pose(s) or the prior, else found by the hypothesis search.

        With several marker poses (one marker's two solutions), the one whose associated blobs fit
        with the most points wins; a tie is no fix.
        """
        fits = []
        for pose in seeds:
            try:
                fits.append(self._joint(model, markers + self.detector.associate(centroids, model, pose, self.params.color_gate), pose))
            except NoFix:
                continue
        fits = [f for f in fits if f[2] <= self.params.max_reprojection_px]
        if len(seeds) > 1:
            fits.sort(key=lambda f: -len(f[0]))
            if len(fits) > 1 and len(fits[1][0]) == len(fits[0][0]):
                raise NoFix("one marker's two planar solutions both fit the blobs")
            if fits and len(fits[0][0]) > len(markers):
                return fits[0]
        elif fits:
            return fits[0]
        if prior is not None:
            points = markers + self.detector.associate(centroids, model, prior, self.params.color_gate)
            if len(points) >= self.params.min_points_with_prior:
                try:
                    return self._joint(model, points, prior, self.params.min_points_with_prior)
                except NoFix:
                    pass
        if len(markers) + sum(len(v) for v in centroids.values()) < self.params.min_points:
            raise NoFix(f"{sum(len(v) for v in centroids.values())} blobs and {len(markers)} marker corners: "
                        f"fewer than {self.params.min_points} points" + (" (none associated by the prior)" if prior is not None else ""))
        return self._colour_search(model, markers, centroids)

    def _joint(self, model: PlanarModel, points: _Points, seed: Sequence[float], min_points: Optional[int] = None):
        min_points = self.params.min_points if min_points is None else min_points
        if len(points) < min_points:
            raise NoFix(f"{len(points)} points, fewer than {min_points}")
        p, rms, err, H = self._refine(model, points, seed)
        if not np.all(_group_max(err, points.group) <= self.params.ransac_reprojection_px):
            raise NoFix("points disagree with the joint fit")
        return points, p, rms, H

    def _colour_search(self, model: PlanarModel, markers: _Points, centroids: Dict[str, np.ndarray]):
        """Cold start: two-blob and three-blob hypotheses over colour-consistent landmarks (module docstring)."""
        # at most max_search_blobs blobs, the largest of each colour first, round-robin over colours
        ranked = sorted(((k, name, uv) for name, uvs in centroids.items() for k, uv in enumerate(uvs)), key=lambda t: t[0])
        ranked = ranked[: self.params.max_search_blobs]
        blobs_uv = np.array([uv for _, _, uv in ranked], dtype=float).reshape(-1, 2)
        blob_colour = [name for _, name, _ in ranked]
        if len(blobs_uv) + len(markers) < self.params.min_points:
            raise NoFix(f"{len(blobs_uv)} blobs and {len(markers)} marker corners: fewer than {self.params.min_points} points")
        lms = self.detector.color_landmarks
        L = np.array([lm.position for lm in lms], dtype=float)
        colour_of = np.array([lm.color for lm in lms])
        same = np.array([[colour_of[j] == blob_colour[b] for j in range(len(lms))] for b in range(len(blobs_uv))]).reshape(len(blobs_uv), len(lms))
        poses = []
        for k, solve, searched in ((2, self._pair_poses, len(blobs_uv)), (3, _triple_poses, self.params.max_triple_blobs)):
            found, X = self._hypotheses(model, blobs_uv[:searched], same, L, k, solve)
            poses.append(found[self._plausible(model, found, X)])
        poses = np.concatenate(poses)
        if len(poses) == 0:
            raise NoFix("no pair or triple of blobs gives a plausible planar pose")
        scores = self._consensus(model, poses, blobs_uv, same, L, markers)
        top = scores.max()
        if top < self.params.min_points:
            raise NoFix(f"best hypothesis explains {int(top)} points, fewer than {self.params.min_points}")
        fits = []
        for pose in _distinct(poses[scores >= top - 1], scores[scores >= top - 1], self.params.ambiguity_distance):
            try:
                fits.append(self._associated_fit(model, markers, centroids, np.array([*pose, 0.0])))
            except NoFix:
                continue
        fits = [f for f in fits if f[2] <= self.params.max_reprojection_px]
        if not fits:
            raise NoFix("no hypothesis survives refinement")
        # the most points, then the least cost: squared residuals plus the tilt prior's (a wrong triple of
        # balls at one height fits its bearings exactly and its rows only with the camera tilted)
        cost = [len(f[0]) * f[2] ** 2 + f[1] @ self._tilt_prior @ f[1] for f in fits]
        order = sorted(range(len(fits)), key=lambda k: (-len(fits[k][0]), cost[k]))
        best = fits[order[0]]
        n = 2 * len(best[0])
        variance = max(self.params.pixel_sigma**2, n * best[2] ** 2 / max(1, n - 3))
        rivals = [k for k in order[1:] if len(fits[k][0]) >= len(best[0])
                  and math.hypot(*(fits[k][1][:2] - best[1][:2])) > self.params.ambiguity_distance
                  and cost[k] - cost[order[0]] < self.params.solution_evidence * variance]
        if rivals:
            raise NoFix("two distinct poses explain the blobs equally well (symmetric layout from here)")
        return best

    @staticmethod
    def _hypotheses(model: PlanarModel, blobs_uv: np.ndarray, same: np.ndarray, L: np.ndarray, k: int,
                    solve: Callable[[PlanarModel, np.ndarray, np.ndarray], Tuple[np.ndarray, np.ndarray]]
                    ) -> Tuple[np.ndarray, np.ndarray]:
        """(poses H x 3, their landmarks H x k x 3) ``solve`` gives for every k blobs matched to k distinct
        landmarks of their colours."""
        marks, chosen = [], []
        for blobs_k in itertools.combinations(range(len(blobs_uv)), k):
            grid = np.stack(np.meshgrid(*(np.flatnonzero(same[b]) for b in blobs_k), indexing="ij"), axis=-1).reshape(-1, k)
            ordered = np.sort(grid, axis=1)
            grid = grid[np.all(ordered[:, 1:] != ordered[:, :-1], axis=1)]  # k distinct landmarks
            marks.append(grid)
            chosen.append(np.broadcast_to(blobs_k, grid.shape))
        marks_all = np.concatenate(marks) if marks else np.zeros((0, k), dtype=int)
        if len(marks_all) == 0:
            return np.zeros((0, 3)), np.zeros((0, k, 3))
        return solve(model, L[marks_all], blobs_uv[np.concatenate(chosen)])

    def _associated_fit(self, model: PlanarModel, markers: _Points, centroids: Dict[str, np.ndarray], pose: np.ndarray):
        """Associate from ``pose``, refine, associate again from the refined pose, refine and gate."""
        for _ in range(2):
            points = markers + self.detector.associate(centroids, model, pose, self.params.color_gate)
            if len(points) < self.params.min_points:
                raise NoFix("the hypothesis lost its blobs on refinement")
            pose, _, _, _ = self._refine(model, points, pose)
        return self._joint(model, points, pose)

    def _pair_poses(self, model: PlanarModel, X: np.ndarray, u: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """(x, y, theta) of every two-point hypothesis (H x 2 x 3, H x 2 x 2) passing the scale check, and its points."""
        n = (u - model.c) / model.f
        H = len(X)
        rows, rhs = _linear_rows(X.reshape(-1, 3), n.reshape(-1, 2), model.R_CB, model.t_CB)
        # rows are (x equations of all points; y equations of all points): regroup per hypothesis
        rows = np.concatenate([rows[: 2 * H].reshape(H, 2, 4), rows[2 * H :].reshape(H, 2, 4)], axis=1)
        rhs = np.concatenate([rhs[: 2 * H].reshape(H, 2), rhs[2 * H :].reshape(H, 2)], axis=1)
        ok = np.abs(np.linalg.det(rows)) > 1e-12
        v = np.full((H, 4), np.nan)
        v[ok] = np.linalg.solve(rows[ok], rhs[ok][..., None])[..., 0]
        norm = np.hypot(v[:, 0], v[:, 1])
        keep = np.isfinite(norm) & (np.abs(norm - 1.0) <= self.params.pair_scale_tolerance)
        return _pose_of(v[keep]).reshape(-1, 3), X[keep]

    def _plausible(self, model: PlanarModel, poses: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Mask of the hypotheses (poses H x 3, their landmarks H x k x 3) with the robot inside the floor the
        balls enclose (by ``max_outside_balls``) and every landmark in front within ``max_range``."""
        X_C = model.to_cameras(poses, X)
        inside = np.all(self._balls.distances(poses[:, :2]) >= -self.params.max_outside_balls, axis=-1)
        seen = np.all((X_C[..., 2] > MIN_DEPTH) & (np.linalg.norm(X_C, axis=-1) < self.params.max_range), axis=1)
        return inside & seen

    def _consensus(self, model: PlanarModel, poses: np.ndarray, blobs_uv: np.ndarray, same: np.ndarray,
                   L: np.ndarray, markers: _Points, chunk: int = 2048) -> np.ndarray:
        """Per pose: blobs whose nearest landmark of their colour is predicted within the gate (each landmark
        claimed once), plus marker corners that fit."""
        scores = np.zeros(len(poses))
        for start in range(0, len(poses), chunk):
            part = poses[start : start + chunk]
            uv = _pixels(model, model.to_cameras(part, L))
            d = np.linalg.norm(blobs_uv[None, :, None, :] - uv[:, None, :, :], axis=3)
            d = np.where(same[None] & np.isfinite(d), d, np.inf)
            nearest = np.argmin(d, axis=2)
            claimed = np.where(np.take_along_axis(d, nearest[..., None], axis=2)[..., 0] <= self.params.color_gate, nearest, -1)
            claimed.sort(axis=1)  # distinct landmarks claimed: each counts once
            distinct = (claimed >= 0) & np.concatenate([np.ones((len(part), 1), bool), claimed[:, 1:] != claimed[:, :-1]], axis=1)
            scores[start : start + chunk] = distinct.sum(axis=1)
            if len(markers):
                error = np.linalg.norm(_pixels(model, model.to_cameras(part, markers.X)) - markers.u, axis=2)
                scores[start : start + chunk] += np.sum(np.nan_to_num(error, nan=np.inf) <= self.params.color_gate, axis=1)
        return scores

    # -- prediction ----------------------------------------------------------------------------

    def predicted_fix(self, pose: Pose, T_BC: np.ndarray) -> Tuple[int, Optional[np.ndarray]]:
        """(points, covariance of (x, y, theta) or None): what a frame from ``pose`` would give (module docstring)."""
        T_BC = self.tilt.correct(T_BC)
        model = self._model(T_BC)
        p = np.array([*pose, 0.0, 0.0])
        X, group, _ = self._visible_points(model, p)
        if len(X) < self.params.min_points:
            return len(X), None
        _, _, J = model.jacobian(p, X)
        try:
            Jr = model.whitener(p, X, group)(J.reshape(-1, 5))
        except NoFix:
            return len(X), None
        tilt_covariance = self._frame_tilt_covariance(T_BC, self.params.roll_sigma)
        H = Jr.T @ Jr + tilt_information(self.params.pixel_sigma, tilt_covariance)
        if np.linalg.cond(H) > 1e10:
            return len(X), None
        G, share_covariance = head_pivot(p, float(T_BC[2, 3]), tilt_covariance, self._sway_covariance(self.params.roll_sigma))
        return len(X), G @ (self.params.pixel_sigma**2 * np.linalg.inv(H)) @ G.T + share_covariance

    def visible_landmarks(self, pose: Pose, T_BC: np.ndarray) -> Tuple[int, int]:
        """(points, landmarks) a frame from ``pose`` would show, by the prediction's rules (module docstring)."""
        X, _, landmarks = self._visible_points(PlanarModel(self.camera, self.tilt.correct(T_BC)), np.array([*pose, 0.0, 0.0]))
        return len(X), landmarks

    def _visible_points(self, model: PlanarModel, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray, int]:
        """(world points, the landmark of each (an index), landmarks) predicted in view from the planar pose ``p``."""
        margin = self.params.view_margin_px
        size = np.array([self.camera.width, self.camera.height])
        chosen, groups = [], []
        landmarks = 0
        corners = self.detector.aruco_corners
        if len(corners):
            uv, z = model.project(p, corners)
            quads, depth = uv.reshape(-1, 4, 2), z.reshape(-1, 4)
            x, y = quads[..., 0], quads[..., 1]
            facing = (x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y).sum(axis=1) > 0
            seen_at = self.camera.distort(uv).reshape(-1, 4, 2)  # where the lens shows them (NaN: not at all)
            inside = np.all((seen_at >= margin) & (seen_at <= size - 1 - margin), axis=(1, 2)) & np.all(depth > MIN_DEPTH, axis=1)
            side = np.linalg.norm(quads - np.roll(quads, 1, axis=1), axis=2).min(axis=1)
            ok = facing & inside & (np.nan_to_num(side) >= self.params.aruco_min_side_px)
            chosen.append(corners.reshape(-1, 4, 3)[ok].reshape(-1, 3))
            groups.append(np.repeat(np.arange(int(ok.sum())), 4))
            landmarks += int(ok.sum())
        if self.detector.color_landmarks and self.perception is not None:
            L = np.array([lm.position for lm in self.detector.color_landmarks], dtype=float)
            diameters = np.array([lm.diameter for lm in self.detector.color_landmarks])
            uv, z = model.project(p, L)
            with np.errstate(invalid="ignore", divide="ignore"):
                radius = self.camera.K[0, 0] * diameters / (2.0 * z)
            area = math.pi * radius**2
            rim = (margin + radius)[:, None]  # a disc cut by the border is dropped by the detector
            seen_at = self.camera.distort(uv)
            inside = np.all((seen_at >= rim) & (seen_at <= size - 1 - rim), axis=1) & (z > MIN_DEPTH)
            seen = inside & (area >= self.perception.landmark_min_area)
            chosen.append(L[seen])
            groups.append(landmarks + np.arange(int(seen.sum())))
            landmarks += int(seen.sum())
        X = np.vstack(chosen) if chosen else np.empty((0, 3))
        return X, np.concatenate(groups) if groups else np.empty(0, dtype=int), landmarks

    def best_landmark_view(self, pose: Pose, camera_in_robot: Callable[[float, float], np.ndarray],
                           directions: Iterable[Tuple[float, float]]) -> Optional[LandmarkView]:
        """Of the head ``directions`` (yaw, pitch), the one whose predicted fix from ``pose`` is most precise."""
        best: Optional[LandmarkView] = None
        for yaw, pitch in directions:
            points, cov = self.predicted_fix(pose, camera_in_robot(yaw, pitch))
            if cov is None:
                continue
            view = LandmarkView(float(yaw), float(pitch), points, float(math.sqrt(np.linalg.eigvalsh(cov[:2, :2])[-1])),
                                float(math.sqrt(cov[2, 2])))
            if best is None or view.position_std < best.position_std:
                best = view
        return best

    # -- fusion --------------------------------------------------------------------------------

    def _accept_jump(self, prior: Pose, fix: PoseFix, odom: Pose) -> bool:
        if fix.conditioned:  # pulled to the prior: it may move the pose within the prior's covariance, and never re-localizes
            return self._within_gate(fix.pose, prior, self.covariance)
        if fix.tracked:  # markers found where the prior put them: they neither re-localize nor vouch for the prior
            return self._within_gate(fix.pose, prior, self.covariance + fix.covariance)
        if self._within_gate(fix.pose, prior, self.covariance + fix.covariance):
            self.rejected_jumps, self._rejected = 0, None
            return True
        correction = compose(fix.pose, relative(odom, (0.0, 0.0, 0.0)))
        agrees = self._rejected is not None and self._within_gate(correction, self._rejected[0], self._rejected[1] + fix.covariance)
        self.rejected_jumps = self.rejected_jumps + 1 if agrees else 1
        self._rejected = (correction, fix.covariance)
        if self.rejected_jumps >= self.params.max_rejected_jumps:
            self.rejected_jumps, self._rejected = 0, None
            self._correction = None  # the prior is wrong: restart from this fix
            return True
        return False

    def _within_gate(self, pose: Pose, prior: Pose, covariance: np.ndarray) -> bool:
        """``pose`` is no jump from ``prior`` (module docstring): within the per-axis gate and the Mahalanobis one."""
        p = self.params
        floor = np.array([p.jump_floor[0], p.jump_floor[0], p.jump_floor[1]])
        if not np.all(np.abs(_difference(pose, prior)) <= p.jump_sigmas * np.sqrt(np.diag(covariance)) + floor):
            return False
        return _mahalanobis(pose, prior, covariance + self._floor) <= p.jump_chi2

    @property
    def intrinsics_covariance(self) -> np.ndarray:
        """Of (s_x, s_y, d_u, d_v, e): what the camera's K and its markers' edges may be off by (module docstring)."""
        return self._intrinsics_covariance

    def set_intrinsics_covariance(self, covariance: np.ndarray) -> None:
        """The covariance of (s_x, s_y, d_u, d_v, e) the camera may be off by (a new estimate: the pose's error
        no longer correlates with the new K's)."""
        self._intrinsics_covariance = np.asarray(covariance, dtype=float)
        self._intrinsics_cross = np.zeros((6, N_INTRINSICS))

    def _fuse(self, fix: PoseFix, prior: Optional[Pose], odom: Pose) -> None:
        G, X, Sigma = fix.intrinsics_gain, self._intrinsics_cross, self._intrinsics_covariance
        R = fix.covariance + self._floor  # what the gate judged the fix by (module docstring)
        if self._correction is None or prior is None or not np.all(np.isfinite(self.covariance)):
            pose = np.array(fix.pose)
            self._augmented = _known_pose(R, self._augmented[3:, 3:])
            self._augmented_total = _known_pose(R + G @ Sigma @ G.T, self._augmented_total[3:, 3:])
            self._intrinsics_cross = np.vstack([G @ Sigma, np.zeros((3, N_INTRINSICS))])
        else:
            P_prior = self.covariance
            if fix.conditioned:  # the posterior already: the data's information I_d = R_post^-1 - P^-1, K = P_post I_d
                prior_information = np.linalg.inv(P_prior)
                w, V = np.linalg.eigh(np.linalg.inv(fix.covariance) - prior_information)
                data_information = (V * np.maximum(w, 0.0)) @ V.T
                pose, P = np.array(fix.pose), np.linalg.inv(prior_information + data_information)
                K = P @ data_information
                KG, measured = G, K @ P.T  # the fix's gain is the posterior's, K G already; K R K^T = P I_d P
            else:
                K = P_prior @ np.linalg.inv(P_prior + R)
                pose = np.array(prior) + K @ _difference(fix.pose, prior)
                P = (np.eye(3) - K) @ P_prior
                KG, measured = K @ G, K @ R @ K.T
            L = np.linalg.solve(P_prior, self._augmented[:3, 3:]).T  # P_sp P^-1: the scales move with the pose
            M = np.vstack([np.eye(3), L])  # the whole state's gain is M K
            self.scale = np.clip(self.scale + L @ _difference(tuple(pose), prior), *SCALE_BOUNDS)
            posterior = self._augmented.copy()
            posterior[:3, :3] = P
            posterior[3:, :3] = L @ P
            posterior[:3, 3:] = posterior[3:, :3].T
            posterior[3:, 3:] -= L @ (P_prior - P) @ L.T
            self._augmented = posterior
            A = np.eye(6) - M @ K @ np.eye(3, 6)
            T = self._augmented_total
            total = A @ T @ A.T + A @ X @ (M @ KG).T + M @ KG @ X.T @ A.T + M @ KG @ Sigma @ KG.T @ M.T + M @ measured @ M.T
            self._augmented_total = total
            self._intrinsics_cross = A @ X + M @ KG @ Sigma
        self._augmented = 0.5 * (self._augmented + self._augmented.T)
        self._augmented_total = 0.5 * (self._augmented_total + self._augmented_total.T)
        fused = (float(pose[0]), float(pose[1]), wrap_angle(float(pose[2])))
        self._correction = compose(fused, relative(self._scaled(odom), (0.0, 0.0, 0.0)))


def _unknown_pose(scale_covariance: np.ndarray) -> np.ndarray:
    """6 x 6 covariance of (pose, scale) with the pose not known (nan) and the scales' ``scale_covariance``."""
    return _known_pose(np.full((3, 3), np.nan), scale_covariance)


def _set_pose_block(augmented: np.ndarray, pose_covariance: np.ndarray) -> None:
    """Set the pose's block of a (pose, scale) covariance, uncorrelated with the scales."""
    augmented[:3, :3] = pose_covariance
    augmented[:3, 3:] = augmented[3:, :3] = 0.0


def _known_pose(pose_covariance: np.ndarray, scale_covariance: np.ndarray) -> np.ndarray:
    """6 x 6 covariance of (pose, scale), the two uncorrelated (a first fix: the pose from landmarks alone)."""
    out = np.zeros((6, 6))
    out[:3, :3], out[3:, 3:] = pose_covariance, scale_covariance
    return out


def head_directions(head_limits, yaw_step: float = 0.25, pitches: int = 2) -> List[Tuple[float, float]]:
    """A grid of head (yaw, pitch) within ``HeadLimits`` (its ``yaw`` range and ``pitch_range(yaw)``)."""
    out = []
    for yaw in np.arange(head_limits.yaw[0], head_limits.yaw[1] + 1e-9, yaw_step):
        lo, hi = head_limits.pitch_range(float(yaw))
        out += [(float(yaw), float(pitch)) for pitch in np.linspace(lo, hi, pitches + 2)[1:-1]]
    return out


def _tilt_evidence(data: np.ndarray, prior: np.ndarray, p: np.ndarray, variance: float) -> Tuple[np.ndarray, np.ndarray]:
    """(I_d, I_d t_d): the information of a fit's data alone on (delta, epsilon), the pose eliminated
    (Schur complement of its normal matrix ``data``, pixel units, residual ``variance``), and the
    vector the fit's optimum p under the zero-mean ``prior`` gives: (I_d,px + prior_tt) t = I_d,px t_d."""
    try:
        marginal = data[3:, 3:] - data[3:, :3] @ np.linalg.solve(data[:3, :3], data[:3, 3:])
    except np.linalg.LinAlgError:
        return np.zeros((2, 2)), np.zeros(2)
    marginal = 0.5 * (marginal + marginal.T)
    return marginal / variance, (marginal + prior[3:, 3:]) @ p[3:5] / variance


def _from_mean(p: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """p - mean for p = (x, y, theta, delta, epsilon), the heading's difference wrapped."""
    offset = p - mean
    offset[2] = wrap_angle(offset[2])
    return offset


def _check_rate(camera_rate: Sequence[float]) -> np.ndarray:
    """The camera's angular velocity as three finite rad/s; ValueError naming it otherwise."""
    rate = np.asarray(camera_rate, dtype=float)
    if rate.shape != (3,) or not np.all(np.isfinite(rate)):
        raise ValueError(f"camera_rate must be three finite rad/s, got {camera_rate!r}")
    return rate


def _positive_covariance(covariance: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """A pose prior's covariance, symmetrized, or None unless 3 x 3, finite and positive definite."""
    if covariance is None:
        return None
    P = np.asarray(covariance, dtype=float)
    if P.shape != (3, 3) or not np.all(np.isfinite(P)):
        return None
    P = 0.5 * (P + P.T)
    return P if np.all(np.linalg.eigvalsh(P) > 0) else None


def _distinct(poses: np.ndarray, scores: np.ndarray, distance: float, limit: int = 8) -> List[np.ndarray]:
    """Up to ``limit`` poses, best score first, each further than ``distance`` from those kept."""
    kept: List[np.ndarray] = []
    for k in np.argsort(-scores, kind="stable"):
        if all(math.hypot(*(poses[k][:2] - q[:2])) > distance for q in kept):
            kept.append(poses[k])
            if len(kept) == limit:
                break
    return kept


def _group_max(err: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Largest error of each group, in the order of np.unique(group)."""
    _, inverse = np.unique(group, return_inverse=True)
    out = np.full(inverse.max() + 1 if len(inverse) else 0, -np.inf)
    np.maximum.at(out, inverse, np.nan_to_num(err, nan=np.inf))
    return out


def _mahalanobis(p: np.ndarray, prior: np.ndarray, S: np.ndarray) -> float:
    d = _difference(tuple(p[:3]), tuple(prior[:3]))
    return float(d @ np.linalg.solve(S, d))


def _difference(a: Pose, b: Pose) -> np.ndarray:
    """a - b with the heading difference wrapped."""
    return np.array([a[0] - b[0], a[1] - b[1], wrap_angle(a[2] - b[2])])


def _merge_boxes(boxes: List[list]) -> List[Box]:
    """Boxes (x0, y0, x1, y1, side, markers) with every overlapping pair replaced by their union
    (smallest side, markers summed), until none overlap."""
    merged: List[list] = []
    for box in boxes:
        while True:
            overlapping = [m for m in merged if box[0] < m[2] and m[0] < box[2] and box[1] < m[3] and m[1] < box[3]]
            if not overlapping:
                break
            for m in overlapping:
                merged.remove(m)
                box = [min(box[0], m[0]), min(box[1], m[1]), max(box[2], m[2]), max(box[3], m[3]), min(box[4], m[4]), box[5] + m[5]]
        merged.append(box)
    return [(int(b[0]), int(b[1]), int(b[2]), int(b[3]), float(b[4]), int(b[5])) for b in merged]


def _check_transform(T_BC: object) -> np.ndarray:
    try:
        T = np.asarray(T_BC, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"T_BC must be a finite 4 x 4 transform, got {type(T_BC).__name__}") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_BC must be a finite 4 x 4 transform, got shape {T.shape}")
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: not orthonormal either
        rigid = np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-3) and np.allclose(T[3], [0, 0, 0, 1])
    if not rigid:
        raise ValueError("T_BC must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
    return T


def _check_pose(pose: object, name: str) -> Pose:
    try:
        values = tuple(float(v) for v in pose)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (x, y, theta), got {pose!r}") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{name} must be three finite numbers (x, y, theta), got {pose!r}")
    return values  # type: ignore[return-value]


def landmarks_in_image(camera: CameraModel, landmarks: LandmarkMap, T_WC: np.ndarray, margin: float = 3.0) -> int:
    """How many landmarks are wholly in the image at T_WC: a marker's four corners (facing the camera),
    a disc with its rim, ``margin`` pixels from the border (tests and the localization benchmark count views by it)."""
    count = 0
    for lm in landmarks.landmarks:
        points = lm.aruco_corners() if lm.kind == "aruco" else np.array([lm.position])
        uv, front = camera.project_world(points, T_WC)
        if not front.all():
            continue
        pad = margin
        if lm.kind == "aruco" and np.dot(lm.normal, T_WC[:3, 3] - np.asarray(lm.position)) <= 0:
            continue
        if lm.kind == "color":
            pad += camera.K[0, 0] * lm.diameter / 2 / np.linalg.norm(np.asarray(lm.position) - T_WC[:3, 3])
        count += bool(np.all(uv >= pad) and np.all(uv <= np.array([camera.width, camera.height]) - 1 - pad))
    return count
