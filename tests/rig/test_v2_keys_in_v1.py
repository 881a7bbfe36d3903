"""A ptp-dataset/2 key in a file that declares ptp-dataset/1: one error naming the format that has it."""

import re

import pytest

from ptpcore.errors import ConfigError
from ptpcore.rig import DATASET_FORMAT, DATASET_FORMAT_2, Rig, load_rig, rig_from_toml, rig_to_toml
from ptpcore.rig.reading import V2_KEYS

V1 = rig_to_toml(Rig())
assert V1.startswith(f'format = "{DATASET_FORMAT}"')

V2 = '''format = "ptp-dataset/2"

[camera]
width = 64
height = 48
bit_depth = 12

[lcd]
width = 3840
height = 2160
pitch_mm = [0.05, 0.05]

[stage]
z_mm = [0.0, 4.0, 8.0]

[fringes]
directions = ["x", "y"]
periods_px = [4096, 512, 64, 16]
steps = [4, 4, 4, 8]

[fringes.x]
shift_sign = 1

[fringes.y]
shift_sign = 1

[images]
template = "z{pos:03d}/{dir}_T{period}_n{step:02d}.png"
'''

# A value of each /2 key that the /2 reader would accept (the /1 reader must refuse it first).
VALUES = {"bit_shift": "0", "cover_glass_mm": "1.1", "cover_glass_index": "1.52", "cover_glass_mm_sigma": "0.05",
          "cover_glass_index_sigma": "0.01", "flatness_u_px": "[0, 3840]", "flatness_v_px": "[0, 2160]",
          "flatness_um": "[[0, 0], [0, 0]]", "repeat_z_mm": "[0.0]", "phase_origin_rad": "0.0",
          "shift_sign": "1", "unwrap": '"periods"', "gray_bits": "0", "gray_inverse": "false",
          "gray_template": '"z{pos:03d}/{dir}_G{bit:02d}_{inverse}.png"', "white_template": '"z{pos:03d}/w.png"',
          "black_template": '"z{pos:03d}/b.png"'}
TABLES = {"display": "levels = [0, 255]\nluminance = [0.0, 1.0]", "decode": "min_modulation = 0.05",
          "projector": "width = 1280\nheight = 800\nperiods_px = [1280.0, 160.0, 20.0]\nsteps = [4, 4, 8]",
          "height": "z_mm = [0.0, 4.0, 8.0]"}


def _allowed(text: str, section: str) -> set[str]:
    """The keys the reader allows in ``[section]``, read off its message for an unknown key."""
    marker = f"[{section}]\n"
    with pytest.raises(ConfigError) as err:
        rig_from_toml(text.replace(marker, marker + "zz_unknown = 1\n", 1))
    listed = re.search(r"unknown key '" + section + r"\.zz_unknown' \(allowed: ([^)]*)\)", str(err.value))
    assert listed, str(err.value)
    return set(listed.group(1).split(", "))


@pytest.mark.parametrize("section", ["camera", "lcd", "stage", "fringes", "images"])
def test_the_list_is_the_readers_difference(section):
    """V2_KEYS holds exactly the keys /2 reads beyond /1 (so a new /2 key cannot be forgotten there)."""
    v2_only = _allowed(V2, section) - _allowed(V1, section)
    assert v2_only == set(V2_KEYS[section])


def _cases():
    for section, keys in V2_KEYS.items():
        for key in keys:
            if section == "":
                yield section, key, V1 + f"\n[{key}]\n{TABLES[key]}\n", f"table [{key}] is a {DATASET_FORMAT_2} table"
            elif key in ("x", "y"):
                text = V1.replace("\n[images]\n", f"\n[fringes.{key}]\nshift_sign = 1\n\n[images]\n")
                yield section, key, text, f"table [fringes.{key}] is a {DATASET_FORMAT_2} table"
            elif key == "frames":
                text = V1 + '\n[[images.frames]]\ndir = "x"\nperiod_index = 0\nstep = 0\nfile = "a.png"\n'
                yield section, key, text, f"table [[images.frames]] is a {DATASET_FORMAT_2} table"
            else:
                text = V1.replace(f"\n[{section}]\n", f"\n[{section}]\n{key} = {VALUES[key]}\n", 1)
                yield section, key, text, f"key '{section}.{key}' is a {DATASET_FORMAT_2} key"


@pytest.mark.parametrize("section, key, text, words", list(_cases()), ids=[f"{c[0]}.{c[1]}" for c in _cases()])
def test_a_v2_key_in_a_v1_file_names_its_format(section, key, text, words):
    with pytest.raises(ConfigError) as err:
        rig_from_toml(text, "rig.toml")
    msg = str(err.value)
    assert msg == f'rig.toml: {words}: set format = "{DATASET_FORMAT_2}"'
    # The same document declaring /2 reads the key (a white template alone, say, is still refused there).
    try:
        rig_from_toml(text.replace(DATASET_FORMAT, DATASET_FORMAT_2, 1), "rig.toml")
    except ConfigError as exc:
        assert f"is a {DATASET_FORMAT_2}" not in str(exc), str(exc)


def test_the_first_v2_key_of_the_file_is_named_once(tmp_path):
    text = V1.replace("[lcd]\n", "[lcd]\ncover_glass_mm = 1.1\ncover_glass_index = 1.5\n", 1) \
        .replace("[camera]\n", "[camera]\nbit_shift = 0\n", 1)
    (tmp_path / "rig.toml").write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_rig(tmp_path)
    assert str(err.value) == (f"{tmp_path / 'rig.toml'}: key 'camera.bit_shift' is a {DATASET_FORMAT_2} key:"
                              f' set format = "{DATASET_FORMAT_2}"')


@pytest.mark.parametrize("value, words", [("67.5", 'a fractional one needs format = "ptp-dataset/2"'),
                                          ("64.0", "write 64")])
def test_a_float_period_in_a_v1_file_says_what_to_write(value, words):
    text = V1.replace("    64,\n", f"    {value},\n", 1)
    with pytest.raises(ConfigError, match=re.escape(f"key 'fringes.periods_px'[2] is {value}: a {DATASET_FORMAT}"
                                                    f" period is an integer ({words})")):
        rig_from_toml(text)
    assert rig_from_toml(text.replace(DATASET_FORMAT, DATASET_FORMAT_2, 1)).fringes.periods_px[2] == float(value)


def test_one_position_in_a_v1_file_names_v2():
    text = V1.replace(rig_to_toml(Rig()).split("z_mm = ")[1].split("]")[0] + "]", "[0.0]", 1)
    with pytest.raises(ConfigError, match=re.escape(f"got 1 (one position needs format = \"{DATASET_FORMAT_2}\")")):
        rig_from_toml(text)
    assert rig_from_toml(text.replace(DATASET_FORMAT, DATASET_FORMAT_2, 1)).stage.z_mm == (0.0,)
