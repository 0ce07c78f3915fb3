"""``label_file``: C3D / CSV in and out, both methods, seed 002's options, plots."""

import numpy as np
import pytest

from carapost.core.template import template_from_frame
from carapost.io.c3d import read_c3d
from carapost.io.marker_csv import read_marker_csv, write_marker_csv
from carapost.io.marker_template import write_marker_template
from carapost.ops.label_file import label_file, read_markers, write_markers
from carapost.synth.mocap import corrupt, face_motion


@pytest.fixture(scope="module")
def face():
    return face_motion(30, 300, 100.0, seed=2)


def _unlabelled_csv(path, face, *, swap=None):
    """A CSV whose columns are unlabelled points ("Marker_k") in a different order every frame,
    except frame 0 which holds the markers under their names; optionally two named columns
    exchanged over a frame range."""
    c = corrupt(face, seed=1, gap_rate=0.002, spurious_rate=0.0)
    x = c.clean_labels_xyz.copy()
    x[0] = face.xyz[0]  # every marker in the labelled frame (a marker never labelled stays unknown)
    F, M, _ = x.shape
    rng = np.random.default_rng(0)
    perm = np.array([np.arange(M)] + [rng.permutation(M) for _ in range(F - 1)])
    shuffled = np.take_along_axis(x, perm[..., None], axis=1)
    names = [f"Marker_{k}" for k in range(M)]
    write_marker_csv(path, names, shuffled, frame_rate=face.frame_rate)
    return x, perm


def test_c3d_round_trip_keeps_right_labels(real_data, tmp_path):
    out = tmp_path / "vicon_labelled.c3d"
    rep = label_file(real_data / "ezc3d/Vicon.c3d", out)
    assert rep["method"] == "assignment" and rep["relabelled_samples"] == 0
    src, dst = read_c3d(real_data / "ezc3d/Vicon.c3d"), read_c3d(out)
    mi = src.marker_indices()
    assert dst.labels[:len(mi)] == [src.labels[i] for i in mi]
    same = np.isfinite(dst.xyz[:, :len(mi), 0])
    assert same.sum() >= 0.999 * np.isfinite(src.xyz[:, mi, 0]).sum()
    np.testing.assert_allclose(dst.xyz[:, :len(mi)][same], src.xyz[:, mi][same], atol=1e-3)
    assert dst.frame_rate == src.frame_rate


def test_swapped_labels_in_the_input_are_repaired(real_data, tmp_path):
    d = read_markers(real_data / "ezc3d/Vicon.c3d")
    x = d.xyz.copy()
    a, b = d.names.index("Daphnee:ARMl"), d.names.index("Daphnee:ARMm")
    x[200:300, [a, b]] = x[200:300, [b, a]]
    inp = tmp_path / "swapped.c3d"
    write_markers(inp, d.names, x, frame_rate=d.frame_rate)
    rep = label_file(inp, tmp_path / "fixed.csv")
    runs = {(r["marker"], r["input"], r["first"], r["last"]) for r in rep["relabel_runs"]}
    assert ("Daphnee:ARMl", "Daphnee:ARMm", 200, 299) in runs
    fixed = read_marker_csv(tmp_path / "fixed.csv")
    ok = np.isfinite(d.xyz[..., 0])
    same = np.isclose(fixed.xyz[:, :len(d.names), 0], d.xyz[..., 0], atol=1e-4) & ok
    assert same.sum() >= ok.sum() - 1  # one sample of this file is left unlabelled


@pytest.mark.parametrize("method", ["assignment", "nearest"])
def test_unlabelled_csv_with_a_template(face, tmp_path, method):
    inp = tmp_path / "in.csv"
    x, perm = _unlabelled_csv(inp, face)
    tpl = tmp_path / "face.json"
    write_marker_template(template_from_frame(face.xyz[150], face.names, face.sticks), tpl)
    out = tmp_path / "out.csv"
    rep = label_file(inp, out, method=method, template=tpl, plot_every=100)
    got = read_marker_csv(out)
    assert got.names[:face.n_markers] == face.names
    ok = np.isfinite(x[..., 0])
    match = np.isclose(got.xyz[:, :face.n_markers, 0], x[..., 0], atol=1e-4) & ok
    assert match.sum() / ok.sum() >= (0.999 if method == "assignment" else 0.98)
    assert len(rep["plots"]) == 4 and all(p.endswith(".png") for p in rep["plots"])


def test_seed_options(face, tmp_path):
    inp = tmp_path / "in.csv"
    x, perm = _unlabelled_csv(inp, face)
    names = face.names
    # frame 0 labelled by frame mappings, the rest by the nearest method
    mapping = {0: {f"Marker_{k}": names[perm[0, k]] for k in range(face.n_markers)}}
    sticks = [(names[a], names[b]) for a, b in face.sticks]
    rep = label_file(inp, tmp_path / "o.csv", method="nearest", marker_names=names, frame_mappings=mapping,
                     sticks=sticks, options={"dist_thresh": 10.0})
    assert rep["reference_frame"] == 0 and rep["markers"] == face.n_markers
    got = read_marker_csv(tmp_path / "o.csv").xyz[:, :face.n_markers]
    ok = np.isfinite(x[..., 0])
    assert (np.isclose(got[..., 0], x[..., 0]) & ok).sum() / ok.sum() >= 0.99
    with pytest.raises(ValueError, match="not a marker name"):
        label_file(inp, tmp_path / "o.csv", marker_names=names, frame_mappings={0: {"Marker_0": "Nope"}})
    with pytest.raises(ValueError, match="no marker names"):
        label_file(inp, tmp_path / "o.csv")
    with pytest.raises(ValueError, match="unknown marker file type"):
        label_file(inp, tmp_path / "o.trc", marker_names=names, frame_mappings=mapping)


def test_ignored_and_fully_labelled_markers(real_data, tmp_path):
    rep = label_file(real_data / "ezc3d/Vicon.c3d", tmp_path / "o.c3d", ignore_markers=["boite:gauche_ext"],
                     labeled_markers=["Daphnee:ASISr"], keep_unlabelled=False)
    assert rep["relabelled_samples"] == 0
    assert read_c3d(tmp_path / "o.c3d").n_points == rep["markers"]
