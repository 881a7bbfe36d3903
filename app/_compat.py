"""Work-arounds for known bugs of the Qt binding.

PySide6 6.12 on Python < 3.12: ``SignalInstance.emit()`` returns ``True``
without taking a reference to it, and other calls do the same with ``None``,
so every signal emitted from Python code (pyqtgraph emits thousands) drops a
reference until the interpreter aborts with "bool_dealloc: deallocating True
or False" or "none_dealloc". Python 3.12 made these singletons immortal and
PySide6 6.11 does not have the bug, so ``pyproject.toml`` requires PySide6 <
6.12 on Python < 3.12. For an environment that has 6.12 anyway, :func:`apply`
gives ``True``, ``False`` and ``None`` reference counts that the missing
references can never exhaust (they are never freed in any case).
"""

from __future__ import annotations

import ctypes
import sys
from importlib import metadata

__all__ = ["apply", "BROKEN_EMIT"]


def _pyside_version() -> str:
    for dist in ("PySide6-Essentials", "PySide6"):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            continue
    return ""


BROKEN_EMIT = sys.version_info < (3, 12) and _pyside_version().startswith("6.12") \
    and sys.implementation.name == "cpython"

_applied = False


def apply() -> None:
    """Apply the work-arounds this environment needs (idempotent)."""
    global _applied
    if _applied or not BROKEN_EMIT:
        return
    _applied = True
    # ob_refcnt is the first field of every CPython object (Py_ssize_t).
    for singleton in (True, False, None):
        ctypes.c_ssize_t.from_address(id(singleton)).value += 1 << 40
