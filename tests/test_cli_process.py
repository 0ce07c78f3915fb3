"""carapost process / the pipeline on a small synthetic take (1280x720, 35 markers, 2 frames)."""

import json

import numpy as np
import pytest

from carapost.cli import main


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=35, n_frames=2, seed=4))
    return synth, write_take(synth, tmp_path_factory.mktemp("proc"), "P")


def picos(files):
    return [str(files[f"pico_{c}"]) for c in range(4)]


def test_process_seeds_end_to_end(capsys, take, tmp_path):
    synth, files = take
    out = tmp_path / "p.cara"
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--brim",
                 str(files["brim_json"]), "--seeds", str(files["seeds"]), "--out", str(out), "--c3d",
                 str(tmp_path / "p.c3d"), "--no-progress", "--json"])
    text, err = capsys.readouterr()
    assert code == 0, err
    summary = json.loads(text.strip().splitlines()[-1])
    stages = [s["stage"] for s in summary["stages"]]
    assert stages[:3] == ["detect blobs", "calibration brim", "snap seeds"]
    assert "solve calibration brim" in stages and "initialize 3D" in stages

    from carapost.io.cara import load_take
    from carapost.synth.evaluate import score_points

    t = load_take(out).take
    ps = score_points(t, synth.truth, [0])
    assert ps.mismatched_observations == 0
    assert ps.median_error_mm < 0.2
    assert summary["points"] >= 0.7 * 35  # limited by blob recall (see docs/blobs.md)
    labelled = [lab for lab in t.points.labels if lab]
    assert len(labelled) >= 5  # named seeds keep their labels
    assert (tmp_path / "p.c3d").exists()


def test_process_auto_init(capsys, take, tmp_path):
    synth, files = take
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--brim", "v2.0",
                 "--auto-init", "--out", str(tmp_path / "a.cara"), "--no-progress"])
    _, err = capsys.readouterr()
    assert code == 0, err


@pytest.mark.parametrize("argv,stage", [
    (["--seeds", "missing.json"], "seeds"),
    (["--seeds", "{seeds}", "--frame", "99"], "seeds"),
])
def test_process_failures_name_the_stage(capsys, take, tmp_path, argv, stage):
    synth, files = take
    argv = [a.replace("{seeds}", str(files["seeds"])) for a in argv]
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]),
                 "--out", str(tmp_path / "x.cara"), "--no-progress", *argv])
    _, err = capsys.readouterr()
    assert code == 1
    assert f"error: {stage}:" in err and err.count("\n") == 1


def test_process_needs_seeds_or_auto(capsys, take, tmp_path):
    _, files = take
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--out",
                 str(tmp_path / "x.cara")])
    assert code == 1 and "--seeds" in capsys.readouterr().err


@pytest.mark.parametrize("where", ["out", "c3d"])
def test_process_checks_its_outputs_before_the_work(capsys, take, tmp_path, where):
    _, files = take
    missing = tmp_path / "no_such_folder"
    out = missing / "x.cara" if where == "out" else tmp_path / "x.cara"
    extra = ["--c3d", str(missing / "x.c3d")] if where == "c3d" else []
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--seeds",
                 str(files["seeds"]), "--out", str(out), "--no-progress", *extra])
    text, err = capsys.readouterr()
    assert code == 1 and f"folder {missing} does not exist" in err and err.count("\n") == 1
    assert "detect blobs" not in text          # failed before the first stage
    assert not out.exists()


def test_process_applies_preset_settings_and_caddies(capsys, take, tmp_path):
    _, files = take
    out = tmp_path / "s.cara"
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--seeds",
                 str(files["seeds"]), "--out", str(out), "--no-progress", "--json", "--preset", "sparse",
                 "--set", "blobs.black_threshold=0.5", "--set", "Initialize 3D Parameters.Max Allowed Depth=30",
                 "--caddies", "0-1,2-3"])
    text, err = capsys.readouterr()
    assert code == 0, err
    init = next(s for s in json.loads(text.strip().splitlines()[-1])["stages"] if s["stage"] == "initialize 3D")
    assert init["points"] > 0 and 0 <= init["median_reprojection_px"] < 0.5

    from carapost.io.cara import load_take
    from carapost.model.params import sparse_35_preset

    t = load_take(out).take
    assert t.params.blobs.black_threshold == 0.5 and t.params.init3d.max_allowed_depth == 30
    assert t.params.tracking == sparse_35_preset().tracking
    assert t.caddies == [(0, 1), (2, 3)]


@pytest.mark.parametrize("argv,message", [
    (["--set", "blobs.no_such_thing=1"], "settings: Blob Parameters: no property named"),
    (["--set", "blobs.black_threshold=2"], "settings: Blob Parameters: Black Threshold must be in the range"),
    (["--set", "blobs=1"], "--set wants GROUP.PROPERTY=VALUE"),
    (["--caddies", "0-1,1-2"], "settings: caddies: camera(s) [1] are in two caddies"),
    (["--caddies", "a-b"], "caddies must be camera pairs like 0-1,2-3, or none"),
    (["--set", "init3d.auto_min_views=5"], "Automatic Min Views (5) exceeds the take's 4 cameras"),
])
def test_process_settings_errors_are_one_line(capsys, take, tmp_path, argv, message):
    _, files = take
    init = ["--auto-init"] if "auto_min_views" in " ".join(argv) else ["--seeds", str(files["seeds"])]
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), *init,
                 "--out", str(tmp_path / "x.cara"), "--no-progress", *argv])
    _, err = capsys.readouterr()
    assert code == 1 and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.cara").exists()


def test_pipeline_undoes_back_to_the_imported_take(take):
    import copy

    from carapost.ops.change import take_diff
    from carapost.ops.pipeline import PipelineOptions, run_pipeline
    from carapost.ops.session import Session

    _, files = take
    with Session.from_sources(picos(files), files["xcp"]) as s:
        before = copy.deepcopy(s.take)
        run_pipeline(s, PipelineOptions(seeds=files["seeds"], brim="v2.0"))
        after = copy.deepcopy(s.take)
        assert s.take.n_points > 30
        while s.stack.can_undo():
            s.stack.undo()
        assert take_diff(s.take, before) == []
        while s.stack.can_redo():
            s.stack.redo()
        assert take_diff(s.take, after) == []


@pytest.fixture(scope="module")
def moving_take(tmp_path_factory):
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=35, n_frames=12, seed=5))
    return synth, write_take(synth, tmp_path_factory.mktemp("track"), "T")


def test_process_tracks_fills_and_stabilizes(capsys, moving_take, tmp_path):
    synth, files = moving_take
    out = tmp_path / "t.cara"
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--brim",
                 str(files["brim_json"]), "--seeds", str(files["seeds"]), "--track", "--fill", "--stabilize",
                 "--out", str(out), "--no-progress", "--json"])
    text, err = capsys.readouterr()
    assert code == 0, err
    summary = json.loads(text.strip().splitlines()[-1])
    stages = {s["stage"]: s for s in summary["stages"]}
    assert list(stages)[-3:] == ["track", "interpolate gaps", "stabilize"]
    assert stages["track"]["frames"] == 11 and stages["stabilize"]["points"] >= 3

    from carapost.io.cara import load_take
    from carapost.synth.evaluate import score_points

    t = load_take(out).take
    seeded = np.isfinite(t.xyz[0, t.face_points()]).all(-1)
    ps = score_points(t, synth.truth)
    assert ps.swaps == 0 and ps.mismatched_observations == 0
    assert ps.median_error_mm < 0.2
    # every point initialized at the seeds' frame has a position (tracked or filled) in every frame
    assert np.isfinite(t.xyz[:, t.face_points()[seeded]]).all()
    assert np.isfinite(t.xyz_stabilized[:, t.face_points()[seeded]]).all()


def test_process_rom_excludes_seeds(capsys, take, tmp_path):
    _, files = take
    with pytest.raises(SystemExit) as exc:  # argparse: usage error, exit status 2
        main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--seeds",
              str(files["seeds"]), "--rom", str(tmp_path / "rom.cara"), "--out", str(tmp_path / "x.cara")])
    assert exc.value.code == 2 and "not allowed with" in capsys.readouterr().err


def test_process_initializes_from_a_rom_take(capsys, take, moving_take, tmp_path):
    """A ROM processed from its seeds initializes another take of the same actor (other seed:
    other expression and helmet position), which is then tracked."""
    _, rom_files = take
    synth, files = moving_take
    rom = tmp_path / "rom.cara"
    assert main(["process", "--cameras", *picos(rom_files), "--calibration", str(rom_files["xcp"]), "--brim",
                 str(rom_files["brim_json"]), "--seeds", str(rom_files["seeds"]), "--out", str(rom),
                 "--no-progress"]) == 0
    out = tmp_path / "shot.cara"
    code = main(["process", "--cameras", *picos(files), "--calibration", str(files["xcp"]), "--rom", str(rom),
                 "--track", "--out", str(out), "--no-progress", "--json"])
    text, err = capsys.readouterr()
    assert code == 0, err
    stages = {s["stage"]: s for s in json.loads(text.strip().splitlines()[-1])["stages"]}

    from carapost.io.cara import load_take
    from carapost.synth.evaluate import score_points

    rom_points = load_take(rom).take.face_points().size
    assert stages["initialize from ROM"]["points"] >= 0.9 * rom_points
    t = load_take(out).take
    ps = score_points(t, synth.truth)
    assert ps.swaps == 0 and ps.mismatched_observations == 0 and ps.median_error_mm < 0.2
