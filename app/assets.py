"""Where the resources are: icons, default rigs and the stylesheet.

They live in the repository's ``resources/`` folder, installed as the package
``ptp_studio.resources``. Looked up, in order: a PyInstaller bundle
(``sys._MEIPASS/resources``), the installed package (wheel or editable
install), the folder beside ``app/`` in a source checkout.
"""

from __future__ import annotations

import sys
from functools import lru_cache
from pathlib import Path

__all__ = ["resource_dir", "icon_path", "default_rigs", "stylesheet"]


@lru_cache(maxsize=1)
def resource_dir() -> Path:
    """The folder holding ``style.qss``, ``icons/`` and ``rigs/``."""
    candidates = []
    bundle = getattr(sys, "_MEIPASS", None)
    if bundle:
        candidates.append(Path(bundle) / "resources")
    try:
        from importlib.resources import files

        candidates.append(Path(str(files("ptp_studio.resources"))))
    except (ImportError, ModuleNotFoundError, TypeError):
        pass
    candidates.append(Path(__file__).resolve().parent.parent / "resources")
    for c in candidates:
        if (c / "style.qss").is_file():
            return c
    raise FileNotFoundError("PTP Studio resources not found (looked in: "
                            + ", ".join(str(c) for c in candidates) + ")")


def icon_path(name: str) -> Path:
    """Path of ``icons/NAME.svg``."""
    return resource_dir() / "icons" / f"{name}.svg"


def default_rigs() -> dict[str, Path]:
    """The shipped ``rig.toml`` files by name (file stem), sorted."""
    return {p.stem: p for p in sorted((resource_dir() / "rigs").glob("*.toml"))}


def stylesheet() -> str:
    """The application's Qt stylesheet."""
    return (resource_dir() / "style.qss").read_text(encoding="utf-8")
