"""Batch processing: find takes, run steps on each in parallel, skip what is up to date.

* :func:`find_takes` (:mod:`carapost.ops.batch_jobs`) turns patterns (folders, searched
  recursively; wildcards; ``.pico`` files, grouped into takes by name; ``.cara`` projects) into
  :class:`TakeJob` s; :class:`BatchOptions` says what to do with them.
* :func:`run_job` runs the requested steps (:mod:`carapost.ops.batch_steps`) on one take,
  saves ``<take>.cara`` and writes its manifest ``<take>.carapost.json``. It never raises for
  a take's failure: the result dict says what went wrong.
* :func:`run_batch` decides per take whether it is up to date (:func:`job_plan`), then runs the
  jobs on a pool (:mod:`carapost.ops.batch_pool`: inline, local processes, or Dask), splitting
  blob detection by frame range across the workers when there are fewer takes than workers.

Idempotence: the manifest records the steps and options (the *recipe*) and the size and
modification time of every input and output. A take is skipped when its manifest is complete,
has the same recipe, and every input and output is as recorded. An existing ``.cara`` that
batch did not write (or that was changed since, e.g. edited in the GUI) is never overwritten
without ``force``: the take is skipped with a message saying so.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from .batch_pool import Pool, limit_threads, open_pool
from .batch_jobs import CALIBRATION_EXTENSIONS, BatchOptions, TakeJob, find_takes
from .batch_steps import STEPS, JobContext, resolve_steps

__all__ = ["TakeJob", "BatchOptions", "find_takes", "job_plan", "run_job", "run_batch", "manifest_path",
           "read_manifest", "MANIFEST_SUFFIX", "CALIBRATION_EXTENSIONS"]

log = logging.getLogger("carapost")

MANIFEST_SUFFIX = ".carapost.json"
MANIFEST_FORMAT = "carapost-batch-manifest"
MANIFEST_VERSION = 1


# -------------------------------------------------------------------------------------------
# manifests
# -------------------------------------------------------------------------------------------
def manifest_path(output: str | os.PathLike) -> Path:
    """``<folder>/<take>.carapost.json`` for the output ``<folder>/<take>.cara``."""
    p = Path(output)
    return p.with_name(p.stem + MANIFEST_SUFFIX)


def _stat(path: str | os.PathLike) -> list[int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return [int(st.st_size), int(st.st_mtime_ns)]


def read_manifest(output: str | os.PathLike) -> dict[str, Any] | None:
    """The manifest of an output ``.cara``, or None if missing or unreadable."""
    try:
        doc = json.loads(manifest_path(output).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT or doc.get("version") != MANIFEST_VERSION:
        return None
    return doc


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    from carapost.io.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(doc, indent=1, default=str) + "\n")


def _watched(job: TakeJob, options: BatchOptions) -> list[str]:
    """Input files whose change makes the take out of date."""
    files = [i for i in job.inputs if Path(i) != Path(job.output)]
    if job.kind == "pico" and job.calibration:
        files.append(job.calibration)
    if "init" in options.steps:
        files += [f for f in (job.seeds, job.brim) if f and Path(f).suffix.lower() in (".json", ".svg")]
    return files


def job_plan(job: TakeJob, options: BatchOptions) -> tuple[str, str]:
    """``("run" | "skip" | "error", reason)`` for a take, from its manifest and files."""
    if job.problem:
        return "error", job.problem
    if options.force:
        return "run", "forced"
    out = Path(job.output)
    in_place = job.kind == "cara" and Path(job.inputs[0]) == out
    if not out.exists():
        return "run", "no output yet"
    man = read_manifest(out)
    if man is None:
        if in_place:
            return "run", "not processed by carapost batch yet"
        return "skip", f"{out} exists and was not written by carapost batch: kept (--force overwrites it)"
    if man.get("state") != "done":
        return "run", "the previous run did not finish"
    if man.get("outputs", {}).get(str(out)) != _stat(out):
        if in_place:
            return "run", f"{out.name} changed since the last batch run"
        return "skip", f"{out} was changed after carapost batch wrote it: kept (--force overwrites it)"
    if man.get("recipe") != json.loads(json.dumps(options.recipe(job))):
        return "run", "steps or options changed"
    recorded = man.get("inputs", {})
    for f in _watched(job, options):
        if recorded.get(f) != _stat(f):
            return "run", f"input changed: {f}"
    for f, st in man.get("outputs", {}).items():
        if _stat(f) != st:
            return "run", f"output missing or changed: {f}"
    return "skip", "up to date"


# -------------------------------------------------------------------------------------------
# one take
# -------------------------------------------------------------------------------------------
class _Capture(logging.Handler):
    """Collects the carapost log records of a job (sent back to the batch's log)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[tuple[int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.records.append((record.levelno, record.getMessage()))
        except Exception:  # pragma: no cover - a bad format string in a log call
            self.handleError(record)


@contextlib.contextmanager
def _captured_log() -> Iterator[_Capture]:
    """Capture the ``carapost`` logger's INFO and above while the block runs."""
    logger = logging.getLogger("carapost")
    cap, old_level = _Capture(), logger.level
    logger.addHandler(cap)
    if logger.getEffectiveLevel() > logging.INFO:
        logger.setLevel(logging.INFO)
    try:
        yield cap
    finally:
        logger.removeHandler(cap)
        logger.setLevel(old_level)


def _result(job: TakeJob, status: str, **extra: Any) -> dict[str, Any]:
    return {"take": job.name, "kind": job.kind, "inputs": list(job.inputs), "output": job.output, "status": status,
            "reason": None, "error": None, "seconds": 0.0, "steps": [], "files": [], "messages": [], **extra}


def _open_session(job: TakeJob, options: BatchOptions) -> Any:
    """The take's session with ``options``' preset, settings and caddies applied."""
    from .session import Session
    from .settings import apply_settings

    session = Session.open(job.inputs[0]) if job.kind == "cara" else \
        Session.from_sources(list(job.inputs), job.calibration, name=job.name)
    try:
        apply_settings(session, preset=options.preset, settings=options.settings, caddies=options.caddies)
    except ValueError:
        session.close()
        raise
    return session


def run_job(job: TakeJob, options: BatchOptions, detections: dict[str, Any] | None = None) -> dict[str, Any]:
    """Run ``options.steps`` on one take; save its ``.cara`` and manifest.

    Does not check whether the take is up to date or whether its output may be overwritten:
    :func:`run_batch` does (:func:`job_plan`) before calling it.

    Parameters
    ----------
    job : TakeJob
    options : BatchOptions
    detections : dict, optional
        Blob detections computed by split detection (see :class:`JobContext`).

    Returns
    -------
    dict
        ``take, kind, inputs, output, status ("done" | "error"), error, seconds, steps (one dict
        per step: name, seconds, numbers), files, messages, log`` (and ``traceback`` for an
        unexpected exception). Nothing is saved when a step fails; the manifest then says
        ``"state": "failed"``.
    """
    t0 = time.perf_counter()
    res = _result(job, "error")
    with _captured_log() as cap, limit_threads(1):  # parallelism is explicit: workers x threads
        _run_steps(job, options, detections, res, t0)
    res["seconds"] = round(time.perf_counter() - t0, 3)
    res["log"] = [[logging.getLevelName(lv), msg] for lv, msg in cap.records]
    return res


def _run_steps(job: TakeJob, options: BatchOptions, detections: dict[str, Any] | None, res: dict[str, Any],
               t0: float) -> None:
    from carapost import __version__

    stage = "open"
    steps, skipped = resolve_steps(options.steps)
    out, mpath = Path(job.output), manifest_path(job.output)
    man: dict[str, Any] = {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "carapost": __version__,
                           "take": job.name, "output": str(out), "state": "started", "recipe": options.recipe(job)}
    try:
        if job.problem:
            raise ValueError(job.problem)
        man.update(inputs={f: _stat(f) for f in _watched(job, options)}, started=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        missing = [f for f, st in man["inputs"].items() if st is None]
        if missing:
            raise ValueError(f"missing input file(s): {', '.join(missing)}")
        out.parent.mkdir(parents=True, exist_ok=True)
        stage = "manifest"
        _write_json(mpath, man)
        stage = "open"
        with _open_session(job, options) as session:
            res["messages"] += session.messages
            ctx = JobContext(session, job, options, detections)
            for name in steps:
                stage = name
                t = time.perf_counter()
                numbers = STEPS[name].run(ctx) or {}
                res["steps"].append({"step": name, "seconds": round(time.perf_counter() - t, 3), **numbers})
            res["messages"] += ctx.messages + [f"step {k} skipped: {why}" for k, why in skipped.items()]
            stage = "save"
            session.save(out)
        stage = "manifest"
        res["files"] = [str(out), *ctx.files]
        man.update(state="done", outputs={f: _stat(f) for f in res["files"]}, steps=res["steps"],
                   seconds=round(time.perf_counter() - t0, 3))
        _write_json(mpath, man)
        res["status"] = "done"
    except Exception as exc:  # one take's failure must not stop the batch: report it
        expected = isinstance(exc, (ValueError, OSError, KeyError, IndexError))
        res["error"] = f"{stage}: {exc}" if expected else f"{stage}: {type(exc).__name__}: {exc}"
        if not expected:
            res["traceback"] = traceback.format_exc()
        if mpath.exists():
            try:
                _write_json(mpath, {**man, "state": "failed", "error": res["error"]})
            except OSError:
                pass


# -------------------------------------------------------------------------------------------
# many takes
# -------------------------------------------------------------------------------------------
def _detect_plan(job: TakeJob, options: BatchOptions) -> tuple[Any, list[int]]:
    """The :class:`~carapost.ops.split_detect.DetectTask` of a take and its undetected frames."""
    from .batch_steps import _undetected
    from .split_detect import detect_task

    if job.problem:
        raise ValueError(job.problem)
    with _open_session(job, options) as session:
        return detect_task(session.take, session.sources), _undetected(session.take)


def _relog(job: TakeJob, res: dict[str, Any], remote: bool) -> None:
    if remote:  # records of a job run here went through this process's handlers already
        for name, msg in res.get("log", []):
            level = logging.getLevelName(name)
            log.log(level if isinstance(level, int) else logging.INFO, "%s: %s", job.name, msg)
    if res["status"] == "done":
        log.info("%s: done in %.1f s (%s)", job.name, res["seconds"], ", ".join(s["step"] for s in res["steps"]))
    elif res["status"] == "skipped":
        log.info("%s: skipped: %s", job.name, res["reason"])
    else:
        log.error("%s: failed: %s", job.name, res["error"])
        if res.get("traceback"):
            log.info("%s: %s", job.name, res["traceback"])


def run_batch(jobs: Sequence[TakeJob], options: BatchOptions, *, workers: int = 1, scheduler: Any = None,
              pool: Pool | None = None, on_result: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Process takes: skip the up-to-date ones, run the others on a pool.

    Parameters
    ----------
    jobs : sequence of TakeJob
        From :func:`find_takes`.
    options : BatchOptions
    workers : int
        Local worker processes (1: run in this process).
    scheduler : str or distributed.Client, optional
        A Dask scheduler address: jobs run on its cluster instead (``workers`` is ignored).
    pool : Pool, optional
        An open pool to use instead (not closed).
    on_result : callable, optional
        Called with each take's result as it finishes (skipped takes first).

    Returns
    -------
    list of dict
        One result per job, in the order of ``jobs`` (see :func:`run_job`; skipped takes have
        ``status="skipped"`` and a ``reason``).
    """
    results: list[dict[str, Any] | None] = [None] * len(jobs)

    def finish(i: int, res: dict[str, Any], remote: bool = False) -> None:
        _relog(jobs[i], res, remote)
        results[i] = res
        if on_result is not None:
            on_result(res)

    to_run = []
    for i, job in enumerate(jobs):
        action, reason = job_plan(job, options)
        if action == "run":
            log.info("%s: running (%s)", job.name, reason)
            to_run.append(i)
        else:
            finish(i, _result(job, "skipped", reason=reason) if action == "skip" else _result(job, "error", error=reason))
    if to_run:
        own = pool is None
        p = open_pool(workers, scheduler) if pool is None else pool
        try:
            _run_on(p, jobs, options, to_run, finish)
        finally:
            if own:
                p.close()
    return [r for r in results if r is not None]


def _run_on(pool: Pool, jobs: Sequence[TakeJob], options: BatchOptions, to_run: list[int],
            finish: Callable[..., None]) -> None:
    """Submit the jobs (and, when splitting, their detection chunks first) and collect them."""
    from .split_detect import detect_chunk, frame_chunks

    split = "detect" in resolve_steps(options.steps)[0] and (
        options.split_detect == "on" or (options.split_detect == "auto" and len(to_run) < pool.workers))
    pending: dict[Any, tuple[str, int]] = {}
    parts: dict[int, dict[str, Any]] = {}
    t_start: dict[int, float] = {}

    def fail(i: int, error: str) -> None:
        mine = [h for h, (_, j) in pending.items() if j == i]
        pool.cancel(mine)
        for h in mine:
            pending.pop(h)
        if i in parts:
            parts[i]["failed"] = True
        finish(i, _result(jobs[i], "error", error=error, seconds=round(time.perf_counter() - t_start[i], 3)))

    def submit(kind: str, i: int, fn: Callable[..., Any], *args: Any) -> bool:
        try:
            pending[pool.submit(fn, *args)] = (kind, i)
        except Exception as exc:  # a broken pool (a worker was killed), a lost scheduler
            fail(i, f"worker: {type(exc).__name__}: {exc}")
            return False
        return True

    for i in to_run:
        t_start[i] = time.perf_counter()
        if split:
            try:
                task, frames = _detect_plan(jobs[i], options)
            except (ValueError, OSError) as exc:
                fail(i, f"detect: {exc}")
                continue
            chunks = frame_chunks(frames, 2 * pool.workers)
            if chunks:
                parts[i] = {"left": len(chunks), "tables": {}, "chunks": len(chunks)}
                for ch in chunks:
                    if not submit("chunk", i, detect_chunk, task, ch):
                        break
                continue
        submit("job", i, run_job, jobs[i], options)
    try:
        while pending:
            done, _ = pool.wait_any(list(pending))
            for h in done:
                if h not in pending:  # dropped with its take's failure
                    continue
                kind, i = pending.pop(h)
                try:
                    value = pool.result(h)
                except Exception as exc:  # the worker died or the task raised
                    value = exc
                if kind == "job":
                    if isinstance(value, Exception):
                        fail(i, f"worker: {type(value).__name__}: {value}")
                        continue
                    if i in parts:  # the take's wall time includes its split detection
                        value["seconds"] = round(time.perf_counter() - t_start[i], 3)
                    finish(i, value, pool.remote)
                    continue
                st = parts[i]
                if st.get("failed"):
                    continue
                if isinstance(value, Exception):
                    fail(i, f"detect: {value}")
                    continue
                for c, tables in value.items():
                    st["tables"].setdefault(c, {}).update(tables)
                st["left"] -= 1
                if st["left"] == 0:
                    det = {"tables": st["tables"], "chunks": st["chunks"], "seconds": time.perf_counter() - t_start[i]}
                    submit("job", i, run_job, jobs[i], options, det)
    except BaseException:
        pool.cancel(list(pending))
        raise
