"""PTP Studio: the calibration wizard (PySide6 + pyqtgraph) over the ``ptpcore`` engine.

The source lives in the repository's ``app/`` folder and installs under the
import name ``ptp_studio`` (``pyproject.toml`` maps it). Layers:

- :mod:`ptp_studio.session` — the one session model every page sees (a plain
  object) and its thin Qt wrapper that emits change signals;
- :mod:`ptp_studio.worker` — the one worker pattern for every long job;
- :mod:`ptp_studio.sessionfile` — session files (``ptp-session/1``): open, save, autosave;
- :mod:`ptp_studio.widgets` — heatmaps, image views, the job panel;
- :mod:`ptp_studio.pages` — the wizard's pages, one module each;
- :mod:`ptp_studio.wizard` — the wizard window;
- :mod:`ptp_studio.tour` — ``ptp-studio --tour OUTDIR``.
"""

__version__ = "0.1.0"

from . import _compat  # noqa: E402

_compat.apply()
