from pathlib import Path

import pytest

from jetbot_rt.config.sections import Config, load_config
from jetbot_rt.errors import UsageError


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return path


def test_defaults_without_file():
    config = load_config(None)
    assert config == Config()
    assert config.loop.rate_hz == 30.0
    assert config.loop.watchdog_timeout_s == pytest.approx(0.1)
    assert config.motors.layout == "waveshare"
    assert config.motors.i2c_bus == 1
    assert config.motors.address == 0x60
    assert config.camera.source == "csi"


def test_values_are_loaded_and_typed(tmp_path):
    config = load_config(write(tmp_path, """
[loop]
rate_hz = 50
[actions]
max_speed = 0.2
trim = [1.0, 0.9]
sign = [1, -1]
[motors]
layout = "adafruit_motorhat"
address = 0x61
[camera]
source = "gst:videotestsrc"
"""))
    assert config.loop.rate_hz == 50.0 and isinstance(config.loop.rate_hz, float)
    assert config.loop.watchdog_timeout_s == pytest.approx(0.1)  # 3 periods, at least 0.1 s
    assert config.max_frame_age_s == pytest.approx(0.15)
    assert config.actions.max_speed == 0.2
    assert config.actions.trim == [1.0, 0.9]
    assert config.actions.sign == [1, -1]
    assert config.motors.layout == "adafruit_motorhat"
    assert config.motors.address == 0x61
    assert config.camera.source == "gst:videotestsrc"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[loop]\nrate_hz = 0", "[loop] rate_hz must be a number in [1, 100] Hz, got 0"),
        ("[loop]\nrate_hz = -5", "[loop] rate_hz must be a number in [1, 100] Hz"),
        ("[loop]\nrate_hz = 'fast'", "[loop] rate_hz must be a number, got 'fast'"),
        ("[loop]\nspeed = 1", "unknown key [loop] speed"),
        ("[wheels]\nx = 1", "unknown section [wheels]"),
        ("[actions]\nmax_speed = 1.5", "[actions] max_speed must be a number in (0, 1]"),
        ("[actions]\nmax_speed = 0", "[actions] max_speed must be a number in (0, 1]"),
        ("[actions]\ntrim = [1.0]", "[actions] trim must be two numbers in [0, 2]"),
        ("[actions]\nsign = [1, 0]", "[actions] sign must be two values, each 1 or -1"),
        ("[motors]\nlayout = 'l298n'", "[motors] layout must be one of 'waveshare'"),
        ("[motors]\naddress = 200", "[motors] address must be 0x03..0x77"),
        ("[camera]\nsource = 'webcam'", "[camera] source must be \"csi\""),
        ("[policy]\nlayout = 'NWHC'", "[policy] layout must be one of 'NHWC', 'NCHW'"),
        ("loop = 3", "[loop] must be a table"),
        ("[loop\nrate_hz = 3", "is not valid TOML"),
    ],
)
def test_bad_values_name_the_key(tmp_path, text, message):
    with pytest.raises(UsageError) as info:
        load_config(write(tmp_path, text))
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(UsageError, match="cannot read config"):
        load_config(tmp_path / "nope.toml")
