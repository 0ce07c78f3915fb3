"""Every pane and every view kind renders a non-empty image (``QWidget.grab()``), with data."""

import numpy as np
import pytest

from uihelpers import inject_truth


def image_stats(widget):
    """(width, height, number of distinct colours) of a widget's rendering."""
    from PySide6.QtGui import QImage

    img = widget.grab().toImage().convertToFormat(QImage.Format.Format_RGB32)
    w, h = img.width(), img.height()
    ptr = img.constBits()
    arr = np.frombuffer(ptr, np.uint32, count=img.bytesPerLine() // 4 * h).reshape(h, -1)[:, :w]
    return w, h, len(np.unique(arr))


@pytest.fixture
def populated(qtbot, loaded, tiny_files):
    synth, _ = tiny_files
    inject_truth(loaded, synth, markers=8)
    take = loaded.doc.take
    loaded.doc.select([int(take.points.ids[0])])
    take.labels = ["Chin", "Nose", "Brow"]
    take.points.labels[0] = "Chin"
    loaded.doc.notify_take_changed()
    return loaded


def test_panes_render(qtbot, populated):
    w = populated
    for key, dock in w.docks.items():
        dock.show()
        dock.raise_()
        qtbot.wait(1)
        width, height, colours = image_stats(dock.widget())
        assert width > 20 and height > 20, key
        assert colours > 2, f"pane {key} rendered blank"


@pytest.mark.parametrize("kind", ["sensor", "3d", "graph", "continuity"])
def test_views_render(qtbot, populated, kind):
    w = populated
    w.workspace.set_layout(1)
    slot = w.workspace.slots[0]
    view = slot.set_view(kind, 1)
    qtbot.wait(1)
    width, height, colours = image_stats(view)
    assert width > 100 and height > 80
    assert colours > 8, f"{kind} view rendered blank"


def test_views_without_take_render(qtbot, window):
    for kind in ("sensor", "3d", "graph", "continuity"):
        view = window.workspace.slots[0].set_view(kind, 0)
        width, height, colours = image_stats(view)
        assert width > 50 and colours >= 2


def test_floating_workspace_and_brim_svg(qtbot, populated):
    w = populated
    fw = w.new_floating_workspace()
    qtbot.waitExposed(fw)
    assert fw.workspace.slots[0].kind == "3d"
    assert image_stats(fw)[2] > 8
    w.actions["process.brim_v20"].trigger()
    assert w.doc.take.brim is not None and w.doc.take.brim.name
    w.actions["view.brim_svg"].trigger()
    svg = [c for c in w.children() if type(c).__name__ == "SvgWindow"]
    assert svg and image_stats(svg[0])[2] > 2
    svg[0].close()
    fw.close()
    qtbot.waitUntil(lambda: not w.floating)
