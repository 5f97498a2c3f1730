"""Topics of the run log (docs/station.md lists what each carries)."""

# as received from the bridge (bytes unchanged), and what the station sent
INFO = "/nao/info"
FRAME_META = "/nao/camera/meta"
FRAME_IMAGE = "/nao/camera/image"  # foxglove.CompressedImage, the JPEG bytes unchanged
CALIBRATION = "/nao/camera/calibration"  # foxglove.CameraCalibration
STATE = "/nao/state"
TRUTH = "/nao/sim/truth"
CMD_WALK = "/nao/cmd/walk"
CMD_HEAD = "/nao/cmd/head"
# the station
CONFIG = "/station/config"  # resolved configuration (replay rebuilds it)
INPUT = "/station/input"  # journal of the inputs handed to the agent, in order
REJECTED = "/station/rejected"  # messages that failed strict decoding
CARVING = "/station/carving"  # live carving progress
ERROR = "/station/error"  # an exception that ended the run, with its traceback
KEYFRAME_POSES = "/station/keyframe_poses"  # the keyframes' T_WC smoothed at the end, which the final carve used
# agent outputs (replay compares every topic under this prefix)
AGENT_PREFIX = "/agent/"
DECISION = "/agent/decision"
POSE = "/agent/pose"
MEASUREMENT = "/agent/measurement"
EKF = "/agent/ekf"
COVERAGE = "/agent/coverage"
PLAN = "/agent/plan"
KEYFRAME = "/agent/keyframe"
FRAME_REJECTED = "/agent/frame_rejected"  # a frame a per-frame step raised on (dropped)
SELF_CALIBRATION = "/agent/self_calibration"  # the camera intrinsics the mission's landmark fixes gave (agent/self_calibration.py)
# Foxglove views (config/foxglove/layout.json)
LOG = "/station/log"  # foxglove.Log: every console line
ESTIMATE = "/station/estimate"  # the object estimate and its standard deviations, for plots
ANNOTATIONS = "/nao/camera/annotations"  # foxglove.ImageAnnotations, stamped like the frame
TRAJECTORY = "/scene/trajectory"  # foxglove.PosesInFrame: the robot's localized poses
TF = "/tf"
SCENE_OBJECT = "/scene/object"
SCENE_LANDMARKS = "/scene/landmarks"
SCENE_KEYFRAMES = "/scene/keyframes"
SCENE_MODEL = "/scene/model"
