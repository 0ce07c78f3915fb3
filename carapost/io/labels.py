"""Label text files (the reference guide's "About label (TXT) files").

A label file lists marker label names separated by white space (spaces, tabs, line breaks), one
or several per line; a name cannot contain a space. Example::

    Mouth_L_Corner  Mouth_R_Corner
    Chin_Center
    Nose_Tip

Files are read as UTF-8 (a UTF-8 byte-order mark is skipped; UTF-16 with a byte-order mark, as
saved by Windows Notepad's "Unicode", is accepted too). Importing adds to the existing labels:
see :func:`merge_labels` for how repeated names become ``"<name> - Copy"``.
"""

from __future__ import annotations

import codecs
import os
import re
from pathlib import Path

from .atomic import atomic_write_bytes

__all__ = ["LabelFileError", "read_label_file", "parse_labels", "merge_labels", "write_label_file",
           "COPY_SUFFIX"]

#: Appended to an imported name that repeats an existing label (reference guide: "- Copy").
COPY_SUFFIX = " - Copy"
_BAD_CHAR = re.compile(r"[\x00-\x08\x0e-\x1f\x7f\u2028\u2029\ufeff]")


class LabelFileError(ValueError):
    """A label file that cannot be read or written; the message names the file (and line)."""


def read_label_file(path: str | os.PathLike) -> list[str]:
    """The label names in a label text file, in file order (repeats kept).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    list of str
        Non-empty names without white space.

    Raises
    ------
    LabelFileError
        The file cannot be read, is not UTF-8 / UTF-16 text (the message gives the line of the
        first bad byte), contains control characters, or holds no label at all.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise LabelFileError(f"{path}: cannot read the label file ({e.strerror or e})") from e
    return parse_labels(raw, source=str(path))


def parse_labels(data: bytes | str, *, source: str = "<labels>") -> list[str]:
    """:func:`read_label_file` on the file's contents; ``source`` names it in error messages."""
    text = data if isinstance(data, str) else _decode(data, source)
    names: list[str] = []
    for lineno, line in enumerate(text.split("\n"), start=1):
        bad = _BAD_CHAR.search(line)
        if bad:
            raise LabelFileError(f"{source}, line {lineno}: control character {bad.group()!r} "
                                 "is not allowed in a label name")
        names.extend(line.split())
    if not names:
        raise LabelFileError(f"{source}: the label file contains no label names")
    return names


def _decode(raw: bytes, source: str) -> str:
    if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            return raw.decode("utf-16")
        except UnicodeDecodeError as e:
            raise LabelFileError(f"{source}: not valid UTF-16 text ({e.reason})") from e
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw[:e.start].count(b"\n") + 1
        raise LabelFileError(f"{source}, line {line}: byte {raw[e.start]:#04x} is not UTF-8 text "
                             "(save the label file as UTF-8)") from e


def merge_labels(existing: list[str], new: list[str]) -> list[str]:
    """Existing labels followed by the imported ones, renaming repeats.

    An imported name equal to any label already in the list (the existing ones, or one imported
    earlier from the same list) gets :data:`COPY_SUFFIX` appended, again and again until it is
    unique: importing ``["A", "A"]`` into ``["A"]`` gives ``["A", "A - Copy", "A - Copy - Copy"]``.
    Comparison is exact (case-sensitive). ``existing`` is not modified and is kept as it is, even
    if it holds repeats itself.

    Raises
    ------
    ValueError
        If an imported name is empty or contains white space.
    """
    for i, name in enumerate(new):
        if not isinstance(name, str) or not name or name != "".join(name.split()):
            raise ValueError(f"imported label {i + 1} ({name!r}) is empty or contains white space")
    out = list(existing)
    taken = set(out)
    for name in new:
        while name in taken:
            name += COPY_SUFFIX
        taken.add(name)
        out.append(name)
    return out


def write_label_file(path: str | os.PathLike, labels: list[str], *,
                     replace_spaces: str | None = None) -> None:
    """Write labels one per line (UTF-8, ``\\n`` line ends), atomically.

    Parameters
    ----------
    path : path-like
    labels : list of str
    replace_spaces : str, optional
        Replace each run of white space inside a name with this (e.g. ``"_"``, turning
        ``"Nose - Copy"`` into ``"Nose_-_Copy"``). By default such names are an error, since the
        format cannot hold them.

    Raises
    ------
    LabelFileError
        An empty name, a name with white space (and no ``replace_spaces``), no labels, or the
        folder does not exist.
    """
    path = Path(path)
    if not labels:
        raise LabelFileError(f"{path}: no labels to write")
    lines = []
    for i, name in enumerate(labels):
        parts = str(name).split()
        if not parts:
            raise LabelFileError(f"{path}: label {i + 1} is empty")
        if len(parts) > 1 or parts[0] != name:
            if replace_spaces is None or "".join(replace_spaces.split()) != replace_spaces:
                raise LabelFileError(f"{path}: label {i + 1} ({name!r}) contains white space, which a label "
                                     "file cannot hold (pass replace_spaces='_' to replace it)")
            name = replace_spaces.join(parts)
        if _BAD_CHAR.search(name):
            raise LabelFileError(f"{path}: label {i + 1} ({name!r}) contains a control character")
        lines.append(name)
    if not path.parent.is_dir():
        raise LabelFileError(f"{path}: cannot write, the folder {path.parent} does not exist")
    data = ("\n".join(lines) + "\n").encode("utf-8")
    atomic_write_bytes(path, data)
