"""The example scripts (``examples/``), run on a small synthetic take.

``examples/make_demo_take.py`` writes the take once per test session (4 frames, 35 markers,
640 x 360): its ``.pico`` files, calibration, brim, seeds, ``Example_b.cara`` (detections) and
``Example.cara`` (brim solved, Initialize 3D, tracked). Every script runs once as a subprocess
(as a user runs it); further options and the error cases call the script's ``main(argv)`` in
this process, which is much faster. Each script's output is checked against what the API reads
from the same files.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import carapost.api as cp

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
GUIDE_SCRIPTS = ["process_detect_blobs.py", "process_track.py", "process_batch_detect_blobs.py",
                 "cara_fbx_export.py", "process_setup_ROM.py", "process_properties.py", "export_3d_simple.py",
                 "export_brim.py", "export_general.py", "export_timecode.py"]
SMALL_BLOBS = ["-p", "Blob Parameters", "Black Min Radius", "2"]


def run(script: str, *args: object, ok: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, str(EXAMPLES / script), *map(str, args)], capture_output=True, text=True,
                          timeout=300)
    if ok:
        assert proc.returncode == 0, f"{script} failed:\n{proc.stdout}\n{proc.stderr}"
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc


@functools.cache
def script(name: str):
    """The example script as a module (its ``main(argv)`` returns the exit code)."""
    spec = importlib.util.spec_from_file_location(f"example_{name[:-3]}", EXAMPLES / name)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def call(capsys, name: str, *args: object) -> tuple[int, str, str]:
    """Run ``main`` of an example script in this process: (exit code, stdout, stderr)."""
    code = script(name).main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="session")
def demo(tmp_path_factory) -> Path:
    """The demo take folder (shared with tests/test_api.py through the session's base temp)."""
    folder = tmp_path_factory.getbasetemp() / "api_demo"
    if not (folder / "Example.cara").exists():
        run("make_demo_take.py", folder)
    return folder


def copy_take(demo: Path, dst: Path, name: str = "Example", *, calibration: bool = True) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for c in range(4):
        shutil.copy(demo / f"Example_{c}.pico", dst / f"{name}_{c}.pico")
    if calibration:
        shutil.copy(demo / "Example.xcp", dst / f"{name}.xcp")
    return dst / f"{name}_0.pico"


@pytest.mark.parametrize("name", GUIDE_SCRIPTS + ["make_demo_take.py"])
def test_every_script_has_help(name, capsys):
    with pytest.raises(SystemExit) as stop:
        script(name).main(["--help"])
    out = capsys.readouterr().out
    assert stop.value.code == 0
    assert out.startswith("usage: ") and len(out.splitlines()) > 3
    assert script(name).__doc__.split("\n\n")[0].split()[0] in out     # the description


def test_demo_take(demo):
    exp = cp.CaraExport(demo / "Example.cara")
    assert exp.n_frames == 4 and exp.n_cameras == 4
    assert len(exp.brim_points) == 18 and len(exp.face_points) >= 5
    seeds = json.loads((demo / "Example_seeds.json").read_text())
    assert sum(1 for lab in exp.labels if lab) >= 2 and set(exp.labels) - {""} <= set(json.dumps(seeds).split('"'))
    face = exp.face_points
    assert np.isfinite(exp.xyz[1:, face]).all(-1).any()          # tracked beyond the first frame
    b = cp.CaraExport(demo / "Example_b.cara")
    assert b.n_points == 0 and all(len(b.detected_frames(c)) == 4 for c in range(4))
    assert b.n_detections() == exp.n_detections() > 100


def test_process_detect_blobs(demo, tmp_path, capsys):
    pico = copy_take(demo, tmp_path / "take")
    proc = run("process_detect_blobs.py", pico, "--frames", "1:2", "--sensors", "0,2", *SMALL_BLOBS)
    out = tmp_path / "take" / "Example_b.cara"
    assert str(out) in proc.stdout
    exp = cp.CaraExport(out)
    assert exp.take.params.blobs.black_min_radius == 2.0
    ref = cp.CaraExport(demo / "Example_b.cara")       # detected with the same parameters
    for c in range(4):
        expected = [1, 2] if c in (0, 2) else []
        assert exp.detected_frames(c).tolist() == expected
        for f in expected:
            np.testing.assert_array_equal(exp.detections(c, f)["x"], ref.detections(c, f)["x"])
    assert exp.take.cameras[0].intrinsics == ref.take.cameras[0].intrinsics     # Example.xcp found
    # -o; errors are one line on stderr.
    code, _, _ = call(capsys, "process_detect_blobs.py", pico, "--frames", "0", "--sensors", "3", "-o",
                      tmp_path / "other.cara")
    assert code == 0 and cp.CaraExport(tmp_path / "other.cara").detected_frames(3).tolist() == [0]
    code, _, err = call(capsys, "process_detect_blobs.py", pico, "--frames", "2:9")
    assert code == 1 and "0..3" in err
    code, _, err = call(capsys, "process_detect_blobs.py", pico, "--sensors", "7")
    assert code == 1 and "sensor 7" in err
    code, _, err = call(capsys, "process_detect_blobs.py", tmp_path / "Nothing_0.pico")
    assert code == 1 and "Nothing_0.pico" in err


def test_process_track(demo, tmp_path, capsys):
    # A take initialized in frame 0 only, then tracked by the script.
    with cp.CaraProcess.open(demo / "Example_b.cara") as take:
        take.run_pipeline(seeds=demo / "Example_seeds.json", brim=str(demo / "Example_brim.json"), detect="none")
        init = take.save(tmp_path / "init.cara")
    before = cp.CaraExport(init)
    face = before.face_points
    assert len(face) >= 5 and np.isfinite(before.xyz[1:, face]).sum() == 0
    proc = run("process_track.py", init, "-o", tmp_path / "tracked.cara")
    assert "tracking from frame 0" in proc.stdout and "Track Forwards [Sequence]" in proc.stdout
    after = cp.CaraExport(tmp_path / "tracked.cara")
    assert after.n_points == before.n_points
    np.testing.assert_array_equal(after.xyz[0], before.xyz[0])
    assert np.isfinite(after.xyz[1:, face]).all(-1).any()
    # In place by default (from the last frame: nothing left to track forwards).
    code, out, _ = call(capsys, "process_track.py", tmp_path / "tracked.cara", "--frame", "3")
    assert code == 0 and "Track" not in out and f"wrote {tmp_path / 'tracked.cara'}" in out
    # A .pico take needs a ROM; a .cara takes none; a take without points cannot be tracked.
    code, _, err = call(capsys, "process_track.py", demo / "Example_0.pico")
    assert code == 1 and "-rom" in err
    code, _, err = call(capsys, "process_track.py", init, "-rom", init)
    assert code == 1 and "-rom" in err
    code, _, err = call(capsys, "process_track.py", demo / "Example_b.cara")
    assert code == 1 and "no frame has 3D points" in err


def test_process_track_with_rom(demo, tmp_path, capsys):
    # The demo's .pico files as a new take, initialized from the solved demo take as the ROM.
    pico = copy_take(demo, tmp_path, "New")
    proc = run("process_track.py", pico, "-rom", demo / "Example.cara")
    assert "Load ROM Example.cara" in proc.stdout
    assert "Initialize from ROM: 18 of 18 brim points" in proc.stdout and "Track Forwards [Sequence]" in proc.stdout
    rom, new = cp.CaraExport(demo / "Example.cara"), cp.CaraExport(tmp_path / "New.cara")
    rf, nf = rom.face_points, new.face_points
    assert len(nf) == len(rf) and len(new.brim_points) == 18
    assert [new.take.points.labels[i] for i in nf] == [rom.take.points.labels[i] for i in rf]
    assert new.take.rom_path == str(demo / "Example.cara")
    # Same images: every face point found in frame 0 where the ROM has it, then tracked.
    np.testing.assert_allclose(new.xyz[0, nf], rom.xyz[0, rf], atol=0.05)
    assert np.isfinite(new.xyz[1:, nf]).all(-1).any()
    # A missing or unusable ROM is one line naming the file.
    code, _, err = call(capsys, "process_track.py", pico, "-rom", tmp_path / "nothing.cara")
    assert code == 1 and "nothing.cara" in err
    code, _, err = call(capsys, "process_track.py", pico, "-rom", demo / "Example_b.cara")
    assert code == 1 and "Example_b.cara" in err and "brim" in err


def test_process_batch_detect_blobs(demo, tmp_path, capsys):
    root = tmp_path / "jobs"
    copy_take(demo, root)
    shutil.copy(demo / "Example_b.cara", root / "Example_b.cara")          # already detected
    copy_take(demo, root / "day2", "ROM1", calibration=False)
    copy_take(demo, root / "day2", "ROM2", calibration=False)
    (root / "day2" / "notes_x.pico").write_bytes(b"")                       # not a take file
    proc = run("process_batch_detect_blobs.py", root / "day2" / "ROM1*.pico", "--frames", "0:0", *SMALL_BLOBS)
    assert "1 take(s): 1 detected, 0 skipped, 0 failed" in proc.stdout
    rom1 = cp.CaraExport(root / "day2" / "ROM1_b.cara")
    assert rom1.detected_frames(1).tolist() == [0] and rom1.n_detections() > 100
    assert not (root / "day2" / "ROM2_b.cara").exists()
    code, out, _ = call(capsys, "process_batch_detect_blobs.py", root, "--dry-run")
    assert code == 0 and "3 take(s): 0 detected, 2 skipped, 0 failed" in out
    assert f"would detect blobs -> {root / 'day2' / 'ROM2_b.cara'}" in out
    code, _, err = call(capsys, "process_batch_detect_blobs.py", tmp_path / "empty*")
    assert code == 1 and "no takes" in err


def test_cara_fbx_export(demo, tmp_path, capsys):
    ufbx = pytest.importorskip("ufbx")
    exp = cp.CaraExport(demo / "Example.cara")
    out = tmp_path / "all.fbx"
    run("cara_fbx_export.py", demo / "Example.cara", "-o", out)
    builtin = tmp_path / "builtin.fbx"
    exp.export(builtin)
    names = {n.name for n in ufbx.load_file(str(out)).nodes}
    assert set(exp.point_names) <= names
    assert names == {n.name for n in ufbx.load_file(str(builtin)).nodes}
    assert abs(out.stat().st_size - builtin.stat().st_size) < 64             # the same but the time stamp
    face = [exp.point_names[p] for p in exp.face_points]
    brim = [exp.point_names[p] for p in exp.brim_points]
    chosen = face[:2] + brim[3:4]
    code, _, _ = call(capsys, "cara_fbx_export.py", demo / "Example.cara", "-o", tmp_path / "face.fbx", "--no-brim",
                      "--points", ",".join(chosen))
    names = {n.name for n in ufbx.load_file(str(tmp_path / "face.fbx")).nodes}
    assert code == 0 and set(chosen) <= names
    assert brim[4] not in names and face[-1] not in names
    code, _, err = call(capsys, "cara_fbx_export.py", demo / "Example.cara", "-o", tmp_path / "x.fbx", "--points",
                        "Nobody")
    assert code == 1 and "Nobody" in err


def test_process_setup_rom(demo, tmp_path, capsys):
    pico = copy_take(demo, tmp_path, "ROM")
    proc = run("process_setup_ROM.py", pico, "--preset", "sparse", "--brim", demo / "Example_brim.json",
               "--frames", "0:0", "--seeds", demo / "Example_seeds.json", *SMALL_BLOBS)
    assert "Preset: sparse" in proc.stdout
    rom = cp.CaraExport(tmp_path / "ROM.cara")
    assert rom.take.params.init3d.max_allowed_depth == 60.0                     # the sparse preset
    assert rom.take.params.blobs.black_min_radius == 2.0
    assert rom.brim is not None and len(rom.brim_points) == 18
    assert np.isfinite(rom.xyz[0, rom.face_points]).all(-1).sum() >= 5        # initialized in frame 0
    # Without seeds: the default brim and detections only; the capture's Blob Parameters kept.
    code, _, _ = call(capsys, "process_setup_ROM.py", pico, "-o", tmp_path / "plain.cara", "--frames", "0:0",
                      "--brim", "v1.1")
    plain = cp.CaraExport(tmp_path / "plain.cara")
    assert code == 0 and plain.brim.name == "v1.1" and len(plain.face_points) == 0
    assert plain.detected_frames(0).tolist() == [0] and plain.take.params.blobs.black_min_radius == 4.0
    code, _, err = call(capsys, "process_setup_ROM.py", pico, "--brim", tmp_path / "brim.txt")
    assert code == 1 and "brim.txt" in err


def test_process_properties(demo, capsys):
    proc = run("process_properties.py", "--json")
    assert json.loads(proc.stdout) == cp.default_properties()
    code, out, _ = call(capsys, "process_properties.py", demo / "Example.cara", "-g", "blob parameters", "--json")
    with cp.CaraProcess(demo / "Example.cara") as take:
        expected = {"Blob Parameters": take.properties("Blob Parameters")}
    assert code == 0 and json.loads(out) == expected
    code, text, _ = call(capsys, "process_properties.py", demo / "Example.cara", "-v")
    for group in cp.default_properties():
        assert f"\n{group}\n" in text
    assert "Max Allowed 3D Point Error" in text and "range 0..1000" in text
    code, _, err = call(capsys, "process_properties.py", "-g", "Nonsense")
    assert code == 1 and "Nonsense" in err


def test_export_3d_simple(demo, capsys):
    exp = cp.CaraExport(demo / "Example.cara")
    lines = [ln.split() for ln in run("export_3d_simple.py", demo / "Example.cara").stdout.splitlines()
             if not ln.startswith("#")]
    face = exp.face_points
    assert len(lines) == exp.n_frames * len(face)
    names = exp.point_names
    for f, name, x, y, z, how in lines:
        p = names.index(name)
        assert p in face
        np.testing.assert_allclose([float(x), float(y), float(z)], exp.xyz[int(f), p], atol=5e-4)
        assert how == cp.Recon(exp.reconstruction[int(f), p]).name.lower()
    code, part, _ = call(capsys, "export_3d_simple.py", demo / "Example.cara", "--frames", "2:3")
    assert code == 0 and {ln.split()[0] for ln in part.splitlines() if not ln.startswith("#")} == {"2", "3"}


def test_export_brim(demo, capsys):
    exp = cp.CaraExport(demo / "Example.cara")
    out = run("export_brim.py", demo / "Example.cara", "--frames", "1:1").stdout.splitlines()
    rows = [ln.split() for ln in out if not ln.startswith("#")]
    model = [r for r in rows if len(r) == 6]
    data = [r for r in rows if len(r) == 7]
    assert len(model) == len(exp.brim) == 18 and len(data) == 18
    np.testing.assert_allclose(np.array([r[1:4] for r in model], float), exp.brim.xyz, atol=5e-4)
    for frame, dot, name, x, y, z, views in data:
        p = exp.point_index(name)
        assert frame == "1" and exp.brim_indices[p] == int(dot)
        np.testing.assert_allclose([float(x), float(y), float(z)], exp.xyz[1, p], atol=5e-4)
        assert int(views) == np.isfinite(exp.observations[1, p, :, 0]).sum()
    code, _, err = call(capsys, "export_brim.py", demo / "Example_b.cara")
    assert code == 1 and "no calibration brim" in err


def test_export_general(demo, tmp_path, capsys):
    exp = cp.CaraExport(demo / "Example.cara")
    png = tmp_path / "tracks.png"
    out = run("export_general.py", demo / "Example.cara", "-o", png, "--width", "320").stdout
    img = cv2.imread(str(png))
    assert img.shape == (2 * 180, 2 * 320, 3)
    table = out.splitlines()[2:2 + exp.n_points]
    assert [row.split()[0] for row in table] == exp.point_names
    # The track is drawn in the point's colour at its first position (camera 0 panel, scale 0.5).
    tracked = np.isfinite(exp.tracks_2d(0)[..., 0]).any(0)
    p = int(next(q for q in exp.face_points if tracked[q]))
    xy = exp.tracks_2d(0)[:, p]
    f = int(np.flatnonzero(np.isfinite(xy).all(-1))[0])
    x, y = np.round(xy[f] * 0.5).astype(int)
    patch = img[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3).astype(int)
    colour = exp.point_colours[p][::-1].astype(int)
    assert np.abs(patch - colour).sum(-1).min() < 60
    code, _, _ = call(capsys, "export_general.py", demo / "Example.cara", "-o", tmp_path / "one.png", "--cameras",
                      "1", "--no-image")
    assert code == 0 and cv2.imread(str(tmp_path / "one.png")).shape == (360, 640, 3)
    code, _, err = call(capsys, "export_general.py", demo / "Example.cara", "--cameras", "4")
    assert code == 1 and "[4]" in err


def test_export_timecode(demo, capsys):
    out = run("export_timecode.py", demo / "Example.cara", "--frame", "3", "--timecode", "00:00:00:02").stdout
    rows = [ln.split() for ln in out.splitlines()[2:]]
    assert rows == [["3", "3", "00:00:00:03", "0.0500"], ["2", "2", "00:00:00:02", "0.0333"]]
    code, out, _ = call(capsys, "export_timecode.py", "--rate", "29.97", "--start", "00:59:59;28", "--first-number",
                        "100", "--frame", "2", "--number", "18082")
    assert code == 0 and "drop-frame timecode" in out
    rows = [ln.split() for ln in out.splitlines()[2:]]
    assert [r[:3] for r in rows] == [["2", "102", "01:00:00;00"], ["17982", "18082", "01:09:59;28"]]
    code, _, err = call(capsys, "export_timecode.py", "--rate", "29.97", "--timecode", "00:01:00;00")
    assert code == 1 and "drop-frame" in err


def test_errors_name_the_file(tmp_path, capsys):
    missing = tmp_path / "missing.cara"
    for name in ("export_3d_simple.py", "export_brim.py", "export_general.py", "export_timecode.py",
                 "cara_fbx_export.py", "process_track.py", "process_properties.py"):
        code, _, err = call(capsys, name, missing)
        assert code == 1 and "missing.cara" in err and err.count("\n") == 1, name
