"""carapost batch: take discovery, per-take jobs, idempotent reruns, local processes, split
detection and a Dask cluster, on tiny synthetic takes (640x360, 3 frames, 35 markers)."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from carapost.ops.batch import BatchOptions, find_takes, job_plan, manifest_path, read_manifest, run_batch, run_job
from carapost.ops.batch_pool import DaskPool
from carapost.ops.batch_steps import STEPS, Step, resolve_steps
from carapost.ops.split_detect import detect_blobs_split, frame_chunks

N_FRAMES = 3


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A tiny take written as a capture folder, and its blob detections made in this process."""
    from carapost.ops.detect import detect_blobs
    from carapost.ops.session import Session
    from carapost.synth import SynthConfig, generate_take, write_take

    synth = generate_take(SynthConfig(n_markers=35, n_frames=N_FRAMES, width=640, height=360, seed=3))
    folder = tmp_path_factory.mktemp("capture")
    files = write_take(synth, folder, "T")
    with Session.from_sources([files[f"pico_{c}"] for c in range(4)], files["xcp"], name="T") as s:
        change = detect_blobs(s.take, s.image, range(N_FRAMES), workers=1)
    reference = {ch.camera: ch.new for ch in change.changes}
    assert sum(len(t["x"]) for tabs in reference.values() for t in tabs.values()) > 100
    return folder, reference


def put_take(capture, folder: Path, name: str, *, seeds: bool = True) -> Path:
    """Copy the capture's files into ``folder`` as take ``name``."""
    src, _ = capture
    folder.mkdir(parents=True, exist_ok=True)
    for f in src.iterdir():
        if f.name.startswith("T_truth"):
            continue
        if f.name.startswith("T_seeds") and not seeds:
            continue
        shutil.copy2(f, folder / (name + f.name[1:]))
    return folder


def assert_same_detections(cara: Path, reference: dict) -> None:
    from carapost.io.cara import load_take

    take = load_take(cara).take
    for c, tabs in reference.items():
        det = take.detections[c]
        assert det.detected.all()
        for f, tab in tabs.items():
            got = det.frame(f)
            for k in ("x", "y", "major", "minor", "score"):
                np.testing.assert_array_equal(got[k], tab[k], err_msg=f"camera {c} frame {f} {k}")


def cli(argv: list[str]) -> int:
    """``carapost.cli.main`` with the batch command (wired here if the CLI does not have it yet)."""
    from carapost import cli as cli_mod
    from carapost.commands import batch as batch_cmd
    from carapost.commands import process

    _, commands = cli_mod._parser()
    if "batch" in commands:
        return cli_mod.main(argv)
    orig = process.add_parsers
    process.add_parsers = lambda sub: {**orig(sub), **batch_cmd.add_parsers(sub)}
    try:
        return cli_mod.main(argv)
    finally:
        process.add_parsers = orig


def last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


# ----------------------------------------------------------------------------------- discovery
def test_find_takes_folders_wildcards_pico_and_cara(capture, tmp_path):
    root = tmp_path / "jobs"
    put_take(capture, root / "a", "A")
    put_take(capture, root / "b" / "c", "Take10")
    put_take(capture, root / "b" / "c", "Take9", seeds=False)
    (root / "a" / "A.cara").write_bytes(b"output of A")            # the output of take A, not a take
    (root / "d").mkdir()
    (root / "d" / "Solo.cara").write_bytes(b"a project")
    (root / ".hidden").mkdir()
    put_take(capture, root / ".hidden", "H")

    jobs = find_takes([root])
    assert [(j.name, j.kind) for j in jobs] == [("A", "pico"), ("Take9", "pico"), ("Take10", "pico"),
                                                ("Solo", "cara")]
    a = jobs[0]
    assert a.inputs == tuple(str((root / "a" / f"A_{c}.pico").resolve()) for c in range(4))
    assert a.output == str((root / "a" / "A.cara").resolve())
    assert a.calibration.endswith("A.xcp") and a.seeds.endswith("A_seeds.json") and a.brim.endswith("A_brim.json")
    assert jobs[1].seeds is None and jobs[3].output == str((root / "d" / "Solo.cara").resolve())

    # a wildcard naming one channel stands for the whole take
    (j,) = find_takes([str(root / "**" / "Take1*_2.pico")])
    assert j.name == "Take10" and len(j.inputs) == 4
    (j,) = find_takes([root / "a" / "A_0.pico"])
    assert j.name == "A"
    # --out, --calibration and --brim apply to every take
    out = tmp_path / "out"
    jobs = find_takes([root / "a", root / "d" / "Solo.cara"],
                      BatchOptions(out_dir=str(out), calibration=str(root / "a" / "A.xcp"), brim="v2.0"))
    assert [j.output for j in jobs] == [str(out.resolve() / "A.cara"), str(out.resolve() / "Solo.cara")]
    assert all(j.brim == "v2.0" for j in jobs) and jobs[0].calibration == str((root / "a" / "A.xcp").resolve())


def test_find_takes_clashes_and_errors(capture, tmp_path):
    put_take(capture, tmp_path / "x", "A")
    put_take(capture, tmp_path / "y", "A")
    jobs = find_takes([tmp_path], BatchOptions(out_dir=str(tmp_path / "out")))
    assert len(jobs) == 2 and all("would also be written" in j.problem for j in jobs)
    assert job_plan(jobs[0], BatchOptions())[0] == "error"
    assert all(j.problem is None for j in find_takes([tmp_path]))  # next to their sources: no clash

    with pytest.raises(ValueError, match="nope: no such file or folder"):
        find_takes([tmp_path / "nope"])
    with pytest.raises(ValueError, match="A.xcp: not a take"):
        find_takes([tmp_path / "x" / "A.xcp"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no takes"):
        find_takes([tmp_path / "empty", str(tmp_path / "zz*")])


def test_steps_registry_and_options():
    assert list(STEPS) == ["detect", "init", "track", "fill", "export"]
    assert resolve_steps(["export", "detect"]) == (("detect", "export"), {})
    with pytest.raises(ValueError, match=r"unknown step\(s\): tracc .*known steps: detect, init, track"):
        resolve_steps(["detect", "tracc"])
    opt = BatchOptions(steps=("export", "Detect"), formats=("FBX", ".c3d"))
    assert opt.steps == ("detect", "export") and opt.formats == ("fbx", "c3d")
    for bad in (dict(formats=("obj",)), dict(fill_method="cubic"), dict(split_detect="maybe"), dict(threads=0),
                dict(steps=())):
        with pytest.raises(ValueError):
            BatchOptions(**bad)


def test_frame_chunks():
    assert frame_chunks(range(10), 3) == [[0, 1, 2], [3, 4, 5, 6], [7, 8, 9]]
    assert frame_chunks([5, 1, 1, 3], 8) == [[1], [3], [5]]
    assert frame_chunks([], 2) == []
    with pytest.raises(ValueError):
        frame_chunks([1], 0)


# ------------------------------------------------------------------------------ jobs, reruns
def test_batch_detect_then_rerun_skips_until_something_changes(capture, tmp_path):
    _, reference = capture
    put_take(capture, tmp_path / "a", "A")
    put_take(capture, tmp_path / "b", "B")
    jobs = find_takes([tmp_path])
    seen = []
    res = run_batch(jobs, BatchOptions(), on_result=lambda r: seen.append(r["take"]))
    assert [r["status"] for r in res] == ["done", "done"] and sorted(seen) == ["A", "B"]
    assert res[0]["steps"][0]["step"] == "detect" and res[0]["steps"][0]["frames"] == N_FRAMES
    for r in res:
        assert_same_detections(Path(r["output"]), reference)
        man = read_manifest(r["output"])
        assert man["state"] == "done" and man["recipe"]["steps"] == ["detect"]
        assert set(man["inputs"]) == set(r["inputs"]) | {str(Path(r["output"]).with_suffix(".xcp"))}

    again = run_batch(jobs, BatchOptions())
    assert [(r["status"], r["reason"]) for r in again] == [("skipped", "up to date")] * 2

    st = os.stat(jobs[1].inputs[2])  # a re-captured camera file
    os.utime(jobs[1].inputs[2], ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert job_plan(jobs[1], BatchOptions()) == ("run", f"input changed: {jobs[1].inputs[2]}")
    assert [r["status"] for r in run_batch(jobs, BatchOptions())] == ["skipped", "done"]

    assert job_plan(jobs[0], BatchOptions(steps=("detect", "export")))[1] == "steps or options changed"
    assert [r["status"] for r in run_batch(jobs[:1], BatchOptions(force=True))] == ["done"]
    os.unlink(jobs[0].output)
    assert job_plan(jobs[0], BatchOptions()) == ("run", "no output yet")


def test_outputs_batch_did_not_write_are_kept(capture, tmp_path):
    put_take(capture, tmp_path, "A")
    (job,) = find_takes([tmp_path])
    Path(job.output).write_bytes(b"made in the GUI")
    (res,) = run_batch([job], BatchOptions())
    assert res["status"] == "skipped" and "not written by carapost batch: kept" in res["reason"]
    assert Path(job.output).read_bytes() == b"made in the GUI"

    (res,) = run_batch([job], BatchOptions(force=True))
    assert res["status"] == "done"
    st = os.stat(job.output)  # edited by hand after the batch wrote it
    os.utime(job.output, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    action, reason = job_plan(job, BatchOptions())
    assert action == "skip" and "changed after carapost batch wrote it" in reason

    man = json.loads(manifest_path(job.output).read_text())
    man["state"] = "started"  # the previous run was interrupted
    manifest_path(job.output).write_text(json.dumps(man))
    assert job_plan(job, BatchOptions()) == ("run", "the previous run did not finish")


def test_cara_project_in_place_and_unavailable_steps(capture, tmp_path, monkeypatch):
    put_take(capture, tmp_path / "src", "A")
    (res,) = run_batch(find_takes([tmp_path / "src"]), BatchOptions())
    solo = tmp_path / "solo" / "Solo.cara"
    solo.parent.mkdir()
    shutil.copy2(res["output"], solo)  # a project with detections, never seen by batch
    (job,) = find_takes([solo])
    assert job.kind == "cara" and job.output == str(solo.resolve())
    assert job_plan(job, BatchOptions()) == ("run", "not processed by carapost batch yet")

    monkeypatch.setitem(STEPS, "track", Step("track", STEPS["track"].run, available=lambda: "no tracker here"))
    opt = BatchOptions(steps=("detect", "track", "fill"))
    assert resolve_steps(opt.steps) == (("detect", "fill"), {"track": "no tracker here"})
    (res,) = run_batch([job], opt)
    assert res["status"] == "done", res["error"]
    assert [s["step"] for s in res["steps"]] == ["detect", "fill"]
    assert res["steps"][0]["frames"] == 0  # everything was detected already: nothing redone
    assert "step track skipped: no tracker here" in res["messages"]
    assert res["files"] == [str(solo.resolve())]
    assert read_manifest(solo)["outputs"] == {str(solo.resolve()): [solo.stat().st_size, solo.stat().st_mtime_ns]}
    assert run_batch([job], opt)[0]["reason"] == "up to date"


def test_failures_are_per_take_and_name_the_step(capture, tmp_path):
    put_take(capture, tmp_path / "a", "A", seeds=False)
    (tmp_path / "c").mkdir()
    for ch in range(2):
        (tmp_path / "c" / f"C_{ch}.pico").write_bytes(b"not a pico file")
    jobs = find_takes([tmp_path])
    res = run_batch(jobs, BatchOptions(steps=("detect", "init")))
    a, c = res
    assert a["status"] == "error" and a["error"].startswith("init: no seeds file (A_seeds.json")
    assert [s["step"] for s in a["steps"]] == ["detect"]  # what ran before the failure is reported
    assert not Path(a["output"]).exists()  # nothing saved for a failed take
    assert read_manifest(a["output"])["state"] == "failed"
    assert c["status"] == "error" and c["error"].startswith("open: ") and "C_0.pico" in c["error"]
    # with detection split by frames (here run inline), the failure is the detect step's
    a, c = run_batch(jobs, BatchOptions(split_detect="on"))
    assert a["status"] == "done" and a["steps"][0]["split_chunks"] == 2
    assert c["status"] == "error" and c["error"].startswith("detect: ") and "C_0.pico" in c["error"]
    assert job_plan(jobs[0], BatchOptions(steps=("detect", "init")))[0] == "run"
    # an unexpected exception is reported with its traceback, not raised
    bad = BatchOptions(steps=("detect",))
    object.__setattr__(bad, "threads", "two")
    r = run_job(jobs[0], bad)
    assert r["status"] == "error" and r["error"].startswith("detect: TypeError") and "Traceback" in r["traceback"]


def test_settings_reach_every_take_and_the_split_detection(capture, tmp_path):
    import dataclasses

    from carapost.io.cara import load_take

    _, reference = capture
    put_take(capture, tmp_path / "a", "A")
    jobs = find_takes([tmp_path])
    opts = BatchOptions(settings=(("blobs", "Black Threshold", "0.9"),), caddies=())
    (r,) = run_batch(jobs, opts)
    assert r["status"] == "done", r["error"]
    take = load_take(r["output"]).take
    assert take.params.blobs.black_threshold == 0.9 and take.caddies == []
    n_strict = sum(len(d) for d in take.detections)
    assert n_strict < sum(len(t["x"]) for tabs in reference.values() for t in tabs.values())
    assert read_manifest(r["output"])["recipe"]["settings"]["set"] == [["blobs", "Black Threshold", "0.9"]]
    assert job_plan(jobs[0], opts) == ("skip", "up to date")
    assert job_plan(jobs[0], BatchOptions()) == ("run", "steps or options changed")
    (r,) = run_batch(jobs, dataclasses.replace(opts, split_detect="on", force=True))
    assert r["status"] == "done" and r["steps"][0]["split_chunks"] == 2
    assert sum(len(d) for d in load_take(r["output"]).take.detections) == n_strict
    (r,) = run_batch(jobs, BatchOptions(settings=(("blobs", "no_such_thing", "1"),), force=True))
    assert r["status"] == "error" and r["error"].startswith("open: settings: Blob Parameters: no property")


# -------------------------------------------------------------------------------- command line
def test_cli_batch_json_dry_run_and_exit_codes(capture, tmp_path, capsys):
    _, reference = capture
    put_take(capture, tmp_path / "a", "A")
    log = tmp_path / "batch.log"
    code = cli(["batch", str(tmp_path), "--dry-run", "--json", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 0 and last_json(out)["takes"][0]["action"] == "run"

    code = cli(["batch", str(tmp_path), "--steps", "detect,fill", "--json", "--no-progress", "--log", str(log)])
    out, err = capsys.readouterr()
    assert code == 0, err
    summary = last_json(out)
    assert (summary["done"], summary["skipped"], summary["failed"]) == (1, 0, 0)
    (t,) = summary["takes"]
    assert t["status"] == "done" and t["seconds"] > 0 and [s["step"] for s in t["steps"]] == ["detect", "fill"]
    assert t["files"] == [str((tmp_path / "a" / "A.cara").resolve())]
    assert_same_detections(tmp_path / "a" / "A.cara", reference)
    assert "A: done in" in log.read_text()

    code = cli(["batch", str(tmp_path), "--steps", "fill,detect", "--formats", "fbx", "--json", "--no-progress"])
    assert code == 0 and last_json(capsys.readouterr().out)["takes"][0]["reason"] == "up to date"

    for ch in range(4):
        (tmp_path / "b").mkdir(exist_ok=True)
        (tmp_path / "b" / f"B_{ch}.pico").write_bytes(b"broken")
    code = cli(["batch", str(tmp_path), "--steps", "detect,fill", "--json", "--no-progress"])
    out, err = capsys.readouterr()
    assert code == 1
    summary = last_json(out)
    assert [t["status"] for t in summary["takes"]] == ["skipped", "error"] and summary["failed"] == 1
    assert err.strip().splitlines()[-1] == "carapost batch: error: 1 of 2 take(s) failed: B"

    code = cli(["batch", str(tmp_path), "--steps", "detect,bogus"])
    err = capsys.readouterr().err
    assert code == 1 and "unknown step(s): bogus" in err and err.count("\n") == 1
    assert cli(["batch", str(tmp_path / "missing")]) == 1
    assert "missing: no such file or folder" in capsys.readouterr().err


def test_full_steps_with_seeds(tmp_path):
    """detect, init (brim + seeds), track, fill, export on a 1280x720 take, checked against truth."""
    from carapost.io.cara import load_take
    from carapost.synth import SynthConfig, generate_take, write_take
    from carapost.synth.evaluate import score_points

    synth = generate_take(SynthConfig(n_markers=35, n_frames=2, seed=4))
    write_take(synth, tmp_path, "F")
    (res,) = run_batch(find_takes([tmp_path]), BatchOptions(steps=("detect", "init", "track", "fill", "export"),
                                                             formats=("c3d", "fbx")))
    assert res["status"] == "done", res["error"]
    steps = {s["step"]: s for s in res["steps"]}
    assert list(steps) == ["detect", "init", "track", "fill", "export"]
    assert steps["init"]["points"] >= 0.7 * 35
    take = load_take(res["output"]).take
    score = score_points(take, synth.truth)
    assert score.mismatched_observations == 0 and score.median_error_mm < 0.3
    assert steps["track"]["point_frames"] >= 2 * steps["init"]["points"] * 0.9
    assert all(Path(f).stat().st_size > 0 for f in res["files"])


# ------------------------------------------------------------------- processes, split, Dask
def test_split_detection_matches_in_process_detection(capture):
    from carapost.ops.session import Session

    folder, reference = capture
    with Session.from_sources([folder / f"T_{c}.pico" for c in range(4)], folder / "T.xcp") as s:
        frames = []
        change = detect_blobs_split(s.take, range(N_FRAMES), workers=2, cameras=[0, 2, 3],
                                    progress=lambda d, t: frames.append((d, t)))
        assert [ch.camera for ch in change.changes] == [0, 2, 3]
        for ch in change.changes:
            assert sorted(ch.new) == list(range(N_FRAMES))
            for f, tab in ch.new.items():
                np.testing.assert_array_equal(tab["x"], reference[ch.camera][f]["x"])
        assert frames[-1] == (3 * N_FRAMES, 3 * N_FRAMES)
        s.apply(change)
        assert s.take.detections[2].detected.all() and not s.take.detections[1].detected.any()
        s.stack.undo()
        assert not s.take.detections[2].detected.any()
        with pytest.raises(ValueError, match="outside the take"):
            detect_blobs_split(s.take, [N_FRAMES], workers=1)
        s.sources[1].source.close()
        s.sources[1] = None  # a moved video
        with pytest.raises(ValueError, match="camera 1 .* has no video"):
            detect_blobs_split(s.take, [0], sources=s.sources, workers=1)


def test_local_processes_with_and_without_split(capture, tmp_path):
    _, reference = capture
    put_take(capture, tmp_path / "a", "A")
    put_take(capture, tmp_path / "b", "B")
    jobs = find_takes([tmp_path])
    res = run_batch(jobs, BatchOptions(), workers=2)  # two takes, two workers: one take per worker
    assert [r["status"] for r in res] == ["done", "done"]
    assert all("split_chunks" not in r["steps"][0] for r in res)
    assert_same_detections(Path(res[1]["output"]), reference)

    (r,) = run_batch(jobs[:1], BatchOptions(force=True), workers=2)  # one take: detection split by frames
    assert r["status"] == "done" and r["steps"][0]["split_chunks"] == N_FRAMES
    assert_same_detections(Path(r["output"]), reference)


def test_dask_local_cluster(capture, tmp_path, capsys):
    distributed = pytest.importorskip("distributed")
    _, reference = capture
    put_take(capture, tmp_path / "a", "A")
    put_take(capture, tmp_path / "b", "B")
    t0 = time.perf_counter()
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        code = cli(["batch", str(tmp_path), "--scheduler", cluster.scheduler_address, "--json", "--no-progress"])
        out, err = capsys.readouterr()
        assert code == 0, err
        summary = last_json(out)
        assert summary["where"] == cluster.scheduler_address and summary["workers"] == 2
        assert [t["status"] for t in summary["takes"]] == ["done", "done"]
        (r,) = run_batch(find_takes([tmp_path / "b"]), BatchOptions(force=True, split_detect="on"),
                         scheduler=cluster.scheduler_address)
        assert r["status"] == "done" and r["steps"][0]["split_chunks"] >= 2
    for name in ("A", "B"):
        assert_same_detections(tmp_path / name.lower() / f"{name}.cara", reference)
    with pytest.raises(ValueError, match="cannot connect to the Dask scheduler tcp://127.0.0.1:1"):
        DaskPool("tcp://127.0.0.1:1", timeout=0.5)
    assert time.perf_counter() - t0 < 60
