"""Command-line helpers shared by the benchmark scripts."""


def seeds_arg(text):
    """`--seeds` values: `"0-9"` (a range, both ends included) or `"1,4,7"`."""
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(v) for v in text.split(",")]
