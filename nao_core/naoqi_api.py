"""Facts of the NAOqi API that both the bridge's NAOqi backend and the NAOqi stand-in rely on.

Camera ids, ``ALMotion.getTransform`` frames, ``ALVideoDevice`` resolution and colour-space ids,
joint names and ``ALMemory`` keys, as documented for NAOqi 2.8 (docs/bridge.md).
"""

TOP_CAMERA = 0
FRAME_ROBOT = 2
RESOLUTION_IDS = {"qqvga": 0, "qvga": 1, "vga": 2, "4vga": 3}
COLOR_SPACE_IDS = {"yuv422": 9, "bgr": 13}
HEAD_JOINTS = ["HeadYaw", "HeadPitch"]
FALL_KEYS = ("robotHasFallen", "ALMotion/RobotIsFalling")
BATTERY_KEY = "Device/SubDeviceList/Battery/Charge/Sensor/Value"
CLOCK_PROBE_KEY = "NaoActiveRecon/ClockProbe"  # the bridge writes it and reads its robot stamp (getTimestamp)
