"""Writing a synthetic take to disk: pico files, nominal calibration, brim, seeds, truth."""

import json

import numpy as np
import pytest
from lxml import etree

from carapost.io.brim import load_brim_json
from carapost.synth import SynthConfig, generate_take, write_take

pico = pytest.importorskip("carapost.io.pico")
calibration = pytest.importorskip("carapost.io.calibration")


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    st = generate_take(SynthConfig(n_frames=3, seed=4, width=320, height=180))
    out = tmp_path_factory.mktemp("synth")
    calls = []
    paths = write_take(st, out, name="Demo", progress=lambda done, total: calls.append((done, total)))
    return st, out, paths, calls


def test_all_files_written(written):
    st, out, paths, calls = written
    assert calls == [(1, 3), (2, 3), (3, 3)]
    expected = {f"pico_{c}": f"Demo_{c}.pico" for c in range(4)}
    expected.update(xcp="Demo.xcp", brim_json="Demo_brim.json", brim_svg="Demo_brim.svg",
                    seeds="Demo_seeds.json", truth="Demo_truth.npz")
    assert {k: p.name for k, p in paths.items()} == expected
    for p in paths.values():
        assert p.parent == out and p.stat().st_size > 0
    # nothing temporary left behind
    assert sorted(p.name for p in out.iterdir()) == sorted(expected.values())


def test_pico_files_hold_the_jpeg_frames_and_metadata(written):
    st, _, paths, _ = written
    for c in range(4):
        with pico.PicoReader(paths[f"pico_{c}"]) as r:
            assert len(r) == 3
            assert r.meta.channel == c and r.meta.camera_name == st.camera_names[c]
            assert (r.meta.width, r.meta.height) == (320, 180)
            assert r.meta.frame_rate == pytest.approx(60.0)
            assert r.meta.blob_parameters["find_black_blobs"] is True
            for f in (0, 2):
                img = r.read(f)
                ref = st.images(f)[c]
                assert img.shape == ref.shape and img.dtype == np.uint8
                # JPEG at quality 92: close to the rendered frame
                assert np.abs(img.astype(int) - ref.astype(int)).mean() < 2.0


def test_xcp_is_the_nominal_calibration(written):
    st, _, paths, _ = written
    cal = calibration.load_calibration(paths["xcp"])
    assert cal.names == st.camera_names
    tr = st.truth
    for c, cam in enumerate(cal.cameras):
        assert cam.intrinsics.focal_length == pytest.approx(tr.intrinsics[c].focal_length, rel=1e-6)
        np.testing.assert_allclose(cam.intrinsics.principal_point, tr.intrinsics[c].principal_point, atol=1e-4)
        np.testing.assert_allclose(cam.intrinsics.radial[:2], tr.intrinsics[c].radial[:2], rtol=1e-5)
        R, t = cam.pose_at(0)
        np.testing.assert_allclose(R, tr.nominal_R[c], atol=1e-6)
        np.testing.assert_allclose(t, tr.nominal_t[c], atol=1e-3)
        # the nominal pose is not the true (flexed) one: a solver has work to do
        assert np.abs(tr.t[0, c] - tr.nominal_t[c]).max() > 1e-3


def test_brim_seeds_and_truth_files(written):
    st, _, paths, _ = written
    b = load_brim_json(paths["brim_json"])
    np.testing.assert_allclose(b.xyz, st.brim.xyz)
    root = etree.parse(str(paths["brim_svg"])).getroot()
    assert len(root.findall(".//{http://www.w3.org/2000/svg}circle")) == len(st.brim)
    seeds = json.loads(paths["seeds"].read_text())
    assert seeds["frame"] == 0 and len(seeds["brim"]) >= 4 and 5 <= len(seeds["face"]) <= 10
    with np.load(paths["truth"]) as z:
        np.testing.assert_array_equal(z["xyz"], st.truth.xyz)
        np.testing.assert_array_equal(z["visible"], st.truth.visible)
        np.testing.assert_array_equal(z["brim_xy"], st.truth.brim_xy)
        assert list(z["names"]) == st.truth.names
        assert json.loads(str(z["config_json"]))["seed"] == 4


def test_bad_name_is_rejected(tmp_path):
    st = generate_take(SynthConfig(n_frames=1, width=320, height=180))
    with pytest.raises(ValueError, match="name"):
        write_take(st, tmp_path, name="a/b")
