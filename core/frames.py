"""Frame numbers as people read them."""


def frame_ranges(frames: list[int]) -> str:
    """Ascending frame numbers as runs: [11, 12, 13, 20] -> '11-13, 20'."""
    runs = []
    for f in frames:
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)
