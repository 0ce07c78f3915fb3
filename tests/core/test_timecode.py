import pytest

from carapost.core.timecode import Timecode, format_timecode, is_drop_frame, parse_timecode


@pytest.mark.parametrize("rate", [24.0, 25.0, 30.0, 50.0, 60.0, 100.0])
def test_non_drop_roundtrip(rate):
    for n in (0, 1, int(rate) - 1, int(rate), 3600 * int(rate) + 17, 86399 * int(rate)):
        assert parse_timecode(format_timecode(n, rate), rate) == n
    assert format_timecode(int(rate) * 61 + 2, rate) == "00:01:01:02"


def test_drop_frame_2997():
    r = 30000 / 1001
    assert is_drop_frame(r) and not is_drop_frame(30.0)
    # The frame after 00:00:59;29 is 00:01:00;02 (frames 00 and 01 are dropped).
    n = parse_timecode("00:00:59;29", r)
    assert format_timecode(n + 1, r) == "00:01:00;02"
    # Every tenth minute keeps its first frames.
    n10 = parse_timecode("00:09:59;29", r)
    assert format_timecode(n10 + 1, r) == "00:10:00;00"
    # One hour of drop-frame timecode is 107892 frames (the standard figure).
    assert parse_timecode("01:00:00;00", r) == 107892
    for k in range(0, 200000, 997):
        assert parse_timecode(format_timecode(k, r), r) == k


def test_drop_frame_5994():
    r = 60000 / 1001
    n = parse_timecode("00:00:59;59", r)
    assert format_timecode(n + 1, r) == "00:01:00;04"
    for k in range(0, 400000, 1999):
        assert parse_timecode(format_timecode(k, r), r) == k


def test_take_conversions_and_errors():
    tc = Timecode(60.0, "10:00:00:00", first_frame_number=1000)
    assert tc.to_timecode(61) == "10:00:01:01"
    assert tc.from_timecode("10:00:01:01") == 61
    assert (tc.to_frame_number(61), tc.from_frame_number(1061)) == (1061, 61)
    assert tc.to_seconds(30) == 0.5
    with pytest.raises(ValueError, match="HH:MM:SS:FF"):
        parse_timecode("10-00", 60)
    with pytest.raises(ValueError, match="out of range"):
        parse_timecode("00:00:00:60", 60)
