"""Batch jobs: what to do (:class:`BatchOptions`) and to which takes (:class:`TakeJob`,
found by :func:`find_takes` from folders, wildcards, ``.pico`` files and ``.cara`` projects).

See :mod:`carapost.ops.batch` for running them.
"""

from __future__ import annotations

import dataclasses
import glob
import logging
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from carapost.io.pico import CALIBRATION_EXTENSIONS
from carapost.model.params import FILL_METHODS

from .batch_steps import EXPORT_FORMATS, STEPS, resolve_steps

__all__ = ["TakeJob", "BatchOptions", "find_takes", "CALIBRATION_EXTENSIONS", "FILL_METHODS"]

log = logging.getLogger("carapost")

_GLOB_CHARS = re.compile(r"[*?\[]")


@dataclass(frozen=True)
class TakeJob:
    """One take to process.

    Attributes
    ----------
    name : str
        Take name (``NAME`` of ``NAME_0.pico``, or the ``.cara``'s stem).
    kind : {"pico", "cara"}
    inputs : tuple of str
        The ``.pico`` files in channel order, or the ``.cara``.
    output : str
        The ``.cara`` written (for a ``.cara`` input without ``--out``: the input itself).
    calibration, seeds, brim : str or None
        Calibration file (``.pico`` takes), seeds file, and brim (file or ``v1.0``/``v1.1``/``v2.0``).
    problem : str or None
        Why the take cannot run (e.g. two takes would write the same output).
    """

    name: str
    kind: str
    inputs: tuple[str, ...]
    output: str
    calibration: str | None = None
    seeds: str | None = None
    brim: str | None = None
    problem: str | None = None


@dataclass(frozen=True)
class BatchOptions:
    """What to do with every take.

    Attributes
    ----------
    steps : tuple of str
        Step names (see :data:`carapost.ops.batch_steps.STEPS`); run in the steps' fixed order.
    out_dir : str or None
        Write ``<take>.cara`` (and exports, manifest) here instead of next to the sources.
    calibration : str or None
        Calibration for every ``.pico`` take (default: ``<take>.xcp/.toml/.qca`` next to it).
    brim : str or None
        ``v1.0 | v1.1 | v2.0 | FILE.svg | FILE.json`` (default: ``<take>_brim.json/.svg`` next
        to the take, if any).
    auto_init : bool
        ``init`` without seeds (Initialize 3D automatically).
    frame : int or None
        Frame to initialize / track from (default: the seeds' frame, else 0).
    formats : tuple of str
        Export formats of the ``export`` step: ``"c3d"``, ``"fbx"``.
    fill_method : {"neighbours", "face_model", "blink"}
    force : bool
        Run even up-to-date takes and overwrite ``.cara`` files batch did not write.
    threads : int
        Threads per job for blob detection without split.
    split_detect : {"auto", "on", "off"}
        Split each take's blob detection by frame range across the workers: always, never, or
        when fewer takes than workers are to run.
    preset : str or None
        Parameter preset applied to every take when it is opened (``default | dense | sparse``).
    settings : tuple of (group, property, value)
        Properties set on every take when it is opened, after the preset
        (:func:`carapost.ops.settings.apply_settings`).
    caddies : tuple of camera pairs or None
        Caddies of every take (empty: none); None keeps each take's.
    """

    steps: tuple[str, ...] = ("detect",)
    out_dir: str | None = None
    calibration: str | None = None
    brim: str | None = None
    auto_init: bool = False
    frame: int | None = None
    formats: tuple[str, ...] = ("c3d",)
    fill_method: str = "neighbours"
    force: bool = False
    threads: int = 1
    split_detect: str = "auto"
    preset: str | None = None
    settings: tuple[tuple[str, str, str], ...] = ()
    caddies: tuple[tuple[int, int], ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "formats", tuple(dict.fromkeys(f.strip().lower().lstrip(".") for f in self.formats)))
        bad = [f for f in self.formats if f not in EXPORT_FORMATS]
        if bad or not self.formats:
            raise ValueError(f"export formats must be among {', '.join(EXPORT_FORMATS)}, got {', '.join(bad) or 'none'}")
        if self.fill_method not in FILL_METHODS:
            raise ValueError(f"fill method must be one of {', '.join(FILL_METHODS)}, got {self.fill_method!r}")
        if self.split_detect not in ("auto", "on", "off"):
            raise ValueError(f"split_detect must be 'auto', 'on' or 'off', got {self.split_detect!r}")
        if self.threads < 1:
            raise ValueError(f"threads must be at least 1, got {self.threads}")
        if self.frame is not None and self.frame < 0:
            raise ValueError(f"frame must be >= 0, got {self.frame}")
        wanted = {s.strip().lower() for s in self.steps}
        resolve_steps(list(wanted))  # raises for unknown steps, with the list of known steps
        object.__setattr__(self, "steps", tuple(s for s in STEPS if s in wanted))

    def recipe(self, job: TakeJob) -> dict[str, Any]:
        """What a take's outputs depend on besides its input files (compared on reruns)."""
        r: dict[str, Any] = {"steps": list(resolve_steps(self.steps)[0])}
        if self.preset is not None or self.settings or self.caddies is not None:
            r["settings"] = {"preset": self.preset, "set": [list(x) for x in self.settings],
                             "caddies": None if self.caddies is None else [list(x) for x in self.caddies]}
        if "init" in self.steps:
            r.update(seeds=job.seeds, brim=job.brim, auto_init=self.auto_init)
        if "init" in self.steps or "track" in self.steps:
            r["frame"] = self.frame
        if "fill" in self.steps:
            r["fill_method"] = self.fill_method
        if "export" in self.steps:
            r["formats"] = list(self.formats)
        if job.kind == "pico":
            r["calibration"] = job.calibration
        return r


# -------------------------------------------------------------------------------------------
# finding takes
# -------------------------------------------------------------------------------------------
def _natural(s: str) -> list[Any]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", s)]


def _walk(folder: Path) -> Iterable[Path]:
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted((d for d in dirs if not d.startswith(".")), key=_natural)
        for f in sorted(files, key=_natural):
            if not f.startswith("."):
                yield Path(root) / f


def _sibling(folder: Path, *names: str) -> str | None:
    for n in names:
        if (folder / n).is_file():
            return str(folder / n)
    return None


def find_takes(patterns: Sequence[str | os.PathLike], options: BatchOptions | None = None) -> list[TakeJob]:
    """The takes matching ``patterns``.

    Parameters
    ----------
    patterns : sequence of path-like
        Folders (searched recursively; hidden files and folders skipped), wildcards (``*``,
        ``?``, ``[..]``, ``**``), ``.pico`` files (standing for all the channels of their take)
        and ``.cara`` projects.
    options : BatchOptions, optional
        ``out_dir``, ``calibration`` and ``brim`` shape the jobs.

    Returns
    -------
    list of TakeJob
        Sorted by folder and name (numbers compared numerically). A ``.cara`` found next to the
        ``.pico`` files of the take of the same name, or at the output of a ``.pico`` take, is
        that take's output, not a take of its own. Takes that would write the same output get a
        ``problem``.

    Raises
    ------
    ValueError
        A named file or folder does not exist, a named file is not a ``.pico``/``.cara``, or
        nothing was found at all.
    """
    from carapost.io.pico import channel_of, take_files

    opt = options or BatchOptions()
    picos: dict[tuple[Path, str], Path] = {}
    caras: dict[Path, None] = {}
    for pat in map(str, patterns):
        globbed = bool(_GLOB_CHARS.search(pat))
        if globbed:
            matches = [Path(m) for m in sorted(glob.glob(os.path.expanduser(pat), recursive=True), key=_natural)]
        else:
            p = Path(pat).expanduser()
            if not p.exists():
                raise ValueError(f"{pat}: no such file or folder")
            matches = [p]
        n_before = len(picos) + len(caras)
        for m in matches:
            explicit = not globbed and not m.is_dir()
            for f in (_walk(m) if m.is_dir() else [m]):
                ext = f.suffix.lower()
                if ext == ".pico":
                    try:
                        prefix, _ = channel_of(f)
                    except ValueError as exc:
                        if explicit:
                            raise
                        log.warning("skipping %s", exc)
                        continue
                    picos.setdefault((f.resolve().parent, prefix), f.resolve())
                elif ext == ".cara":
                    caras[f.resolve()] = None
                elif explicit:
                    raise ValueError(f"{f}: not a take (expected .pico files, a folder or a .cara project)")
        if len(picos) + len(caras) == n_before:
            log.warning("%s: no takes found", pat)
    out_dir = Path(opt.out_dir).resolve() if opt.out_dir else None
    calibration = str(Path(opt.calibration).resolve()) if opt.calibration else None
    brim = opt.brim
    if brim and Path(brim).suffix.lower() in (".json", ".svg"):
        brim = str(Path(brim).resolve())
    jobs: list[TakeJob] = []
    for (folder, prefix), any_pico in sorted(picos.items(), key=lambda kv: _natural(f"{kv[0][0]}/{kv[0][1]}")):
        files = take_files(any_pico)
        jobs.append(TakeJob(
            name=prefix, kind="pico", inputs=tuple(str(f.resolve()) for f in files),
            output=str((out_dir or folder) / f"{prefix}.cara"),
            calibration=calibration or _sibling(folder, *(prefix + e for e in CALIBRATION_EXTENSIONS)),
            seeds=_sibling(folder, f"{prefix}_seeds.json"),
            brim=brim or _sibling(folder, f"{prefix}_brim.json", f"{prefix}_brim.svg")))
    pico_outputs = {j.output for j in jobs}
    for cara in sorted(caras, key=lambda p: _natural(str(p))):
        if str(cara) in pico_outputs or (cara.parent, cara.stem) in picos:
            continue
        jobs.append(TakeJob(name=cara.stem, kind="cara", inputs=(str(cara),),
                            output=str((out_dir / cara.name) if out_dir else cara),
                            seeds=_sibling(cara.parent, f"{cara.stem}_seeds.json"),
                            brim=brim or _sibling(cara.parent, f"{cara.stem}_brim.json", f"{cara.stem}_brim.svg")))
    if not jobs:
        raise ValueError(f"no takes (.pico files or .cara projects) found in {', '.join(map(str, patterns))}")
    by_output: dict[str, list[int]] = {}
    for i, j in enumerate(jobs):
        by_output.setdefault(j.output, []).append(i)
    for out, idx in by_output.items():
        if len(idx) > 1:
            for i in idx:
                others = "; ".join(jobs[k].inputs[0] for k in idx if k != i)
                jobs[i] = dataclasses.replace(jobs[i], problem=f"{out} would also be written by the take of {others}: "
                                                               f"give the takes distinct names or leave out --out")
    return jobs
