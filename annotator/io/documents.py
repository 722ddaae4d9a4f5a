"""Reading the JSON and YAML files users hand us: one-line errors, bounded nesting, checked
values.

Every reader of a user's document goes through :func:`read_json` or :func:`parse_yaml`, so
that whatever the file holds, the user sees one line naming the file and the problem, never
a traceback:

- a file that is missing, unreadable, not UTF-8 or not valid JSON / YAML;
- a document nested deeper than :data:`MAX_NESTING` levels (no file of the format needs more
  than a handful; a deeper one is a mistake or an attack, and would otherwise exhaust the
  parser's recursion);
- a UTF-8 byte-order mark at the start is allowed (editors on Windows write one).

Values are then checked by the format's reader with :func:`finite_number`, which names the
entry and field of a value that is not a finite number.
"""

from __future__ import annotations

import difflib
import json
import math
import re
from pathlib import Path
from typing import Any

from annotator.errors import UserError

#: The deepest nesting of lists and mappings a document may have.
MAX_NESTING = 64

_BOM = "\ufeff"


def read_text(path: str | Path) -> str:
    """The UTF-8 text of ``path`` without a byte-order mark, or a one-line UserError."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserError("file is missing", path=path) from None
    except IsADirectoryError:
        raise UserError("is a folder, not a file", path=path) from None
    except UnicodeDecodeError as exc:
        raise UserError(f"not UTF-8 text ({exc.reason} at byte {exc.start})", path=path) from None
    except OSError as exc:
        raise UserError(f"cannot read ({exc.strerror or exc})", path=path) from None
    return text.removeprefix(_BOM)


def parse_json(text: str, path: str | Path) -> Any:
    """``text`` parsed as JSON, nested at most :data:`MAX_NESTING` deep, or a UserError
    naming ``path``."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UserError(f"not valid JSON ({exc})", path=path) from None
    except RecursionError:
        raise _too_deep(path) from None
    if _json_depth(text) > MAX_NESTING:
        raise _too_deep(path)
    return doc


#: A JSON string, escapes included (unrolled, so that long strings are matched fast).
_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
#: A list or object with no list or object inside, once everything but brackets is gone.
_INNERMOST = re.compile(r"\[\]|\{\}")


def _json_depth(text: str) -> int:
    """How deep the lists and objects of a valid JSON text nest (up to one past
    :data:`MAX_NESTING`): only the brackets outside strings are kept, then each pass removes
    the innermost pairs. A walk over the parsed document would visit every number."""
    rest = _JSON_STRING.sub("", text) if '"' in text else text
    rest = _NOT_BRACKET.sub("", rest)
    depth = 0
    while rest and depth <= MAX_NESTING:
        rest, n = _INNERMOST.subn("", rest)
        if n == 0:
            break
        depth += 1
    return depth


def read_json(path: str | Path) -> Any:
    """A JSON file (see :func:`parse_json`), or a one-line UserError naming it."""
    return parse_json(read_text(path), path)


def parse_yaml(text: str, path: str | Path) -> Any:
    """``text`` parsed as YAML (safe loader), nested at most :data:`MAX_NESTING` deep.

    Raises:
        UserError: naming ``path``, with the line and column of a syntax error.
    """
    import yaml  # here: JSON readers (evaluate, export) need not pay for it

    try:
        # The pure-Python loader, not libyaml's: the two accept different documents (tabs,
        # directives) and word their errors differently, and not every PyYAML has libyaml.
        doc = yaml.safe_load(text.removeprefix(_BOM))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        what = "; ".join(
            str(x) for x in (getattr(exc, "context", None), getattr(exc, "problem", None)) if x
        )
        raise UserError(
            f"not valid YAML{where} ({what or type(exc).__name__})", path=path
        ) from None
    except RecursionError:
        raise _too_deep(path) from None
    check_nesting(doc, path)
    return doc


def read_yaml(path: str | Path) -> Any:
    """A YAML file (see :func:`parse_yaml`), or a one-line UserError naming it."""
    return parse_yaml(read_text(path), path)


def check_nesting(doc: Any, path: str | Path) -> None:
    """Raise a UserError if ``doc`` nests lists and mappings deeper than :data:`MAX_NESTING`.

    Iterative, so that it never recurses however deep ``doc`` is.
    """
    stack: list[tuple[Any, int]] = [(doc, 1)]
    seen: set[int] = set()  # YAML anchors can make a node appear twice (or in itself)
    while stack:
        node, depth = stack.pop()
        if isinstance(node, dict):
            children: Any = node.values()
        elif isinstance(node, list):
            children = node
        else:
            continue
        if depth > MAX_NESTING:
            raise _too_deep(path)
        if id(node) in seen:
            continue
        seen.add(id(node))
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))


def _too_deep(path: str | Path) -> UserError:
    return UserError(f"nested deeper than {MAX_NESTING} levels; no such file needs that", path=path)


def finite_number(
    value: Any,
    where: str,
    path: str | Path,
    *,
    low: float | None = None,
    high: float | None = None,
) -> float:
    """``value`` as a finite float within [``low``, ``high``], or a one-line UserError naming
    ``path`` and ``where`` (the entry and field, e.g. ``instances[3] (brick/01): occlusion.rate``).

    Booleans and strings are refused: JSON and YAML have numbers, and a quoted one is a
    mistake worth pointing at.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"{where} must be a number, got {_shown(value)}", path=path)
    number = float(value)
    if not math.isfinite(number):
        raise UserError(f"{where} is {value}; it must be a finite number", path=path)
    if (low is not None and number < low) or (high is not None and number > high):
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        span = f"[{lo}, {hi}]"
        raise UserError(f"{where} is {number:g}, outside {span}", path=path)
    return number


def _shown(value: Any) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def unified_diff(old: str | None, new: str, path: str | Path, *, label: str) -> str:
    """A unified diff from ``old`` (None: no file) to ``new``, labelled with ``path`` and,
    for the new text, ``label`` (what made it: ``calibrated``, ``measured``...)."""
    return "".join(
        difflib.unified_diff(
            (old or "").splitlines(keepends=True),
            new.splitlines(keepends=True),
            fromfile="/dev/null" if old is None else f"{path} (before)",
            tofile=f"{path} ({label})",
        )
    )
