"""The ``.cara`` project file: save and load a whole take (HDF5 via h5py).

The schema is documented in ``docs/formats/cara.md``. In short: one HDF5 file with root
attributes ``format="carapost.cara"``, ``version_major``, ``version_minor``, ``writer``; groups
``/take``, ``/cameras/<c>``, ``/poses``, ``/points``, ``/tracks``, ``/detections/<c>``,
``/keyframes``, ``/labels``, ``/sticks``, ``/brim`` (optional) and ``/params``. The images stay
in their own files; each camera's source is stored by absolute path and by path relative to
the ``.cara`` file's folder.

Example
-------
>>> save_take(take, "session/take01.cara")             # doctest: +SKIP
>>> result = load_take("moved/session/take01.cara")     # doctest: +SKIP
>>> result.missing_sources, result.messages             # doctest: +SKIP
([], ['camera 0 (cam_0): images found at ...'])
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from carapost.model.take import SourceRef, Take

from .cara_migrate import migrate
from .cara_read import CaraDoc, build_take
from .cara_schema import CARA_VERSION, FORMAT, CaraError
from .cara_write import source_paths, write_take

__all__ = ["CARA_VERSION", "CaraError", "LoadResult", "save_take", "load_take", "relocate_source",
           "resolve_source"]

PathLike = str | os.PathLike


@dataclass
class LoadResult:
    """What :func:`load_take` returns.

    Attributes
    ----------
    take : Take
        The loaded take; camera sources that were found point at where they were found.
    missing_sources : list of int
        Camera indices whose images were not found (their :class:`SourceRef` is kept as saved).
    messages : list of str
        Migrations, newer-version notes, relocated and missing sources, for the user.
    """

    take: Take
    missing_sources: list[int] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------------- save
def save_take(take: Take, path: PathLike) -> None:
    """Save ``take`` as a ``.cara`` file, atomically.

    The file is written to a temporary file in the same folder and then renamed over
    ``path``, so a failure at any point leaves an existing file untouched (and no temporary
    file behind). ``take`` is not modified.

    Parameters
    ----------
    take : Take
    path : str or PathLike
        Destination; its folder must exist.

    Raises
    ------
    CaraError
        If the take breaks its array contract, or the file cannot be written (the message
        names the file).
    """
    path = Path(path)
    try:
        take.check()
    except ValueError as e:
        raise CaraError(f"{path}: cannot save an inconsistent take: {e}") from None
    folder = path.parent.resolve() if str(path.parent) else Path.cwd()
    if not folder.is_dir():
        raise CaraError(f"{path}: cannot save: folder {folder} does not exist")
    if path.is_dir():
        raise CaraError(f"{path}: cannot save: it is a folder")
    tmp = folder / f".{path.name}.{secrets.token_hex(6)}.tmp"
    try:
        # O_EXCL: never clobber anything; mode 0o666 lets the umask decide, as for any new file.
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        with h5py.File(tmp, "w") as f:
            write_take(f, take, folder)
        _fsync(tmp)
        if path.exists():
            os.chmod(tmp, path.stat().st_mode & 0o7777)
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise CaraError(f"{path}: cannot save: {e.strerror or e}") from e
        raise
    _fsync_dir(folder)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make the rename durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------------- load
def load_take(path: PathLike) -> LoadResult:
    """Load a ``.cara`` file.

    Older versions are migrated (a message says so); a newer minor version is read with a
    message, ignoring what this version does not know; a newer major version is refused.
    Each camera's source is looked for at its relative path (from the ``.cara`` file's
    folder), then its absolute path, then in the ``.cara`` file's folder by name (the guide's
    "Relocate Files" behaviour).

    Parameters
    ----------
    path : str or PathLike

    Returns
    -------
    LoadResult

    Raises
    ------
    CaraError
        File missing, not HDF5, truncated or damaged, not a CaraPost project, written by a
        newer major version, or with missing or malformed content. The message names the
        file and the problem.
    """
    path = Path(path)
    if not path.exists():
        raise CaraError(f"{path}: no such file")
    if path.is_dir():
        raise CaraError(f"{path}: is a folder, not a .cara file")
    try:
        is_h5 = h5py.is_hdf5(path)
    except OSError as e:
        raise CaraError(f"{path}: cannot read: {e}") from None
    if not is_h5:
        raise CaraError(f"{path}: not a CaraPost project (.cara) file: it is not an HDF5 file")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise CaraError(f"{path}: cannot open: the file is truncated or damaged ({e})") from None
    with f:
        doc = CaraDoc(f, path)
        try:
            messages = _check_version(doc)
            take = build_take(doc)
        except CaraError:
            raise
        except (OSError, KeyError, RuntimeError, TypeError, ValueError) as e:
            raise CaraError(f"{path}: cannot read: the file is damaged ({type(e).__name__}: {e})") from None
    missing, found_msgs = _resolve_sources(take, path.parent)
    return LoadResult(take=take, missing_sources=missing, messages=messages + found_msgs)


def _check_version(doc: CaraDoc) -> list[str]:
    fmt = doc.attrs("").get("format")
    if isinstance(fmt, bytes):
        fmt = fmt.decode("utf-8", "replace")
    if fmt != FORMAT:
        what = "no 'format' attribute" if fmt is None else f"format attribute {fmt!r}"
        raise doc.error(f"not a CaraPost project (.cara) file: {what}, expected {FORMAT!r}")
    major = doc.int_attr("", "version_major")
    minor = doc.int_attr("", "version_minor")
    cur_major, cur_minor = CARA_VERSION
    if major > cur_major:
        raise doc.error(f"written by a newer CaraPost (format {major}.{minor}); this version reads up to "
                        f"{cur_major}.x")
    if major == cur_major and minor > cur_minor:
        writer = doc.attrs("").get("writer", "an unknown writer")
        return [f"{doc.path.name}: written by a newer CaraPost ({writer}, format {major}.{minor}); this "
                f"version reads format {cur_major}.{cur_minor} and ignored what it does not know"]
    return migrate(doc, (major, minor))


# ------------------------------------------------------------------------------- sources
def _split_name(path: str) -> str:
    """The last component of a path written on any system (``/`` or ``\\`` separators)."""
    return re.split(r"[\\/]", path.rstrip("\\/"))[-1]


def resolve_source(ref: SourceRef, cara_dir: PathLike | None) -> Path | None:
    """The existing file or folder a source refers to, or ``None``.

    Tries, in order: ``cara_dir / ref.relpath``, ``ref.path``, ``cara_dir / <file name>``.
    """
    candidates: list[Path] = []
    if cara_dir is not None and ref.relpath:
        candidates.append(Path(cara_dir) / ref.relpath)
    if ref.path:
        candidates.append(Path(ref.path))
        if cara_dir is not None:
            name = _split_name(ref.path)
            if name:
                candidates.append(Path(cara_dir) / name)
    for cand in candidates:
        if cand.exists():
            return Path(os.path.abspath(cand))
    return None


def _resolve_sources(take: Take, cara_dir: Path) -> tuple[list[int], list[str]]:
    """Point each camera's source at where it is found now; list the missing ones."""
    cara_dir = Path(os.path.abspath(cara_dir))
    missing: list[int] = []
    messages: list[str] = []
    for c, cam in enumerate(take.cameras):
        ref = cam.source
        if ref is None:
            continue
        found = resolve_source(ref, cara_dir)
        if found is None:
            missing.append(c)
            alt = cara_dir / ref.relpath if ref.relpath else None
            also = f" (nor at {alt})" if alt is not None and str(alt) != ref.path else ""
            messages.append(f"camera {c} ({cam.name}): source not found: {ref.path}{also}; "
                            "use Relocate Files to point at it")
            continue
        absolute, rel = source_paths(str(found), cara_dir)
        if absolute != ref.path:
            messages.append(f"camera {c} ({cam.name}): source found at {absolute} (saved as {ref.path})")
        take.cameras[c] = dataclasses.replace(cam, source=SourceRef(path=absolute, relpath=rel, kind=ref.kind))
    return missing, messages


def relocate_source(take: Take, camera: int, new_path: PathLike, *, cara_path: PathLike | None = None) -> None:
    """Point camera ``camera``'s source at ``new_path`` (the Relocate Files dialog).

    Parameters
    ----------
    take : Take
        Modified in place: ``take.cameras[camera]`` is replaced by a copy with the new source.
    camera : int
        0-based camera index.
    new_path : str or PathLike
        An existing ``.pico`` file, video file or image folder.
    cara_path : str or PathLike, optional
        The take's ``.cara`` file, to fill in the relative path (it is recomputed on save anyway).

    Raises
    ------
    ValueError
        If there is no such camera or ``new_path`` does not exist.
    """
    if not 0 <= camera < take.n_cameras:
        raise ValueError(f"no camera {camera}: the take has cameras 0..{take.n_cameras - 1}")
    p = Path(new_path)
    if not p.exists():
        raise ValueError(f"{p}: no such file or folder")
    if p.is_dir():
        kind = "images"
    elif p.suffix.lower() == ".pico":
        kind = "pico"
    else:
        kind = "video"
    absolute, rel = os.path.abspath(p), ""
    if cara_path is not None:
        absolute, rel = source_paths(absolute, Path(os.path.abspath(Path(cara_path).parent)))
    cam = take.cameras[camera]
    take.cameras[camera] = dataclasses.replace(cam, source=SourceRef(path=absolute, relpath=rel, kind=kind))
