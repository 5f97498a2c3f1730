"""Facts of the NAOqi API that both the bridge's NAOqi backend and the NAOqi stand-in rely on.

Camera ids, ``ALMotion.getTransform`` frames, ``ALVideoDevice`` resolution and colour-space ids,
joint names and ``ALMemory`` keys, as documented for NAOqi 2.8 (docs/bridge.md).
"""

TOP_CAMERA = 0
FRAME_ROBOT = 2
RESOLUTION_IDS = {"qqvga": 0, "qvga": 1, "vga": 2, "4vga": 3}
COLOR_SPACE_IDS = {"yuv422": 9, "bgr": 13}  # the colour spaces the bridge asks for
RGB_COLOR_SPACE = 11  # kRGBColorSpace: decoded when a robot answers with it
Y_COLOR_SPACE = 0  # kYuvColorSpace (luma only): decoded to grey when a robot answers with it
YUV_COLOR_SPACE = 10  # kYUVColorSpace (3 bytes a pixel): decoded when a robot answers with it
HEAD_JOINTS = ["HeadYaw", "HeadPitch"]
FALL_KEYS = ("robotHasFallen", "ALMotion/RobotIsFalling")
BATTERY_KEY = "Device/SubDeviceList/Battery/Charge/Sensor/Value"
CLOCK_PROBE_KEY = "NaoActiveRecon/ClockProbe"  # the bridge writes it and reads its robot stamp (getTimestamp)


def error_line(exc: BaseException) -> str:
    """A libqi error's message without the remote traceback it appends (the exception's type if empty)."""
    return (str(exc).strip().splitlines() or [type(exc).__name__])[0]
