"""Help menu commands."""

from __future__ import annotations

import logging
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QUrl
from PySide6.QtGui import QDesktopServices

if TYPE_CHECKING:  # pragma: no cover
    from .main_window import MainWindow

log = logging.getLogger("carapost")

ONLINE_HELP = "https://help.vicon.com/"
DOCS = Path(__file__).resolve().parents[2] / "docs" / "gui.md"
THIRD_PARTY = ("numpy", "scipy", "opencv-python-headless", "h5py", "hdf5plugin", "lxml", "ezc3d", "filterpy",
               "tqdm", "psygnal", "PySide6-Essentials", "shiboken6", "pyqtgraph", "av")


def version() -> str:
    try:
        return metadata.version("carapost")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a plain checkout
        return "0.0.0"


def online_help(w: "MainWindow") -> None:
    if not QDesktopServices.openUrl(QUrl(ONLINE_HELP)):
        log.warning("Could not open a web browser for %s", ONLINE_HELP)


def installed_help(w: "MainWindow") -> None:
    if not DOCS.exists():
        raise ValueError(f"{DOCS}: the installed help is missing")
    if not QDesktopServices.openUrl(QUrl.fromLocalFile(str(DOCS))):
        log.warning("Could not open %s", DOCS)
    log.info("Help: %s", DOCS)


def check_updates(w: "MainWindow") -> None:
    log.info("CaraPost for Python %s: this build never contacts the internet; see the project page for "
             "new releases", version())


def licensing(w: "MainWindow") -> None:
    w.prompts.info("Licensing", "CaraPost for Python is open source (Apache-2.0): no licence server or "
                                "activation is needed.")


def third_party_licenses(w: "MainWindow") -> None:
    lines = []
    for name in THIRD_PARTY:
        try:
            md = metadata.metadata(name)
        except metadata.PackageNotFoundError:
            continue
        lic = md.get("License-Expression") or md.get("License") or ""
        if not lic or len(lic) > 60:
            classifiers = [c.split("::")[-1].strip() for c in md.get_all("Classifier") or [] if c.startswith("License")]
            lic = ", ".join(classifiers) or (lic[:60] + "..." if lic else "see the package")
        lines.append(f"{name} {md.get('Version', '')}: {lic}")
    w.prompts.info("Third Party Licenses", "\n".join(lines))


def about(w: "MainWindow") -> None:
    w.prompts.info("About CaraPost for Python",
                   f"CaraPost for Python {version()}\n\nAn open re-implementation of Vicon CaraPost: "
                   "multi-camera facial motion capture from painted-marker video to labelled 3D data.\n\n"
                   "Licence: Apache-2.0.")
