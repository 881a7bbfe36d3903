"""The wizard as a person sees it: each screen size under Xvfb, every page walked with real X events.

    python -m benchmarks.gui_walk OUT_DIR [--sizes 1366x768,1920x1080,1536x864] [--camera 96x72] [--positions 9]

For each size an X server (Xvfb) of that size is started and the real wizard (``StudioWizard`` with the
application's look, ``configure_app``, on the xcb platform) is walked by :func:`ptp_studio.tour.run_tour`,
its buttons pressed with xdotool (mouse clicks and keys the X server delivers as it would a person's). At
every page it writes the screen (``import -window root``: what is on the X screen, not a widget's own
rendering) and checks what a program can (:mod:`ptp_studio.layoutcheck`): the main view's share of the
window (at least half) and that it is whole in view, no horizontal scroll bar, no label, header or plot
title cut. It prints one table row per page and exits 1 when a check fails, 2 when a tool is missing.

1536x864 is 1920x1080 at 125 % scaling in logical pixels: the X screen is made that size (Qt then lays the
window out exactly as on a scaled 1920x1080 screen; ``QT_SCALE_FACTOR=1.25`` on a 1920x1080 screen gives
the same logical size with blurrier screenshots).

Needs: Xvfb, xdotool, ImageMagick's ``import`` (Debian/Ubuntu: ``apt-get install xvfb xdotool imagemagick``)
and Qt's xcb libraries (``libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1 ...``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

SIZES = ("1366x768", "1920x1080", "1536x864")
TOOLS = ("Xvfb", "xdotool", "import")


class XDriver:
    """Presses the wizard's buttons with xdotool: real X pointer and key events (see ``QtDriver``)."""

    def _xdo(self, *args: str) -> None:
        subprocess.run(["xdotool", *args], check=True, timeout=30)

    def click(self, widget) -> None:
        from ptp_studio.tour import settle

        p = widget.mapToGlobal(widget.rect().center())
        self._xdo("mousemove", "--sync", str(p.x()), str(p.y()), "click", "1")
        settle(150)

    def choose(self, combo, index: int) -> None:
        """Open the combo's list with a click, then Home, Down ``index`` times, Return."""
        from ptp_studio.tour import settle

        self.click(combo)
        settle(200)
        self._xdo("key", "Home", *(["Down"] * index), "Return")
        settle(150)

    def click_at(self, widget, point) -> None:
        """A left click at ``point`` in ``widget``'s coordinates."""
        from ptp_studio.tour import settle

        p = widget.mapToGlobal(point)
        self._xdo("mousemove", "--sync", str(p.x()), str(p.y()), "click", "1")
        settle(150)

    def drag(self, widget, start, end, steps: int = 8) -> None:
        """Button 1 down at ``start``, moved to ``end`` in ``steps`` moves, released (widget coordinates)."""
        from ptp_studio.tour import settle

        a, b = widget.mapToGlobal(start), widget.mapToGlobal(end)
        self._xdo("mousemove", "--sync", str(a.x()), str(a.y()), "mousedown", "1")
        settle(100)
        for i in range(1, steps + 1):
            x, y = a.x() + (b.x() - a.x()) * i // steps, a.y() + (b.y() - a.y()) * i // steps
            self._xdo("mousemove", "--sync", str(x), str(y))
            settle(30)
        self._xdo("mouseup", "1")
        settle(150)

    def set_slider(self, slider, value: int) -> None:
        """A click on the slider (it takes the focus), then the keys Home and Right ``value`` times."""
        from ptp_studio.tour import settle

        self.click(slider)
        self._xdo("key", "Home", *(["Right"] * value))
        settle(150)

    def type_text(self, line_edit, text: str) -> None:
        from ptp_studio.tour import settle

        self.click(line_edit)
        self._xdo("key", "ctrl+a")
        self._xdo("type", "--delay", "2", text)
        self._xdo("key", "Tab")
        settle(150)


def _child(out: Path, camera: tuple[int, int], positions: int) -> int:
    """Inside the X server: walk the wizard, screenshot and check every page (``layout.json``)."""
    from PySide6.QtWidgets import QApplication

    from ptp_studio.layoutcheck import check_page
    from ptp_studio.tour import run_tour, settle, tour_size
    from ptp_studio.wizard import configure_app

    app = QApplication(sys.argv[:1])
    configure_app(app)
    rows = []

    def on_page(name: str, wiz) -> None:
        wiz.raise_()
        wiz.activateWindow()
        settle(200)
        screen = out / f"screen-{len(rows) + 1:02d}-{name}.png"
        subprocess.run(["import", "-window", "root", str(screen)], check=True, timeout=60)
        r = check_page(wiz.currentPage(), wiz)
        rows.append({"shot": name, "page": r.page, "view_share": r.view_share, "view_inside": r.view_inside,
                     "problems": r.problems, "window": [wiz.width(), wiz.height()], "screenshot": str(screen)})

    size = tour_size()
    run_tour(out, camera[0], camera[1], positions, log=lambda *_: None, driver=XDriver(), size=size,
             on_page=on_page)
    (out / "layout.json").write_text(json.dumps({"size": [size.width(), size.height()], "pages": rows}, indent=1))
    return 0


def _free_display() -> int:
    for n in range(90, 200):
        if not Path(f"/tmp/.X11-unix/X{n}").exists() and not Path(f"/tmp/.X{n}-lock").exists():
            return n
    raise RuntimeError("no free X display number between :90 and :199")


def walk_size(out: Path, size: str, camera: str, positions: int, timeout: float = 1800) -> dict:
    """Start Xvfb at ``size``, walk the wizard in it (a child process), stop Xvfb; the layout report."""
    out.mkdir(parents=True, exist_ok=True)
    n = _free_display()
    xvfb = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{size}x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 30
        while not Path(f"/tmp/.X11-unix/X{n}").exists():
            if xvfb.poll() is not None or time.monotonic() > end:
                raise RuntimeError(f"Xvfb :{n} did not start")
            time.sleep(0.1)
        env = dict(os.environ, DISPLAY=f":{n}", QT_QPA_PLATFORM="xcb")
        env.pop("QT_SCALE_FACTOR", None)
        cmd = [sys.executable, "-m", "benchmarks.gui_walk", str(out), "--child", "--camera", camera,
               "--positions", str(positions)]
        done = subprocess.run(cmd, env=env, timeout=timeout, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"the walk at {size} failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
        return json.loads((out / "layout.json").read_text())
    finally:
        xvfb.terminate()
        xvfb.wait(10)


def table(size: str, report: dict) -> tuple[list[str], int]:
    """The report as text lines and the number of failed checks."""
    lines = [f"{size} (window {report['pages'][0]['window'][0]}x{report['pages'][0]['window'][1]})"
             if report["pages"] else size,
             f"  {'screenshot':<24} {'view':>6}  problems"]
    failed = 0
    for row in report["pages"]:
        share = "-" if row["view_share"] is None else f"{100 * row['view_share']:.0f} %"
        lines.append(f"  {row['shot']:<24} {share:>6}  {'; '.join(row['problems']) or 'ok'}")
        failed += len(row["problems"])
    return lines, failed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.gui_walk", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="folder of the screenshots, one subfolder per size")
    ap.add_argument("--sizes", default=",".join(SIZES), help=f"screen sizes (default {','.join(SIZES)})")
    ap.add_argument("--camera", default="96x72", help="simulated camera WxH (default 96x72: seconds per fit)")
    ap.add_argument("--positions", type=int, default=9, help="stage positions (default 9)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    try:
        camera = tuple(int(v) for v in args.camera.lower().split("x"))
        sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
        for s in sizes:
            w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        print(f"gui_walk: sizes and camera are WIDTHxHEIGHT, got --sizes {args.sizes!r} --camera {args.camera!r}",
              file=sys.stderr)
        return 2
    if args.child:
        return _child(args.out, camera, args.positions)
    missing = [t for t in TOOLS if shutil.which(t) is None]
    if missing:
        print(f"gui_walk: {', '.join(missing)} not found (Debian/Ubuntu: apt-get install xvfb xdotool imagemagick)",
              file=sys.stderr)
        return 2
    failed = 0
    for s in sizes:
        report = walk_size(args.out / s, s, args.camera, args.positions)
        lines, n = table(s, report)
        print("\n".join(lines), flush=True)
        failed += n
    print(f"{failed} failed checks" if failed else "every check passed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
