"""Seed 002's marker CSV layout (Motive's export)."""

import numpy as np
import pytest

from carapost.io.marker_csv import MarkerCSVError, read_marker_csv, write_marker_csv
from carapost.io.marker_template import TemplateFileError, read_marker_template, write_marker_template
from carapost.core.template import MarkerTemplate


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(7, 3, 3)) * 100
    x[2, 1] = np.nan
    p = tmp_path / "m.csv"
    write_marker_csv(p, ["A", "B", "C"], x, frame_rate=120.0, frames=np.arange(10, 17))
    lines = p.read_text().splitlines()
    assert lines[3] == ",Name,A,A,A,B,B,B,C,C,C"
    assert lines[6].startswith("Frame,Time")
    assert lines[9].startswith("12,0.100000,") and ",,," in lines[9]
    d = read_marker_csv(p)
    assert d.names == ["A", "B", "C"] and d.frame_rate == 120.0 and d.units == "millimeters"
    np.testing.assert_allclose(d.xyz, x, atol=1e-6)
    np.testing.assert_array_equal(d.frames, np.arange(10, 17))
    # in metres on disk, millimetres in memory
    write_marker_csv(p, ["A", "B", "C"], x, frame_rate=120.0, units="m")
    np.testing.assert_allclose(read_marker_csv(p).xyz, x, atol=1e-3)


def test_six_header_lines_names_once_and_metres(tmp_path):
    p = tmp_path / "seed.csv"
    p.write_text("Take header\n\n\n,,Hands_R_T1,,,Hands_R_T2,,\n\nFrame,Time,X,Y,Z,X,Y,Z\n"
                 "0,0.00,0.1,0.2,0.3,,,\n1,0.01,0.1,0.2,0.3,0.5,0.5,0.5\n")
    d = read_marker_csv(p, units="m")
    assert d.names == ["Hands_R_T1", "Hands_R_T2"] and d.xyz.shape == (2, 2, 3)
    np.testing.assert_allclose(d.xyz[0, 0], [100.0, 200.0, 300.0])
    assert np.isnan(d.xyz[0, 1]).all()
    assert d.frame_rate == pytest.approx(100.0)


def test_real_motive_file(real_data):
    d = read_marker_csv(real_data / "optitrack-motive-csv/test_markers_enabled.csv")
    assert d.xyz.shape == (1353, 18, 3) and d.frame_rate == 360.0
    assert d.names[0] == "Unlabeled 1036"
    assert 0.05 < np.isnan(d.xyz[..., 0]).mean() < 0.12  # 8.4 % blank cells
    np.testing.assert_allclose(d.xyz[0, 0], [2659.741943, -830.793884, -2862.19165])


def test_errors(tmp_path, real_data):
    with pytest.raises(MarkerCSVError, match="cannot read"):
        read_marker_csv(tmp_path / "missing.csv")
    with pytest.raises(MarkerCSVError, match="no marker names"):
        read_marker_csv(real_data / "optitrack-motive-csv/test_default.csv")
    bad = tmp_path / "bad.csv"
    bad.write_text("h\n\n\n,,A,A,A\n\n\nFrame,Time,X,Y,Z\n0,0,1,x,3\n")
    with pytest.raises(MarkerCSVError, match="not a number"):
        read_marker_csv(bad)
    bad.write_text("h,1,Length Units,Furlongs\n\n\n,,A,A,A\n\n\nFrame,Time,X,Y,Z\n0,0,1,2,3\n")
    with pytest.raises(MarkerCSVError, match="unknown length unit"):
        read_marker_csv(bad)
    with pytest.raises(MarkerCSVError, match="commas"):
        write_marker_csv(tmp_path / "o.csv", ["a,b"], np.zeros((1, 1, 3)))
    with pytest.raises(MarkerCSVError, match="folder"):
        write_marker_csv(tmp_path / "no" / "o.csv", ["a"], np.zeros((1, 1, 3)))


def test_template_file_round_trip_and_errors(tmp_path):
    t = MarkerTemplate(["a", "b", "c"], np.array([[0.0, 1, 2], [np.nan] * 3, [3.0, 4, 5]]), np.array([[0, 2]]),
                       "test")
    p = tmp_path / "t.json"
    write_marker_template(t, p)
    u = read_marker_template(p)
    assert u.names == t.names and u.source == "test" and u.sticks.tolist() == [[0, 2]]
    np.testing.assert_array_equal(u.xyz, t.xyz)
    p.write_text(p.read_text().replace('"version": 1', '"version": 9'))
    with pytest.raises(TemplateFileError, match="newer"):
        read_marker_template(p)
    p.write_text("{}")
    with pytest.raises(TemplateFileError, match="not a CaraPost marker template"):
        read_marker_template(p)
    p.write_text('{"format": "carapost-marker-template", "version": 1, "names": ["a"], "xyz": [[1, 2]]}')
    with pytest.raises(TemplateFileError, match="triples|three numbers"):
        read_marker_template(p)
