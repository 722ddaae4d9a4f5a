"""COCO run-length masks checked before any C routine reads them.

pycocotools' C decoder (``rleFrString``) trusts its input: a string cut in half reads past
its end, and runs that do not add up to the image (or go negative) make its area and IoU
loops run for billions of steps, holding the interpreter so that no signal is handled. So
every mask is checked here first, on arrays, as that decoder would read it:

- a compressed ``counts`` string holds characters ``'0'``..``'o'`` only (6 bits each: 5 of
  value, 1 "more follows"), and its last character ends a number;
- each number takes at most 7 characters (a 32-bit run);
- the runs, once the decoder's differences are undone (run ``m`` > 2 is stored minus run
  ``m - 2``), are none negative and add up to ``h * w``;
- an uncompressed ``counts`` list holds non-negative integers adding up to ``h * w``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["rle_problems"]

#: Characters of a number at most (7 x 5 bits hold a 32-bit run and its sign).
MAX_CHARS = 7


def rle_problems(counts: Sequence[object], sizes: Sequence[tuple[int, int]]) -> dict[int, str]:
    """Why each bad mask of ``counts`` (strings or lists) with ``sizes`` (h, w) cannot be
    read, by its index; an empty dict when every one is a whole mask.

    >>> from pycocotools import mask
    >>> good = mask.encode(np.asfortranarray(np.eye(6, dtype=np.uint8)))["counts"].decode()
    >>> rle_problems([good, good[:3], "0~", [30, 6], [-1, 37]], [(6, 6)] * 5)
    {1: 'its runs add up to 7 pixels, not 6 x 6 = 36', 2: "character '~' is not of an RLE string", 4: 'a run is negative'}
    """
    problems: dict[int, str] = {}
    strings = [(i, c) for i, c in enumerate(counts) if isinstance(c, str)]
    for i, c in enumerate(counts):
        if isinstance(c, str):
            continue
        try:  # sum and min at C speed; a string or a float among the runs fails them
            total, low = (sum(c), min(c)) if isinstance(c, list) and c else (0, 0)
            whole = isinstance(c, list) and type(total) is int
        except TypeError:
            whole = False
        if not whole:
            problems[i] = "counts must be an RLE string or a list of integers"
        elif low < 0:
            problems[i] = "a run is negative"
        elif total != sizes[i][0] * sizes[i][1]:
            problems[i] = _sum_problem(total, sizes[i])
    if strings:
        problems.update(_string_problems(strings, sizes))
    return dict(sorted(problems.items()))


def _sum_problem(total: int, size: tuple[int, int]) -> str:
    h, w = size
    return f"its runs add up to {total} pixels, not {h} x {w} = {h * w}"


def _string_problems(
    strings: list[tuple[int, str]], sizes: Sequence[tuple[int, int]]
) -> dict[int, str]:
    problems: dict[int, str] = {}
    ascii_ok: list[tuple[int, str]] = []
    for i, s in strings:
        if not s.isascii():
            problems[i] = (
                f"character {next(ch for ch in s if not ch.isascii())!r} is not of an RLE string"
            )
        elif not s:
            if sizes[i][0] * sizes[i][1]:
                problems[i] = _sum_problem(0, sizes[i])
        else:
            ascii_ok.append((i, s))
    if not ascii_ok:
        return problems
    lens = np.array([len(s) for _, s in ascii_ok], np.int64)
    c = np.frombuffer("".join(s for _, s in ascii_ok).encode("ascii"), np.uint8).astype(np.int64)
    c -= 48
    owner = np.repeat(np.arange(len(ascii_ok)), lens)
    outside = (c < 0) | (c > 63)
    if outside.any():  # named, then left out of the decoding
        at = np.flatnonzero(outside)
        firsts = at[np.unique(owner[at], return_index=True)[1]]
        for j in owner[firsts]:
            i, s = ascii_ok[j]
            bad = next(ch for ch in s if not "0" <= ch <= "o")
            problems[i] = f"character {bad!r} is not of an RLE string"
        keep = [j for j in range(len(ascii_ok)) if ascii_ok[j][0] not in problems]
        ascii_ok = [ascii_ok[j] for j in keep]
        if not ascii_ok:
            return problems
        mask = np.isin(owner, keep)
        c, lens = c[mask], lens[keep]
        owner = np.repeat(np.arange(len(ascii_ok)), lens)
    ends = (c & 0x20) == 0
    last = np.cumsum(lens) - 1
    cut = ~ends[last]
    # The numbers: each ends at a character without the "more" bit (or at its string's end,
    # for a string cut short: refused below, but its numbers stay its own).
    ends[last] = True
    end_at = np.flatnonzero(ends)
    start_at = np.concatenate([[0], end_at[:-1] + 1])
    k = np.arange(len(c)) - np.repeat(start_at, end_at - start_at + 1)
    too_long = np.zeros(len(ascii_ok), bool)
    np.logical_or.at(too_long, owner[k >= MAX_CHARS], True)
    shift = np.minimum(k, MAX_CHARS) * 5
    x = np.add.reduceat((c & 0x1F) << shift, start_at)
    width = (end_at - start_at + 1) * 5
    negative = (c[end_at] & 0x10) != 0
    x = np.where(negative, x - (np.int64(1) << np.minimum(width, 62)), x)
    # Undo the differences: run m > 2 is stored minus run m - 2 (per string, per parity).
    num_owner = owner[end_at]
    first = np.searchsorted(num_owner, np.arange(len(ascii_ok)))
    start = first[num_owner]  # each number's string's first number
    odd = ((np.arange(len(end_at)) - start) % 2).astype(bool)
    alone = np.arange(len(end_at)) == start  # run 0: no difference undone
    runs = x.copy()
    for lane in (odd, ~odd & ~alone):  # running sums per string and parity
        summed = np.cumsum(np.where(lane, x, 0))
        before = np.concatenate([[0], summed])[start]
        runs[lane] = (summed - before)[lane]
    bad_run = np.zeros(len(ascii_ok), bool)
    np.logical_or.at(bad_run, num_owner[(runs < 0) | (runs >= 2**32)], True)
    totals = np.bincount(num_owner, weights=runs.astype(np.float64), minlength=len(ascii_ok))
    for j, (i, _) in enumerate(ascii_ok):
        h, w = sizes[i]
        if cut[j]:
            problems[i] = "the RLE string is cut short (its last number goes on)"
        elif too_long[j]:
            problems[i] = f"a number of the RLE string is over {MAX_CHARS} characters"
        elif bad_run[j]:
            problems[i] = "a run is negative"
        elif int(totals[j]) != h * w:
            problems[i] = _sum_problem(int(totals[j]), (h, w))
    return problems
