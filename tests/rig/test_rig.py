"""rig.toml: round trip and validation at load time."""

import pytest

from ptpcore.errors import ConfigError
from ptpcore.rig import Rig, load_rig, rig_from_toml, rig_to_toml, save_rig, validate_template

GOOD = rig_to_toml(Rig())


def test_round_trip(tmp_path):
    rig = Rig().with_z([0.0, 2.5, 5.0])
    save_rig(rig, tmp_path / "rig.toml")
    assert load_rig(tmp_path) == rig


def test_formats_md_example_loads():
    text = '''
format = "ptp-dataset/1"
[camera]
width = 640
height = 480
bit_depth = 8
[lcd]
width = 3840
height = 2160
pitch_mm = [0.05, 0.05]
[stage]
z_mm = [0.0, 4.0, 8.0]
direction = [0.0, 0.0, 1.0]
[fringes]
directions = ["x", "y"]
periods_px = [4096, 512, 64, 16]
steps = [4, 4, 4, 8]
offset = 127.5
amplitude = 100.0
carrier_px_per_mm = [0.0, 0.0]
gamma = 1.0
[images]
template = "z{pos:03d}/{dir}_T{period}_n{step:02d}.png"
'''
    rig = rig_from_toml(text)
    assert rig.fringes.steps == (4, 4, 4, 8)
    assert rig.image_name(2, "y", 64, 3, 4) == "z002/y_T64_n03.png"


def test_single_integer_steps():
    rig = rig_from_toml(GOOD.replace("steps = [\n    4,\n    4,\n    4,\n    8,\n]", "steps = 6"))
    assert rig.fringes.steps == (6, 6, 6, 6)


@pytest.mark.parametrize("old,new,culprit", [
    ("width = 640", 'width = "640"', "camera.width"),
    ("bit_depth = 8", "bit_depth = 20", "camera.bit_depth"),
    ("[camera]", "[camera]\nexposure = 3", "camera.exposure"),
    ("gamma = 1.0", "gamma = -1.0", "fringes.gamma"),
    ("    4.0,\n", "    0.0,\n", "stage.z_mm"),
    ("    512,\n", "    8192,\n", "fringes.periods_px"),
])
def test_errors_name_the_key(old, new, culprit):
    assert old in GOOD
    with pytest.raises(ConfigError, match=culprit.replace(".", r"\.")):
        rig_from_toml(GOOD.replace(old, new, 1))


def test_missing_section():
    text = GOOD.split("[lcd]")[0] + "[stage]" + GOOD.split("[stage]")[1]
    with pytest.raises(ConfigError, match=r"missing section \[lcd\]"):
        rig_from_toml(text)


@pytest.mark.parametrize("template", ["{pos.__class__}/{dir}{period}{step}.png", "{dir[0]}{pos}{period}{step}.png",
                                      "{pos!r}{dir}{period}{step}.png", "{pos}{dir}{period}{step}{evil}.png",
                                      "../{pos}{dir}{period}{step}.png", "{pos:{step}}{dir}{period}{step}.png"])
def test_template_refuses_anything_but_plain_fields(template):
    with pytest.raises(ConfigError, match="images.template"):
        validate_template(template)
