"""Values a user gives, checked one way for the commands and for the Python API.

The commands' option types (:func:`annotator.commands.whole`, :func:`annotator.commands.number`)
and the library's functions call these checks, so that a value the command line refuses the
API refuses too, in the same words; the command line names the option (``argument
--workers: ...``), the API the argument (``workers: ...``).

>>> whole(2, name="workers", low=1)
2
>>> whole(-1, name="workers", low=1)
Traceback (most recent call last):
...
annotator.values.BadValue: workers: must be a whole number at least 1, not -1
>>> number(float("nan"), name="threshold_mm", low=0, above=True)
Traceback (most recent call last):
...
annotator.values.BadValue: threshold_mm: must be a finite number above 0, not nan
"""

from __future__ import annotations

import math
from typing import Any

from annotator.errors import UserError


class BadValue(UserError):
    """A value out of its range or of the wrong kind; ``reason`` is the message without the
    name, which the command line puts after the option's own.

    >>> from annotator.values import whole
    >>> try:
    ...     whole(0, name="workers", low=1)
    ... except BadValue as exc:
    ...     print(exc.reason)
    must be a whole number at least 1, not 0
    """

    def __init__(self, name: str, reason: str) -> None:
        super().__init__(f"{name}: {reason}")
        self.reason = reason


def whole(value: Any, *, name: str, low: int = 0, high: int | None = None) -> int:
    """``value`` as an int within [``low``, ``high``]; UserError (one line) otherwise. A
    string of digits is read (the command line's case); a bool or a float is not a whole
    number."""
    parsed: int | None = None
    if isinstance(value, str):
        try:
            parsed = int(value)
        except ValueError:
            parsed = None
    elif isinstance(value, int) and not isinstance(value, bool):
        parsed = int(value)
    if parsed is None or parsed < low or (high is not None and parsed > high):
        span = f"at least {low}" if high is None else f"from {low} to {high}"
        raise BadValue(name, f"must be a whole number {span}, not {value!r}")
    return parsed


def number(
    value: Any,
    *,
    name: str,
    low: float | None = None,
    high: float | None = None,
    above: bool = False,
) -> float:
    """``value`` as a finite float within [``low``, ``high``] (``above``: strictly greater
    than ``low``); NaN, infinities, bools and non-numbers are refused in one line."""
    parsed = math.nan
    if isinstance(value, str):
        try:
            parsed = float(value)
        except ValueError:
            parsed = math.nan
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        parsed = float(value)
    ok = math.isfinite(parsed)
    if ok and low is not None:
        ok = parsed > low if above else parsed >= low
    if ok and high is not None:
        ok = parsed <= high
    if not ok:
        bounds = []
        if low is not None:
            bounds.append(f"{'above' if above else 'at least'} {low:g}")
        if high is not None:
            bounds.append(f"at most {high:g}")
        span = f" {' and '.join(bounds)}" if bounds else ""
        raise BadValue(name, f"must be a finite number{span}, not {value!r}")
    return parsed


def of_type(value: Any, kind: type | tuple[type, ...], *, name: str, what: str) -> Any:
    """``value`` if it is a ``kind``; else a TypeError saying what was expected (``what``)
    and what came, instead of an AttributeError deep inside the library."""
    if not isinstance(value, kind):
        raise TypeError(f"{name} must be {what}, not {type(value).__name__} {value!r:.60}")
    return value
