"""ptp-dataset/2 in rig.toml: every key parsed, validated, kept; /1 unchanged."""

import math

import pytest

from ptpcore.errors import ConfigError
from ptpcore.rig import (DATASET_FORMAT, DATASET_FORMAT_2, Rig, format_period, load_rig, rig_from_toml,
                         rig_to_toml, save_rig)

FULL = '''
format = "ptp-dataset/2"

[camera]
width = 64
height = 48
bit_depth = 12
bit_shift = 4

[lcd]
width = 3840
height = 2160
pitch_mm = [0.05, 0.05]
cover_glass_mm = 1.1
cover_glass_index = 1.5
cover_glass_mm_sigma = 0.05
cover_glass_index_sigma = 0.01
flatness_u_px = [0, 1920, 3840]
flatness_v_px = [0, 1080, 2160]
flatness_um = [[0, 5, 0], [5, 12, 5], [0, 5, 0]]

[display]
levels = [0, 64, 128, 192, 255]
luminance = [0.0, 0.05, 0.22, 0.53, 1.0]

[stage]
z_mm = [0.0, 4.0, 8.0]
repeat_z_mm = [0.0]

[fringes]
directions = ["x", "y"]
periods_px = [3840.0, 480.0, 67.5]
steps = [8, 8, 8]
phase_origin_rad = 3.14159
shift_sign = -1
unwrap = "gray"
gray_bits = 5
gray_inverse = true

[fringes.y]
periods_px = [2160.0, 270.0, 33.75]
steps = [4, 4, 6]
shift_sign = 1
gray_bits = 4

[decode]
min_modulation = 0.05
border_margin_px = 2
unwrap_tolerance = 0.2

[images]
template = "z{pos:03d}/{dir}_T{period}_n{step:02d}.png"
gray_template = "z{pos:03d}/{dir}_G{bit:02d}_{inverse}.png"
white_template = "z{pos:03d}/white.png"
black_template = "z{pos:03d}/black.png"
'''


def test_formats_md_v2_example_round_trips(tmp_path):
    rig = rig_from_toml(FULL)
    f = rig.fringes
    assert rig.camera.bit_shift == 4
    assert rig.lcd.cover_glass_mm == 1.1 and rig.lcd.flatness_um[1] == (5, 12, 5)
    assert rig.display.luminance[2] == 0.22
    assert rig.stage.repeat_z_mm == (0.0,) and rig.stage.n_positions == 3
    assert f.periods("x") == (3840.0, 480.0, 67.5) and f.periods("y") == (2160.0, 270.0, 33.75)
    assert f.steps_of("y") == (4, 4, 6) and f.steps_of("x") == (8, 8, 8)
    assert f.sign("x") == -1 and f.sign("y") == 1 and f.origin("y") == 3.14159
    assert f.bits("x") == 5 and f.bits("y") == 4
    assert rig.decode.unwrap_tolerance == 0.2
    assert rig.image_name(1, "x", 67.5, 2, 8) == "z001/x_T67.5_n02.png"
    assert rig.image_name(0, "x", 3840.0, 0, 8) == "z000/x_T3840_n00.png"
    assert rig.gray_name(2, "y", 3, True) == "z002/y_G03_1.png"
    assert rig.reference_name(0, "black") == "z000/black.png"
    assert f.frames_per_position == 24 + 14 + 2 * 9
    text = rig_to_toml(rig)
    assert text.startswith(f'format = "{DATASET_FORMAT_2}"')
    assert rig_from_toml(text) == rig
    save_rig(rig, tmp_path / "rig.toml")
    assert load_rig(tmp_path) == rig


def test_v1_rig_still_written_as_v1():
    text = rig_to_toml(Rig())
    assert text.startswith(f'format = "{DATASET_FORMAT}"')
    assert rig_from_toml(text) == Rig()
    # A /2 file using no /2 key is the same rig, and writes back as /1.
    rig = rig_from_toml(text.replace(DATASET_FORMAT, DATASET_FORMAT_2))
    assert rig == Rig() and rig_to_toml(rig).startswith(f'format = "{DATASET_FORMAT}"')


def test_period_formatting():
    assert format_period(67.5) == 67.5 and str(format_period(120.0)) == "120"
    assert str(format_period(759 / 0.9)) == repr(759 / 0.9)


def test_frames_list_round_trip():
    text = '''
format = "ptp-dataset/2"
[camera]
width = 8
height = 6
[lcd]
width = 100
height = 100
pitch_mm = [0.1, 0.1]
[stage]
z_mm = [0.0]
[fringes]
directions = ["x"]
periods_px = [150.0, 66.66666666666667]
steps = 3
phase_origin_rad = -2.0943951023931953
unwrap = "gray"
gray_bits = 1
gray_inverse = true
''' + "".join(f'''
[[images.frames]]
dir = "x"
period_index = {j}
step = {n}
file = "pat{3 * j + n:02d}.png"
''' for j in range(2) for n in range(3)) + '''
[[images.frames]]
dir = "x"
gray_bit = 0
file = "g0.png"
[[images.frames]]
dir = "x"
gray_bit = 0
inverse = true
file = "g0i.png"
[[images.frames]]
reference = "white"
file = "w.png"
[[images.frames]]
reference = "black"
file = "b.png"
'''
    rig = rig_from_toml(text)
    assert rig.image_name(0, "x", 66.66666666666667, 2, 3) == "pat05.png"
    assert rig.gray_name(0, "x", 0, True) == "g0i.png" and rig.reference_name(0, "white") == "w.png"
    assert rig.has_references and rig.stage.n_positions == 1
    assert rig_from_toml(rig_to_toml(rig)) == rig
    with pytest.raises(ConfigError, match=r"names no frame for pos = 0, dir = 'x', period_index = 1, step = 2"):
        rig_from_toml(text.replace('[[images.frames]]\ndir = "x"\nperiod_index = 1\nstep = 2\nfile = "pat05.png"\n', ""))
    with pytest.raises(ConfigError, match="entry 6: the same frame as entry 5"):
        rig_from_toml(text.replace("period_index = 1\nstep = 2", "period_index = 1\nstep = 1"))
    with pytest.raises(ConfigError, match="entry 11: unknown key 'colour'"):
        rig_from_toml(text + '[[images.frames]]\ncolour = 1\nfile = "x.png"\n')
    with pytest.raises(ConfigError, match="white reference frame for pos = 0 but not its black"):
        rig_from_toml(text.replace('[[images.frames]]\nreference = "black"\nfile = "b.png"\n', ""))


@pytest.mark.parametrize("old,new,culprit", [
    ("shift_sign = -1", "shift_sign = 2", "fringes.shift_sign"),
    ('unwrap = "gray"', 'unwrap = "spiral"', "fringes.unwrap"),
    ("gray_bits = 5", "gray_bits = 99", "fringes.gray_bits"),
    ("gray_inverse = true", "gray_inverse = 1", "fringes.gray_inverse"),
    ("steps = [4, 4, 6]", "steps = [4, 4]", "fringes.y.steps"),
    ("periods_px = [2160.0, 270.0, 33.75]", "periods_px = [2160.0, 33.75, 270.0]", "fringes.y.periods_px"),
    ("[fringes.y]", "[fringes.y]\nwobble = 1", "fringes.y.wobble"),
    ("bit_shift = 4", "bit_shift = 5", "camera.bit_shift"),
    ("cover_glass_mm = 1.1", "cover_glass_mm = -1.1", "lcd.cover_glass_mm"),
    ("cover_glass_index = 1.5", "cover_glass_index = 0.5", "lcd.cover_glass_index"),
    ("flatness_um = [[0, 5, 0], [5, 12, 5], [0, 5, 0]]", "flatness_um = [[0, 5], [5, 12], [0, 5]]", "lcd.flatness_um"),
    ("luminance = [0.0, 0.05, 0.22, 0.53, 1.0]", "luminance = [0.0, 0.5, 0.22, 0.53, 1.0]", "display.luminance"),
    ("repeat_z_mm = [0.0]", "repeat_z_mm = [\"a\"]", "stage.repeat_z_mm"),
    ("unwrap_tolerance = 0.2", "unwrap_tolerance = 0.7", "decode.unwrap_tolerance"),
    ("min_modulation = 0.05", "min_modulation = 2", "decode.min_modulation"),
    ("[decode]", "[decode]\nk = 5", "decode.k"),
    ('gray_template = "z{pos:03d}/{dir}_G{bit:02d}_{inverse}.png"', 'gray_template = "z{pos:03d}/{dir}_G{bit:02d}.png"',
     "images.gray_template"),
    ('white_template = "z{pos:03d}/white.png"\n', "", "images.black_template"),
    # Several positions: a Gray-code or reference template without {pos} would name one file for all.
    ('gray_template = "z{pos:03d}/{dir}_G', 'gray_template = "g/{dir}_G', "images.gray_template"),
    ('white_template = "z{pos:03d}/white.png"', 'white_template = "white.png"', "images.white_template"),
    ("{period}_n", "{period:04d}_n", "images.template"),
])
def test_v2_errors_name_the_key(old, new, culprit):
    assert old in FULL
    with pytest.raises(ConfigError, match=culprit.replace(".", r"\.")):
        rig_from_toml(FULL.replace(old, new))


def test_integer_format_spec_on_fractional_period_names_template():
    with pytest.raises(ConfigError, match=r"key 'images.template' cannot name period 67.5 px"):
        rig_from_toml(FULL.replace("{period}_n", "{period:04d}_n"))
    # ... but an integer period with an integer spec is fine, and {period_index} serves too.
    ok = rig_from_toml(FULL.replace("{period}_n", "{period_index}_n"))
    assert ok.image_name(0, "y", 33.75, 0, 6) == "z000/y_T2_n00.png"


def test_v2_keys_refused_in_v1():
    text = rig_to_toml(Rig())
    with pytest.raises(ConfigError, match="'camera.bit_shift' is a ptp-dataset/2 key"):
        rig_from_toml(text.replace("bit_depth = 8", "bit_depth = 8\nbit_shift = 0"))
    with pytest.raises(ConfigError, match=r"\[decode\] is a ptp-dataset/2 table"):
        rig_from_toml(text + "\n[decode]\nmin_modulation = 0.1\n")
    with pytest.raises(ConfigError, match="fringes.periods_px"):
        rig_from_toml(text.replace("    16,\n]", "    16.5,\n]"))


def test_plain_design_flag():
    assert Rig().fringes.is_plain
    rig = rig_from_toml(FULL)
    assert not rig.fringes.is_plain
    assert math.isclose(rig.fringes.origin("x"), 3.14159)


def test_cover_glass_zero_declared_is_not_absent():
    """Issue 14: ``cover_glass_mm = 0`` (no glass, declared) round-trips and differs from the key absent."""
    from dataclasses import replace

    from ptpcore.rig import rig_from_toml, rig_to_toml
    from ptpcore.simulate import preset

    rig = preset("mild")[0]
    assert rig.lcd.cover_glass_mm is None and "cover_glass_mm" not in rig_to_toml(rig)
    zero = replace(rig, lcd=replace(rig.lcd, cover_glass_mm=0.0))
    text = rig_to_toml(zero)
    assert "cover_glass_mm = 0.0" in text
    back = rig_from_toml(text)
    assert back.lcd.cover_glass_mm == 0.0 and back == zero and back != rig
