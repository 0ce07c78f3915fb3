"""Label text files: reading, merging with " - Copy", writing."""

from __future__ import annotations

from pathlib import Path

import pytest

from carapost.io.labels import (COPY_SUFFIX, LabelFileError, merge_labels, parse_labels, read_label_file,
                                write_label_file)

GUIDE_EXAMPLE = ("Mouth_L_Corner  \nMouth_R_Corner  \nChin_Center  \nChin_L_Pt1  \nChin_L_Pt2  \n"
                 "Chin_R_Pt1  \nChin_R_Pt2  \nNose_Tip\n")


def test_guide_example(tmp_path: Path) -> None:
    path = tmp_path / "face.txt"
    path.write_text(GUIDE_EXAMPLE)
    assert read_label_file(path) == ["Mouth_L_Corner", "Mouth_R_Corner", "Chin_Center", "Chin_L_Pt1",
                                     "Chin_L_Pt2", "Chin_R_Pt1", "Chin_R_Pt2", "Nose_Tip"]


def test_many_per_line_tabs_crlf_blank_lines_bom() -> None:
    data = "\ufeffA B\tC\r\n\r\n   D  \r\nE\n\nF G".encode("utf-8")
    assert parse_labels(data) == ["A", "B", "C", "D", "E", "F", "G"]


def test_utf16_and_non_ascii(tmp_path: Path) -> None:
    path = tmp_path / "u16.txt"
    path.write_bytes("Lèvre_G Œil_D\nNez".encode("utf-16"))  # Notepad's "Unicode", with BOM
    assert read_label_file(path) == ["Lèvre_G", "Œil_D", "Nez"]
    path.write_bytes("Lèvre_G Œil_D\nNez".encode("utf-8"))
    assert read_label_file(path) == ["Lèvre_G", "Œil_D", "Nez"]


def test_repeats_kept_on_read() -> None:
    assert parse_labels(b"A A\nB") == ["A", "A", "B"]


def test_bad_encoding_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "latin1.txt"
    path.write_bytes("Nose\nChin\nL\u00e8vre\n".encode("latin-1"))
    with pytest.raises(LabelFileError, match=r"latin1\.txt, line 3: byte 0xe8 is not UTF-8"):
        read_label_file(path)


def test_control_character_names_line(tmp_path: Path) -> None:
    path = tmp_path / "ctrl.txt"
    path.write_bytes(b"A\nB\x00C\n")
    with pytest.raises(LabelFileError, match=r"ctrl\.txt, line 2: control character"):
        read_label_file(path)


def test_empty_and_missing_files(tmp_path: Path) -> None:
    path = tmp_path / "empty.txt"
    path.write_text(" \n\t\n")
    with pytest.raises(LabelFileError, match=r"empty\.txt: the label file contains no label names"):
        read_label_file(path)
    with pytest.raises(LabelFileError, match=r"gone\.txt: cannot read"):
        read_label_file(tmp_path / "gone.txt")
    assert issubclass(LabelFileError, ValueError)


def test_merge_appends_copy() -> None:
    existing = ["Nose_Tip", "Chin_Center"]
    merged = merge_labels(existing, ["Mouth_L", "Nose_Tip", "Chin_Center"])
    assert merged == ["Nose_Tip", "Chin_Center", "Mouth_L", "Nose_Tip - Copy", "Chin_Center - Copy"]
    assert existing == ["Nose_Tip", "Chin_Center"]  # not modified
    assert COPY_SUFFIX == " - Copy"


def test_merge_repeated_copies_and_repeats_inside_import() -> None:
    assert merge_labels(["A"], ["A", "A"]) == ["A", "A - Copy", "A - Copy - Copy"]
    assert merge_labels([], ["B", "B", "C"]) == ["B", "B - Copy", "C"]
    # an existing "A - Copy" is skipped over
    assert merge_labels(["A", "A - Copy"], ["A"]) == ["A", "A - Copy", "A - Copy - Copy"]
    # case-sensitive
    assert merge_labels(["nose"], ["Nose"]) == ["nose", "Nose"]
    # importing the same file twice
    once = merge_labels([], ["X", "Y"])
    assert merge_labels(once, ["X", "Y"]) == ["X", "Y", "X - Copy", "Y - Copy"]


def test_merge_rejects_bad_names() -> None:
    with pytest.raises(ValueError, match="label 2"):
        merge_labels(["A"], ["B", ""])
    with pytest.raises(ValueError, match="white space"):
        merge_labels([], ["has space"])


def test_write_read_round_trip(tmp_path: Path) -> None:
    labels = ["Mouth_L_Corner", "Chin_Center", "Lèvre_G"]
    path = tmp_path / "out.txt"
    write_label_file(path, labels)
    assert path.read_bytes() == "Mouth_L_Corner\nChin_Center\nLèvre_G\n".encode("utf-8")
    assert read_label_file(path) == labels
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]  # no temporary file left


def test_write_names_with_spaces(tmp_path: Path) -> None:
    path = tmp_path / "out.txt"
    path.write_text("old\n")
    merged = merge_labels(["Nose"], ["Nose"])
    with pytest.raises(LabelFileError, match=r"out\.txt: label 2 \('Nose - Copy'\) contains white space"):
        write_label_file(path, merged)
    assert path.read_text() == "old\n"  # untouched on error
    write_label_file(path, merged, replace_spaces="_")
    assert read_label_file(path) == ["Nose", "Nose_-_Copy"]


def test_write_errors(tmp_path: Path) -> None:
    with pytest.raises(LabelFileError, match="no labels"):
        write_label_file(tmp_path / "a.txt", [])
    with pytest.raises(LabelFileError, match="label 2 is empty"):
        write_label_file(tmp_path / "a.txt", ["A", "  "])
    with pytest.raises(LabelFileError, match="does not exist"):
        write_label_file(tmp_path / "no" / "a.txt", ["A"])
    with pytest.raises(LabelFileError, match="white space"):
        write_label_file(tmp_path / "a.txt", ["A B"], replace_spaces=" ")
