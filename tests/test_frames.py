from splatwright.core.frames import frame_ranges


def test_frame_ranges_join_runs_of_consecutive_frames():
    assert frame_ranges([]) == ""
    assert frame_ranges([5]) == "5"
    assert frame_ranges([1, 2, 3, 7]) == "1-3, 7"
    assert frame_ranges([11, 12, 13, 20, 22, 23]) == "11-13, 20, 22-23"
