"""The display's response measured in capture and the patterns generated through its inverse (issue 14)."""

from dataclasses import replace
import json

import numpy as np
import pytest

from ptpcore.capture import capture
from ptpcore.capture.devices import simulated_devices
from ptpcore.capture.sequence import STATE_FILE, display_from_means
from ptpcore.decode.harmonics import coherent_harmonic
from ptpcore.decode.patterns import display_inverse, display_response, fringe_profile
from ptpcore.errors import CaptureError
from ptpcore.io.dataset import read_image
from ptpcore.rig import load_rig
from ptpcore.rig.rigfile import Display
from ptpcore.simulate import scaled_preset

GAMMA = 1.3


def test_inverse_makes_the_measured_luminance_linear():
    levels = np.arange(0, 256, 16.0).tolist() + [255.0]
    disp = Display(tuple(levels), tuple((np.asarray(levels) / 255.0) ** GAMMA))
    g = np.linspace(0, 255, 1001)
    lv = display_inverse(disp, g)
    assert np.all(np.diff(lv) >= 0) and lv[0] == 0 and lv[-1] == 255
    # PCHIP through 17 points of x**1.3: the luminance of the inverse is linear within 0.2 % of full scale.
    assert np.max(np.abs(display_response(disp, lv) - g / 255)) < 1e-6  # its 4096-point inverse table
    assert np.max(np.abs((lv / 255) ** GAMMA - g / 255)) < 2e-3
    # The rig's [display] replaces [fringes] gamma in the displayed levels.
    rig, _ = scaled_preset("mild", 48)
    f = replace(rig.fringes, gamma=2.2)
    plain = fringe_profile(rig.lcd, f, "x", 213, 0, 8, 0.0)
    through = fringe_profile(rig.lcd, f, "x", 213, 0, 8, 0.0, disp)
    want = np.rint(display_inverse(disp, np.clip(f.offset + f.amplitude * np.cos(
        2 * np.pi * np.arange(rig.lcd.width) / 213 + f.origin("x")), 0, 255)))
    assert np.array_equal(through, want) and not np.array_equal(plain, through)
    with pytest.raises(CaptureError, match="does not see the LCD"):
        display_from_means([0, 255], [10.0, 10.0])


def _capture(tmp_path, name, measure, rig, settings):
    out = tmp_path / name
    result = capture(out, rig, *simulated_devices(rig, settings, 3), measure_display=measure)
    return out, result


def test_capture_measures_the_response_and_its_inverse_removes_the_harmonics(tmp_path):
    """A display of gamma 1.3, patterns not pre-compensated: the ramp gives the true curve within 3
    standard errors of the camera means' noise (3.5 for 15 levels); the patterns through its inverse carry a 2nd harmonic
    below the camera noise, without it the harmonic is above."""
    rig, s = scaled_preset("mild", 96, positions=2)
    rig = replace(rig, fringes=replace(rig.fringes, gamma=1.0))
    s = replace(s, display_gamma=GAMMA, lcd_black=0.01)  # a black level above the camera's 0: no clipping
    out, result = _capture(tmp_path, "measured", True, rig, s)
    r = load_rig(out)
    assert r.display is not None and r.display == result.rig.display
    lv, lum = np.asarray(r.display.levels), np.asarray(r.display.luminance)
    true = (lv / 255.0) ** GAMMA  # (black + (1 - black) x**g - black) / (1 - black)
    state = json.loads((out / STATE_FILE).read_text())
    means, n = np.asarray(state["display"]["camera_means"]), state["display"]["camera_pixels"]
    assert np.allclose(means, result.display_means) and n > 0.5 * rig.camera.width * rig.camera.height
    sig = s.noise_dn(rig.camera, means) / np.sqrt(n)  # standard error of each mean (grey levels)
    span = means[-1] - means[0]
    se = np.sqrt(sig ** 2 + ((1 - true) * sig[0]) ** 2 + (true * sig[-1]) ** 2) / span
    # Each of the 15 inner levels within 3.5 standard errors (Bonferroni: 0.7 % false alarms in all).
    assert np.all(np.abs(lum - true) < 3.5 * se + 1e-12), np.max(np.abs(lum - true) / se)
    out_plain, _ = _capture(tmp_path, "plain", False, rig, s)
    assert load_rig(out_plain).display is None
    f = r.fringes
    t, big_n = f.periods_px[-1], f.steps[-1]
    for folder, below in ((out, True), (out_plain, False)):
        rr = load_rig(folder)
        for d in ("x", "y"):
            frames = [read_image(folder / rr.image_name(0, d, t, st, big_n), rr) for st in range(big_n)]
            h2 = np.nanmedian(coherent_harmonic(frames, 2, 8)["amplitude"])
            noise = float(s.noise_dn(rig.camera, np.mean(frames)))
            assert (h2 < noise) == below, (folder.name, d, h2, noise)


def test_a_resumed_capture_keeps_the_response_it_measured(tmp_path):
    from ptpcore.errors import Cancelled

    rig, s = scaled_preset("mild", 48, positions=3)
    rig = replace(rig, fringes=replace(rig.fringes, gamma=1.0))
    s = replace(s, display_gamma=GAMMA)

    def stop(_f, message):
        if message.startswith(("position 1 ", "position 1,")):  # the second position
            raise Cancelled("cancelled")

    out = tmp_path / "cap"
    with pytest.raises(Cancelled):
        capture(out, rig, *simulated_devices(rig, s, 3), measure_display=True, progress=stop)
    state = json.loads((out / STATE_FILE).read_text())
    first = Display(tuple(state["display"]["levels"]), tuple(state["display"]["luminance"]))
    result = capture(out, rig, *simulated_devices(rig, replace(s, display_gamma=2.0), 3), resume=True,
                     measure_display=True)
    assert result.kept == [0] and result.rig.display == first == load_rig(out).display  # not measured again
    assert np.allclose(result.display_means, state["display"]["camera_means"])
