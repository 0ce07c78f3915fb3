"""The carapost command line: every command, its JSON summary, and one-line errors."""

import json

import pytest

from carapost.cli import main


@pytest.fixture(scope="module")
def take_files(tmp_path_factory):
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=35, n_frames=3, width=640, height=360, seed=1))
    return write_take(synth, tmp_path_factory.mktemp("cli"), "Cli")


def run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_info_on_every_kind(capsys, take_files):
    code, out, err = run(capsys, "info", str(take_files["pico_0"]), str(take_files["xcp"]))
    assert code == 0, err
    assert "pico" in out and "frames: 3" in out and "cameras: 4" in out
    code, out, _ = run(capsys, "info", str(take_files["pico_1"]), "--json")
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["files"][0]["channel"] == 1 and summary["files"][0]["width"] == 640


def test_info_errors_are_one_line(capsys, tmp_path):
    code, out, err = run(capsys, "info", str(tmp_path / "missing.pico"))
    assert code == 1
    assert err.strip().count("\n") == 0 and "missing.pico" in err and "Traceback" not in err
    bad = tmp_path / "bad.xcp"
    bad.write_text("<not xml")
    code, _, err = run(capsys, "info", str(bad))
    assert code == 1 and "bad.xcp" in err


def test_detect_csv_and_save_then_export(capsys, take_files, tmp_path):
    csv = tmp_path / "d.csv"
    cara = tmp_path / "d.cara"
    code, out, err = run(capsys, "detect", str(take_files["pico_0"]), "--calibration", str(take_files["xcp"]),
                         "--csv", str(csv), "--save", str(cara), "--frames", "0:1", "--black-min-radius", "1.5",
                         "--no-progress", "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"] == 2 and summary["detections"] > 50
    header = csv.read_text().splitlines()[0]
    assert header == "frame,camera,x,y,major,minor,angle,polarity,score"
    code, out, err = run(capsys, "info", str(cara))
    assert code == 0 and "frames_detected: [2, 2, 2, 2]" in out
    code, out, err = run(capsys, "export", str(cara), str(tmp_path / "cams.xcp"), "--frame", "0")
    assert code == 0, err


def test_detect_takes_settings_then_flags(capsys, take_files, tmp_path):
    cara = tmp_path / "s.cara"
    code, _, err = run(capsys, "detect", str(take_files["pico_0"]), "--calibration", str(take_files["xcp"]),
                       "--save", str(cara), "--frames", "0", "--set", "blobs.adaptive_background=true", "--set",
                       "blobs.black_threshold=0.7", "--black-threshold", "0.6", "--no-progress")
    assert code == 0, err
    from carapost.io.cara import load_take

    p = load_take(cara).take.params.blobs
    assert p.adaptive_background and p.black_threshold == 0.6      # the dedicated flag comes last
    code, _, err = run(capsys, "detect", str(take_files["pico_0"]), "--save", str(cara), "--set", "blobs.nope=1")
    assert code == 1 and "settings: Blob Parameters: no property named 'nope'" in err


def test_detect_needs_an_output(capsys, take_files):
    code, _, err = run(capsys, "detect", str(take_files["pico_0"]))
    assert code == 1 and "nothing to write" in err


def test_detect_and_calibrate_check_their_outputs_first(capsys, take_files, tmp_path):
    missing = tmp_path / "no_such_folder"
    code, out, err = run(capsys, "detect", str(take_files["pico_0"]), "--csv", str(missing / "d.csv"))
    assert code == 1 and f"folder {missing} does not exist" in err and not out
    code, _, err = run(capsys, "detect", str(take_files["pico_0"]), "--save", str(tmp_path))
    assert code == 1 and "it is a folder" in err
    code, _, err = run(capsys, "calibrate", "--target", "checkerboard:4x7:60", "--camera", str(tmp_path),
                       "--out", str(missing / "c.xcp"))
    assert code == 1 and f"folder {missing} does not exist" in err


def test_convert_video_to_pico(capsys, tmp_path, take_files):
    import cv2
    import numpy as np

    folder = tmp_path / "imgs"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"f_{i}.png"), np.full((40, 60), 10 * i, np.uint8))
    code, out, err = run(capsys, "convert", str(folder), "--out", str(tmp_path / "out"), "--name", "T",
                         "--lossless", "--no-progress")
    assert code == 0, err
    assert (tmp_path / "out" / "T_0.pico").exists()


def test_export_unknown_extension(capsys, take_files, tmp_path):
    code, _, err = run(capsys, "export", str(take_files["truth"]), str(tmp_path / "x.abc"))
    assert code == 1 and "error" in err


def test_process_auto_init_on_the_real_room_videos(capsys, real_data, tmp_path):
    """The issue's real-data flow from the command line: Pose2Sim's four videos, its Qualisys
    calibration, white retro-reflective markers, no caddies (cameras around a room)."""
    root = real_data / "pose2sim-demo"
    videos = [str(root / "videos" / f"cam0{c}.mp4") for c in (1, 2, 3, 4)]
    sets = ["blobs.find_black_blobs=false", "blobs.find_white_blobs=true", "blobs.white_min_radius=1",
            "blobs.white_max_radius=8", "blobs.white_threshold=0.05", "blobs.adaptive_background=true"]
    code, out, err = run(capsys, "process", "--cameras", *videos, "--calibration",
                         str(root / "calibration" / "Calib.qca.txt"), "--auto-init", "--caddies", "none",
                         *[a for s in sets for a in ("--set", s)], "--out", str(tmp_path / "p.cara"),
                         "--no-progress", "--json")
    assert code == 0, err
    stages = {s["stage"]: s for s in json.loads(out.strip().splitlines()[-1])["stages"]}
    assert stages["detect blobs"]["detections"] == 392       # 92 / 112 / 98 / 90 (docs/initialize-3d.md)
    # 3 points at 1.08 px with the default 2 px hypothesis limit; the file's poses are off
    # (docs/initialize-3d.md): the 1.0 px target is not met, this pins the behaviour.
    assert stages["initialize 3D"]["points"] >= 2
    assert stages["initialize 3D"]["median_reprojection_px"] <= 1.5
    # The benchmark's setting (3 px) from the command line: its 7 points at 1.52 px.
    code, out, err = run(capsys, "process", "--cameras", *videos, "--calibration",
                         str(root / "calibration" / "Calib.qca.txt"), "--auto-init", "--caddies", "none",
                         *[a for s in sets for a in ("--set", s)], "--set", "init3d.Automatic Max Reprojection Error=3",
                         "--out", str(tmp_path / "p.cara"), "--no-progress", "--json")
    assert code == 0, err
    init = next(s for s in json.loads(out.strip().splitlines()[-1])["stages"] if s["stage"] == "initialize 3D")
    assert init["points"] == 7 and abs(init["median_reprojection_px"] - 1.52) < 0.01


@pytest.mark.slow
def test_calibrate_real_checkerboards_intrinsics(capsys, real_data, tmp_path):
    folder = real_data / "pose2sim-demo" / "calibration" / "intrinsics"
    cams = [str(folder / f"int_cam0{c}_img") for c in (1, 2)]
    code, out, err = run(capsys, "calibrate", "--target", "checkerboard:4x7:60", "--camera", cams[0], "--camera",
                         cams[1], "--out", str(tmp_path / "rig.xcp"), "--no-extrinsics", "--no-progress", "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    from carapost.io.calibration import load_calibration

    q = load_calibration(real_data / "pose2sim-demo" / "calibration" / "Calib.qca.txt")
    for c in range(2):
        f = summary["cameras"][c]["focal_length_px"]
        assert abs(f / q.cameras[c].intrinsics.focal_length - 1) < 0.01


def test_calibrate_bad_target(capsys, tmp_path):
    code, _, err = run(capsys, "calibrate", "--target", "checkerboard:4by7", "--camera", str(tmp_path),
                       "--out", str(tmp_path / "x.xcp"))
    assert code == 1 and "checkerboard:4x7:60" in err


def test_label_command_repairs_a_swap(capsys, tmp_path):
    import numpy as np

    from carapost.io.marker_csv import read_marker_csv, write_marker_csv

    rng = np.random.default_rng(0)
    F, M = 120, 12
    base = rng.uniform(-60, 60, (M, 3))
    t = np.linspace(0, 2 * np.pi, F)
    xyz = base[None] + 3 * np.sin(t)[:, None, None] * rng.normal(size=(1, M, 3))
    swapped = xyz.copy()
    swapped[60:, [2, 5]] = swapped[60:, [5, 2]]
    names = [f"M{i}" for i in range(M)]
    src = tmp_path / "in.csv"
    write_marker_csv(src, names, swapped, frame_rate=60.0)
    code, out, err = run(capsys, "label", str(src), str(tmp_path / "out.csv"), "--no-progress", "--json")
    assert code == 0, err
    back = read_marker_csv(tmp_path / "out.csv")
    order = [back.names.index(n) for n in names]
    np.testing.assert_allclose(back.xyz[:, order], xyz, atol=1e-3)


def test_label_command_isolated_check_switch(capsys, tmp_path):
    import json

    import numpy as np

    from carapost.io.marker_csv import write_marker_csv

    rng = np.random.default_rng(1)
    xyz = rng.uniform(-60, 60, (1, 8, 3)) + rng.normal(0, 0.05, (90, 8, 3))
    src = tmp_path / "in.csv"
    write_marker_csv(src, [f"M{i}" for i in range(8)], xyz, frame_rate=60.0)
    reports = {}
    for flag in ((), ("--no-isolated-check",)):
        code, out, err = run(capsys, "label", str(src), str(tmp_path / "out.csv"), "--no-progress", "--json", *flag)
        assert code == 0, err
        assert "labelled_samples: 720" in out
        reports[flag] = json.loads(out.strip().splitlines()[-1])
    assert reports[()]["labeller"]["unseen_named"] == 0
    assert "unseen_named" not in reports[("--no-isolated-check",)]["labeller"]


def test_label_command_take_check_switch(capsys, tmp_path):
    import json

    import numpy as np

    from carapost.io.marker_csv import read_marker_csv, write_marker_csv

    rng = np.random.default_rng(2)
    xyz = rng.uniform(-60, 60, (1, 8, 3)) + rng.normal(0, 0.05, (300, 8, 3))
    xyz[100:250, 7] = np.nan                     # a marker absent for 150 frames: the take check runs
    src = tmp_path / "in.csv"
    write_marker_csv(src, [f"M{i}" for i in range(8)], xyz, frame_rate=60.0)
    reports = {}
    for flag in ((), ("--no-take-check",)):
        code, out, err = run(capsys, "label", str(src), str(tmp_path / "out.csv"), "--no-progress", "--json", *flag)
        assert code == 0, err
        reports[flag] = json.loads(out.strip().splitlines()[-1])
        back = read_marker_csv(tmp_path / "out.csv")
        order = [back.names.index(f"M{i}") for i in range(8)]
        np.testing.assert_allclose(back.xyz[:, order], xyz, atol=1e-3)
    assert reports[()]["labeller"]["take_renamed"] == 0
    assert "take_renamed" not in reports[("--no-take-check",)]["labeller"]


def test_ctrl_c_cancels_then_interrupts(capsys):
    import os
    import signal

    from carapost.commands.common import interrupt_cancels

    with interrupt_cancels("test") as cancel:
        assert not cancel()
        os.kill(os.getpid(), signal.SIGINT)
        assert cancel()                                  # the first Ctrl+C asks the operation to stop
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)          # the second one aborts
    assert "stopping after the current frame" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_process_ctrl_c_keeps_and_saves_the_finished_frames(capsys, tmp_path, monkeypatch):
    import os
    import signal

    import numpy as np

    from carapost.io.cara import load_take
    from carapost.ops import track as track_ops
    from carapost.synth import SynthConfig, generate_take, write_take

    files = write_take(generate_take(SynthConfig(n_markers=35, n_frames=6, seed=2)), tmp_path, "C")
    real = track_ops.track

    def interrupted_track(take, start, **kw):
        progress = kw["progress"]

        def on_frame(done, total):
            progress(done, total)
            if done == 2:
                os.kill(os.getpid(), signal.SIGINT)       # the user presses Ctrl+C during tracking
        return real(take, start, **{**kw, "progress": on_frame})

    monkeypatch.setattr(track_ops, "track", interrupted_track)
    out = tmp_path / "c.cara"
    code = main(["process", "--cameras", *[str(files[f"pico_{c}"]) for c in range(4)], "--calibration",
                 str(files["xcp"]), "--brim", str(files["brim_json"]), "--seeds", str(files["seeds"]), "--track",
                 "--out", str(out), "--no-progress"])
    assert code == 130 and "cancelled" in capsys.readouterr().out
    take = load_take(out).take
    tracked = np.isfinite(take.xyz[:, take.face_points()]).all(-1).any(-1)
    assert tracked[:3].all() and not tracked[4:].any()   # frames 0-2 kept (and saved), the rest not tracked
