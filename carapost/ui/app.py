"""Start the desktop application: ``carapost``, ``carapost gui [FILE]`` or
``python -m carapost.ui.app [FILE]``.

``FILE`` is a ``.cara`` project, or one ``.pico`` file of a take (the whole take is imported,
with ``NAME.xcp`` next to it as the calibration), or several camera files.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from PySide6.QtCore import QCoreApplication, Qt
from PySide6.QtGui import QColor, QPalette
from PySide6.QtWidgets import QApplication

from .settings import APP, ORG

__all__ = ["main", "apply_theme", "application"]


def apply_theme(app: QApplication) -> None:
    """The dark Fusion look of CaraPost (white text; warnings yellow and errors red read well)."""
    app.setStyle("Fusion")
    pal = QPalette()
    base, window, text = QColor(42, 44, 50), QColor(53, 55, 61), QColor(225, 225, 225)
    for role, colour in ((QPalette.ColorRole.Window, window), (QPalette.ColorRole.WindowText, text),
                         (QPalette.ColorRole.Base, base), (QPalette.ColorRole.AlternateBase, QColor(48, 50, 56)),
                         (QPalette.ColorRole.ToolTipBase, QColor(60, 62, 68)), (QPalette.ColorRole.ToolTipText, text),
                         (QPalette.ColorRole.Text, text), (QPalette.ColorRole.Button, window),
                         (QPalette.ColorRole.ButtonText, text), (QPalette.ColorRole.BrightText, QColor(255, 80, 80)),
                         (QPalette.ColorRole.Highlight, QColor(60, 110, 180)),
                         (QPalette.ColorRole.HighlightedText, QColor(255, 255, 255)),
                         (QPalette.ColorRole.Link, QColor(100, 160, 255))):
        pal.setColor(role, colour)
    for role in (QPalette.ColorRole.Text, QPalette.ColorRole.ButtonText, QPalette.ColorRole.WindowText):
        pal.setColor(QPalette.ColorGroup.Disabled, role, QColor(120, 120, 120))
    app.setPalette(pal)


def application(argv: Sequence[str] | None = None) -> QApplication:
    """The QApplication (created if needed) with the organisation names settings use."""
    QCoreApplication.setOrganizationName(ORG)
    QCoreApplication.setApplicationName(APP)
    app = QApplication.instance()
    if app is None:
        QApplication.setHighDpiScaleFactorRoundingPolicy(Qt.HighDpiScaleFactorRoundingPolicy.PassThrough)
        app = QApplication(list(argv) if argv is not None else [sys.argv[0]])
    return app  # type: ignore[return-value]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the GUI; ``argv`` are the arguments after the program name (files to open)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] in ("-h", "--help"):
        print(__doc__)
        return 0
    app = application([sys.argv[0]])
    apply_theme(app)
    from .main_window import MainWindow

    win = MainWindow()
    win.show()
    files = [a for a in args if not a.startswith("-")]
    if files:
        if len(files) == 1:
            win.open_path(files[0], ask=False)
        else:
            win.import_sources(files)
    return int(app.exec())


if __name__ == "__main__":
    raise SystemExit(main())
