import pytest

from carapost.core.timecode import TimeBase, TimecodeError, count_to_timecode, is_drop_frame_rate, timecode_to_count


@pytest.mark.parametrize("rate", [24.0, 25.0, 30.0, 50.0, 60.0, 100.0])
def test_non_drop_roundtrip(rate):
    for n in (0, 1, int(rate) - 1, int(rate), 3600 * int(rate) + 17, 86399 * int(rate)):
        assert timecode_to_count(count_to_timecode(n, rate), rate) == n
    assert count_to_timecode(int(rate) * 61 + 2, rate) == "00:01:01:02"


def test_drop_frame_2997():
    r = 30000 / 1001
    assert is_drop_frame_rate(r) and not is_drop_frame_rate(30.0)
    n = timecode_to_count("00:00:59;29", r)
    assert count_to_timecode(n + 1, r) == "00:01:00;02"  # labels 00 and 01 are skipped
    n10 = timecode_to_count("00:09:59;29", r)
    assert count_to_timecode(n10 + 1, r) == "00:10:00;00"  # except every tenth minute
    assert timecode_to_count("01:00:00;00", r) == 107892  # the standard figure for one hour
    for k in range(0, 200000, 997):
        assert timecode_to_count(count_to_timecode(k, r), r) == k


def test_drop_frame_5994():
    r = 60000 / 1001
    n = timecode_to_count("00:00:59;59", r)
    assert count_to_timecode(n + 1, r) == "00:01:00;04"


def test_take_conversions_and_errors():
    tb = TimeBase(60.0, "10:00:00:00", first_frame_number=1000)
    assert tb.frame_to_timecode(61) == "10:00:01:01"
    assert tb.timecode_to_frame("10:00:01:01") == 61
    assert (tb.frame_to_number(61), tb.number_to_frame(1061)) == (1061, 61)
    assert tb.frame_to_seconds(30) == 0.5
    with pytest.raises(TimecodeError):
        timecode_to_count("10-00", 60)
    with pytest.raises(TimecodeError):
        timecode_to_count("00:00:00:60", 60)
