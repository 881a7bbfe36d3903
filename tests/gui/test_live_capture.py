"""Live capture in the wizard with simulated devices, and the LCD window, headless."""

from __future__ import annotations

import filecmp

import numpy as np
import pytest
from gui_helpers import run_job

from ptpcore.capture import capture, capture_state
from ptpcore.capture.devices import SimulatedCamera, SimulatedStage
from ptpcore.errors import DeviceError
from ptpcore.rig import load_rig
from ptpcore.simulate import VirtualRig, scaled_preset, simulate_dataset
from ptp_studio.lcd_window import LcdWindow, QtDisplay, list_screens, screen_mismatch
from ptp_studio.worker import Job


def go_live(wizard, folder):
    """Rig page: choose live capture; on to the Acquire page; simulated devices, no settle, into ``folder``."""
    rig_page = wizard.page_by_key["rig"]
    rig_page.src_live.setChecked(True)
    s = wizard.model.session
    assert s.source_kind == "live" and wizard.next_blocker() is None
    assert rig_page.cam_w.isEnabled() and rig_page.sim_box.isEnabled()  # the rig describes the hardware
    wizard.next()
    assert wizard.page_by_key["fringes"].periods.isEnabled()  # a live capture shows the patterns it designs
    wizard.next()
    acq = wizard.page_by_key["acquire"]
    assert acq.live.isVisible() and not acq.write_check.isVisible()
    assert acq.start_button.text() == "Start live capture"
    acq.live.settle.setValue(0)
    acq.live.set_folder(folder)
    assert s.dataset_folder == folder and "live capture into" in acq.source_label.text()
    return acq


def same_images(a, b) -> bool:
    names = sorted(p.relative_to(a) for p in a.rglob("*.png"))
    return bool(names) and names == sorted(p.relative_to(b) for p in b.rglob("*.png")) and all(
        filecmp.cmp(a / n, b / n, shallow=False) for n in names)


def test_live_capture_with_simulated_devices(wizard, qtbot, tmp_path):
    acq = go_live(wizard, tmp_path / "cap")
    s = wizard.model.session
    assert wizard.next_blocker() == "Acquire the images first: press Start live capture."
    frames = []
    job = acq.start()
    job.partial.connect(lambda p: frames.append(p[0]))
    assert run_job(qtbot, job) == "finished", acq.jobs.error.text()
    assert s.samples is not None and s.samples.x.shape == (9, 120, 160)
    assert s.truth is not None
    assert all(st.state == "done" for st in s.positions)
    assert {"start", "captured", "frame", "exposure", "position"} <= set(frames)
    assert acq.live.exposure_label.text().startswith("Exposure check: exposure ok")
    assert wizard.next_blocker() is None
    # The folder is the dataset `ptp simulate` writes with the same settings, bit for bit.
    simulate_dataset(tmp_path / "sim", s.rig, s.sim_settings, s.seed)
    assert same_images(tmp_path / "sim", tmp_path / "cap")
    assert load_rig(tmp_path / "cap") == s.rig
    assert capture_state(tmp_path / "cap")["complete"]
    assert "complete capture" in acq.live.folder_state.text()
    # The phase-map page decodes from the captured folder.
    assert s.make_source().folder == tmp_path / "cap"


def test_live_capture_cancel_then_resume(wizard, qtbot, tmp_path):
    acq = go_live(wizard, tmp_path / "cap")
    s = wizard.model.session
    job = acq.start()

    def cancel_after_two(payload):
        if payload[0] == "captured" and payload[1] == 1:
            acq.jobs.cancel()

    job.partial.connect(cancel_after_two)
    assert run_job(qtbot, job) == "cancelled"
    assert "cancelled" in wizard.next_blocker()
    st = capture_state(tmp_path / "cap")
    assert st["done"] >= 2 and not st["complete"]
    assert "partial capture" in acq.live.folder_state.text() and "Resume" in acq.live.folder_state.text()
    # Without Resume the folder is refused with the reason; with it the capture goes on.
    assert run_job(qtbot, acq.start()) == "errored"
    assert "holds a partial capture" in acq.jobs.error.text()
    acq.live.resume_check.setChecked(True)
    job = acq.start()
    kept = []
    job.partial.connect(lambda p: p[0] == "kept" and kept.append(p[1]))
    assert run_job(qtbot, job) == "finished", acq.jobs.error.text()
    assert kept == list(range(st["done"]))
    assert s.samples is not None and wizard.next_blocker() is None
    simulate_dataset(tmp_path / "sim", s.rig, s.sim_settings, s.seed)
    assert same_images(tmp_path / "sim", tmp_path / "cap")


def test_live_capture_with_a_manual_stage(wizard, qtbot, tmp_path):
    acq = go_live(wizard, tmp_path / "cap")
    s = wizard.model.session
    planned = s.rig.stage.z_mm
    acq.live.stage_combo.setCurrentIndex(acq.live.stage_combo.findData("manual"))
    assert s.live.stage == "manual"
    job = acq.start()
    asked = []

    def answer(dialog):
        asked.append(dialog.reading.value())
        dialog.reading.setValue(dialog.reading.value() + 0.003)  # the engineer reads 3 µm more
        dialog.accept()

    acq.asker.dialogOpened.connect(answer)
    assert run_job(qtbot, job) == "finished", acq.jobs.error.text()
    assert asked == pytest.approx(list(planned))
    assert s.rig.stage.z_mm == pytest.approx([z + 0.003 for z in planned])  # the readings, not the plan
    assert load_rig(tmp_path / "cap").stage.z_mm == s.rig.stage.z_mm
    assert s.samples is not None and [st.z_mm for st in s.positions] == pytest.approx(list(s.rig.stage.z_mm))


def test_cancel_while_the_dialog_waits(wizard, qtbot, tmp_path):
    acq = go_live(wizard, tmp_path / "cap")
    acq.live.stage_combo.setCurrentIndex(acq.live.stage_combo.findData("manual"))
    job = acq.start()
    with qtbot.waitSignal(acq.asker.dialogOpened, timeout=20000) as blocker:
        pass
    dialog = blocker.args[0]
    assert dialog.isVisible()
    acq.jobs.cancel()
    assert run_job(qtbot, job) == "cancelled"
    qtbot.waitUntil(lambda: acq.asker.dialog is None)


def test_bad_device_settings_reach_the_page(wizard, qtbot, tmp_path):
    acq = go_live(wizard, tmp_path / "cap")
    acq.live.stage_combo.setCurrentIndex(acq.live.stage_combo.findData("serial"))
    assert acq.start() is None
    assert "needs a capture.toml with a [stage.serial] table" in acq.jobs.error.text()
    assert "failed" in wizard.next_blocker()
    acq.live.stage_combo.setCurrentIndex(acq.live.stage_combo.findData("sim"))
    acq.live.exposure.setValue(60_000)  # 6x the nominal: saturates
    assert run_job(qtbot, acq.start()) == "errored"
    assert "overexposed" in acq.jobs.error.text() and "nothing is captured yet" in acq.jobs.error.text()
    assert "overexposed" in acq.live.exposure_label.text()


# --------------------------------------------------------------------------- the LCD window

def test_screens_are_listed_with_their_resolution(wizard):
    screens = list_screens()
    assert screens and screens[0].width > 0 and screens[0].height > 0
    lcd = wizard.model.session.rig.lcd
    assert "is not the rig's LCD (3840x2160 px in rig.toml)" in screen_mismatch(screens[0], lcd)
    acq = wizard.page_by_key["acquire"]
    assert acq.live.screen_combo.count() == 1 + len(screens)
    acq.live.screen_combo.setCurrentIndex(1)
    assert wizard.model.session.live.screen == 0
    assert "is not the rig's LCD" in acq.live.screen_warning.text()


def test_lcd_window_shows_images_pixel_for_pixel(qtbot):
    info = list_screens()[0]
    display = QtDisplay(0, info.width, info.height, settle_s=0.0)
    win = display.window
    qtbot.addWidget(win)
    display.open()
    qtbot.waitExposed(win)
    assert win.isFullScreen() and not (win.windowFlags() & ~win.windowFlags() & 0)
    assert win.size().width() * win.devicePixelRatioF() == info.width
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (info.height, info.width), dtype=np.uint8)
    display.show(image)
    shot = win.grab().toImage()
    assert (shot.width(), shot.height()) == (info.width, info.height)
    got = np.array([[shot.pixelColor(c, r).red() for c in range(0, info.width, 37)]
                    for r in range(0, info.height, 41)])
    assert np.array_equal(got, image[::41, ::37])  # no scaling, no smoothing
    with pytest.raises(ValueError, match="uint8 image"):
        display.show(image[:-1])
    display.close()
    assert not win.isVisible()
    with pytest.raises(DeviceError, match="no screen 5"):
        LcdWindow(4)


def test_a_capture_through_the_lcd_window(qtbot, tmp_path):
    """The simulated camera photographs what the Qt window shows, from the worker thread: same dataset."""
    rig, settings = scaled_preset("mild", 32, positions=2)
    simulate_dataset(tmp_path / "sim", rig, settings, seed=4)
    display = QtDisplay(0, rig.lcd.width, rig.lcd.height, settle_s=0.0)
    qtbot.addWidget(display.window)
    stage = SimulatedStage()
    camera = SimulatedCamera(VirtualRig(rig, settings, 4), display, stage)
    job = Job(lambda ctx: capture(tmp_path / "cap", rig, camera, stage, display, progress=ctx.progress), "capture")
    with qtbot.waitSignal(job.done, timeout=60000):
        job.start()
    assert job.outcome == "finished", job.error
    assert display.shown == 2 + 2 * rig.fringes.frames_per_position and display.window.serial == display.shown
    assert not display.window.isVisible()
    assert same_images(tmp_path / "sim", tmp_path / "cap")


def test_live_capture_measures_the_display_response(wizard, qtbot, tmp_path):
    """Issue 14: the Acquire page's switch measures the display's response; the curve is plotted and
    the dataset's rig.toml carries it as [display]."""
    acq = go_live(wizard, tmp_path / "cap")
    s = wizard.model.session
    assert not acq.live.display_plot.isVisibleTo(acq.live)
    acq.live.display_check.setChecked(True)
    assert s.live.measure_display
    frames = []
    job = acq.start()
    job.partial.connect(lambda p: frames.append(p[0]))
    assert run_job(qtbot, job) == "finished", acq.jobs.error.text()
    assert "display" in frames
    disp = load_rig(tmp_path / "cap").display
    assert disp is not None and s.rig.display == disp
    x, y = acq.live.display_curve.getData()
    assert np.allclose(x, disp.levels) and np.allclose(y, disp.luminance)
    assert acq.live.display_plot.isVisibleTo(acq.live)
    # plumbing: the preset's display response is what was measured (its noise is checked in test_display_response)
    g = s.sim_settings.display_gamma
    black = s.sim_settings.lcd_black
    true = (black + (1 - black) * (np.asarray(disp.levels) / 255) ** g - black) / (1 - black)
    assert np.max(np.abs(np.asarray(disp.luminance) - true)) < 0.01
