"""Helpers shared by the benchmark scripts: seed lists, and a valve's slip count."""

import numpy as np


def seeds_arg(text):
    """`--seeds` values: ranges (both ends included) and single seeds, comma-separated:
    `"0-9"`, `"1,4,7"` or `"0-19,30-39"`."""
    seeds = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        seeds += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return seeds


def seeds_text(seeds):
    """The inverse of `seeds_arg`: `[0, 1, 2, 5]` -> `"0-2,5"`."""
    parts, i = [], 0
    while i < len(seeds):
        j = i
        while j + 1 < len(seeds) and seeds[j + 1] == seeds[j] + 1:
            j += 1
        parts.append(f"{seeds[i]}-{seeds[j]}" if j > i else f"{seeds[i]}")
        i = j + 1
    return ",".join(parts)


def slip_count(valve) -> int:
    """How many times a valve path starts to move after standing still (its slips)."""
    moving = np.abs(np.diff(np.asarray(valve))) > 1e-9
    return int(np.sum(moving[1:] & ~moving[:-1]))
