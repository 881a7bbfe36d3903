"""Which phase conventions the data cannot tell apart (issue 32, METHOD.md section 4).

Analytic phase maps (no rendering): the wrapped phases a camera would see of a known LCD
coordinate field, shown with a true convention and decoded with the rig's. The set the
check lists is compared with the set METHOD.md section 4 states, computed here on its own:
a wrong origin ``g`` hides exactly when ``(r_j - 1) g = 0 (mod 2 pi)`` at every level, a wrong
shift sign (origin negated) never shows in unwrapping, and of those the members whose
coordinates stay on the LCD remain.
"""

import math
from functools import reduce

import numpy as np
import pytest

from ptpcore.decode.patterns import design_check
from ptpcore.decode.phase import DecodedPosition, DirectionDecode, WrappedPhase, apply_convention
from ptpcore.rig.rigfile import rig_from_toml
from ptpcore.run.diagnose import convention_check

W = 1000  # LCD width, px
T0 = 1024.0  # coarsest period: covers the LCD (METHOD.md section 4)
SHAPE = (40, 60)  # 2400 pixels: all of them sampled by the check (CHECK_PIXELS = 4000)

# name -> the period ratios of consecutive levels (coarse to fine)
DESIGNS = {"r2": (2, 2), "r3": (3, 3), "r4": (4, 4), "r5": (5, 5), "r8": (8, 8), "mixed": (3, 5)}
# wrong origins: pi, 2 pi m / N (m = 1, N = 3; m = 1, N = 4), a random value
WRONG = {"pi": math.pi, "2pi/3": 2 * math.pi / 3, "2pi/4": math.pi / 2,
         "random": float(np.random.default_rng(32).uniform(0, 2 * math.pi))}
# the part of the LCD the camera sees: a third of it (several sets stay on the LCD), or nearly all
FIELDS = {"narrow": (300.0, 620.0), "wide": (3.0, 996.0)}


def _periods(ratios):
    ps = [T0]
    for r in ratios:
        ps.append(ps[-1] / r)
    return ps


def _rig(periods):
    text = f'''format = "ptp-dataset/2"
[camera]
width = {SHAPE[1]}
height = {SHAPE[0]}
[lcd]
width = {W}
height = 800
pitch_mm = [0.1, 0.1]
[stage]
z_mm = [0.0]
[fringes]
directions = ["x"]
periods_px = {[float(p) for p in periods]!r}
steps = 4
'''
    return rig_from_toml(text)


def _field(lo, hi):
    """(H, W) LCD coordinate u a camera sees: a slightly perspective ramp from ``lo`` to ``hi``."""
    rows, cols = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(float)
    x, y = cols / (SHAPE[1] - 1), rows / (SHAPE[0] - 1)
    return lo + (hi - lo) * (x + 0.02 * x * y) / 1.02


def _position(rig, u, true_sign, true_origin):
    """The decoded position the pipeline would make of the frames: N-step phases of patterns
    shown with ``(true_sign, true_origin)``, the rig's convention then applied."""
    f = rig.fringes
    wrapped = []
    for t in f.periods("x"):
        theta = 2 * np.pi * u / t
        raw = np.angle(np.exp(1j * true_sign * (theta + true_origin)))  # the N-step estimate
        wp = WrappedPhase(raw.astype(np.float32), np.full(u.shape, 100.0, np.float32),
                          np.full(u.shape, 127.0, np.float32), np.zeros(u.shape, bool))
        wrapped.append(apply_convention(wp, f.sign("x"), f.origin("x")))
    dec = DirectionDecode(np.zeros(u.shape), wrapped, np.zeros(u.shape, bool), None, tuple(f.periods("x")))
    return DecodedPosition(0, 0.0, None, None, np.zeros(u.shape, np.uint8), {"x": dec})


def _method_set(ratios, u, true_sign, true_origin):
    """METHOD.md section 4's set, less those whose coordinates leave the LCD (analytic)."""
    d = reduce(math.gcd, [r - 1 for r in ratios])
    hidden = [2 * math.pi * k / d for k in range(d)]
    out = []
    for g in hidden:
        for sign, origin, coord in (
                (true_sign, true_origin - g, np.mod(u + T0 * g / (2 * np.pi), T0)),   # shifted map
                (-true_sign, -true_origin - g, np.mod(-u + T0 * g / (2 * np.pi), T0))):  # mirrored map
            inside = np.mean((coord >= -0.5) & (coord <= W - 0.5))
            if inside >= 0.99:  # the check's criterion: as consistent as the best within 1 point
                out.append((sign, origin))
    return out


def _same_set(a, b, tol_deg=0.5):
    """The same conventions (origins within ``tol_deg``: the check refines them to 0.05 degree)."""
    def close(m, n):
        return m[0] == n[0] and abs(math.remainder(m[1] - n[1], 2 * math.pi)) < math.radians(tol_deg)
    return (len(a) == len(b) and all(any(close(m, n) for n in b) for m in a)
            and all(any(close(m, n) for m in a) for n in b))


@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("wrong_sign", [False, True])
@pytest.mark.parametrize("wrong", WRONG)
@pytest.mark.parametrize("design", DESIGNS)
def test_the_listed_set_is_the_set_the_data_cannot_tell_apart(design, wrong, wrong_sign, field):
    ratios = DESIGNS[design]
    rig = _rig(_periods(ratios))  # configured: shift_sign = 1, phase_origin_rad = 0
    true_sign, true_origin = (-1 if wrong_sign else 1), WRONG[wrong]
    u = _field(*FIELDS[field])
    expected = _method_set(ratios, u, true_sign, true_origin)
    assert any(_same_set([m], [(true_sign, true_origin)]) for m in expected)  # the truth is always in it
    findings = convention_check(rig, _position(rig, u, true_sign, true_origin))
    configured_hidden = any(_same_set([m], [(1, 0.0)]) for m in expected)
    if configured_hidden:
        # The wrong configured convention decodes as consistently: a warning lists the whole set.
        assert len(expected) > 1
        assert len(findings) == 1 and not findings[0].fatal
    else:
        assert len(findings) == 1 and findings[0].fatal
    fd = findings[0]
    assert _same_set(fd.conventions, expected), (fd.conventions, expected)
    msg = fd.message()
    assert len(fd.candidates) == len(expected)
    if len(expected) == 1:
        # one member: the fix itself, named as the setting
        assert fd.conventions[0][0] == true_sign
        assert abs(math.remainder(fd.conventions[0][1] - true_origin, 2 * math.pi)) < math.radians(0.5)
        assert "set it" in msg and "cannot tell" not in msg
    else:
        assert f"{len(expected)} " in msg and "cannot tell them apart" in msg
        # the reason and the design change that would tell: origins (a ratio-2 level), mirrors (more of the LCD)
        assert ("ratio to the coarser one is 2" in msg) == any(
            sum(m[0] == s for m in expected) > 1 for s in (1, -1))
        assert ("mirrors the map" in msg) == (len({m[0] for m in expected}) > 1)
        for i in range(len(expected)):
            assert f"({i + 1}) " in msg


def test_the_right_convention_alone_gives_no_finding():
    for ratios in DESIGNS.values():
        rig = _rig(_periods(ratios))
        assert convention_check(rig, _position(rig, _field(*FIELDS["wide"]), 1, 0.0)) == []


@pytest.mark.parametrize("design,hidden_degrees", [("r2", []), ("r3", [180]), ("r4", [120, 240]),
                                                   ("r5", [90, 180, 270]), ("mixed", [180])])
def test_the_design_check_names_the_hidden_origins_before_capture(design, hidden_degrees):
    rig = _rig(_periods(DESIGNS[design]))
    items = [i for i in design_check(rig).items if i.name == "convention check x"]
    assert len(items) == 1
    msg = items[0].message
    if hidden_degrees:
        assert "phase_origin_rad wrong by " + ", ".join(str(h) for h in hidden_degrees) + " degrees" in msg
    else:
        assert "wrong by" not in msg
    assert "shift_sign" in msg and "ratio to the coarser one is 2" in msg
    # the widest view that cannot tell: mirrored about T0 / 2, 2 W - T0 px of the LCD
    assert items[0].value == pytest.approx(max([2 * W - T0] + [W - min(T0 * h / 360, T0 - T0 * h / 360)
                                                               for h in hidden_degrees]))
