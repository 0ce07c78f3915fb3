"""File menu commands: open, save, imports, exports, recent files."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from carapost.ops import labels as label_ops

from . import adapters

if TYPE_CHECKING:  # pragma: no cover
    from .main_window import MainWindow

log = logging.getLogger("carapost")

CARA_FILTER = "CaraPost projects (*.cara)"
SOURCE_FILTER = ("Camera files (*.pico *.avi *.mp4 *.mov *.mkv *.m4v *.webm *.wmv *.mpg *.mpeg);;"
                 "Pico files (*.pico);;All files (*)")


def open_project(w: "MainWindow") -> None:
    """File > Open (Ctrl+O)."""
    path = w.prompts.open_file("Open", f"{CARA_FILTER};;All files (*)", w.last_dir())
    if path:
        w.open_path(path)


def clear(w: "MainWindow") -> None:
    """File > Clear: close the current project (asking to save changes first)."""
    if w.maybe_save():
        w.doc.set_session(None)
        log.info("Project cleared")


def save(w: "MainWindow") -> None:
    """File > Save (Ctrl+S): a new project asks for a name."""
    w.save()


def save_as(w: "MainWindow") -> None:
    path = w.prompts.save_file("Save As", CARA_FILTER, w.default_save_path())
    if path:
        w.save(path)


def import_pico(w: "MainWindow") -> None:
    """File > Import Pico Files: one file stands for its whole take (``NAME_0..N.pico``);
    several files (or videos) are used as given. A ``NAME.xcp`` next to them is used as the
    calibration."""
    paths = w.prompts.open_files("Import Pico Files", SOURCE_FILTER, w.last_dir())
    if paths and w.maybe_save():
        w.import_sources(paths)


def import_brim_svg(w: "MainWindow") -> None:
    path = w.prompts.open_file("Import Calibration Brim [svg]", "SVG files (*.svg);;All files (*)", w.last_dir())
    if path:
        w.apply(adapters.ops("brim").import_brim_svg(w.doc.take, path))


def import_xcp(w: "MainWindow") -> None:
    from carapost.io.calibration import load_calibration

    path = w.prompts.open_file("Import XCP", "Calibrations (*.xcp *.qca *.toml);;All files (*)", w.last_dir())
    if path:
        w.apply(adapters.ops("calibrate").apply_calibration(w.doc.take, load_calibration(path)))


def import_labels_cara(w: "MainWindow") -> None:
    path = w.prompts.open_file("Import Labels From Cara File", CARA_FILTER, w.last_dir())
    if path:
        w.apply(label_ops.import_labels_from_cara(w.doc.take, path))


def import_labels_text(w: "MainWindow") -> None:
    path = w.prompts.open_file("Import Labels From Text File", "Label files (*.txt);;All files (*)", w.last_dir())
    if path:
        w.apply(label_ops.import_labels_from_text(w.doc.take, path))


def _export(w: "MainWindow", title: str, ext: str, **kwargs: object) -> None:
    from carapost.io.export import export_take

    path = w.prompts.save_file(title, f"{ext.upper()[1:]} files (*{ext})", w.default_save_path(ext))
    if not path:
        return
    if not path.lower().endswith(ext):
        path += ext
    take = w.doc.take
    selection = w.doc.selected_columns()

    def job(progress, cancel):  # type: ignore[no-untyped-def]
        export_take(take, path, selection=selection, **kwargs)
        return path

    w.run_job(title, job, lambda p, cancelled: log.info("%s: wrote %s", title, p))


def export_xcp(w: "MainWindow") -> None:
    _export(w, "Export XCP [Current Frame]", ".xcp", frame=w.doc.frame)


def export_c3d(w: "MainWindow") -> None:
    _export(w, "Export C3D", ".c3d")


def export_fbx(w: "MainWindow") -> None:
    _export(w, "Export FBX", ".fbx")


def clear_recent(w: "MainWindow") -> None:
    w.settings.clear_recent()
    w.refresh_recent_menu()


def exit_app(w: "MainWindow") -> None:
    w.close()


def open_recent(w: "MainWindow", path: str) -> None:
    if not Path(path).exists():
        log.error("%s: the file no longer exists", path)
        return
    if w.maybe_save():
        w.open_path(path, ask=False)
