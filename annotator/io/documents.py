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

import numpy as np
import orjson

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
    naming ``path``.

    orjson parses (several times faster on the float-heavy files of poses); a text it refuses
    is parsed again by the standard library, which is what decides: it accepts what orjson
    does not (NaN and Infinity, which the format's checks then name) and words the error of a
    text that is not JSON."""
    try:
        doc = orjson.loads(text)
    except orjson.JSONDecodeError:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise UserError(f"not valid JSON ({exc})", path=path) from None
        except RecursionError:
            raise _too_deep(path) from None
    if json_depth(text) > MAX_NESTING:
        raise _too_deep(path)
    return doc


#: Every byte but the quote and the brackets, which are all that the nesting depends on.
_NOT_STRUCTURE = bytes(b for b in range(256) if b not in b'"[]{}')
#: A string, once escapes and everything but quotes and brackets are gone.
_BARE_STRING = re.compile(rb'"[^"]*"')
#: +1 for an opening bracket, -1 for a closing one, by byte.
_STEP = np.zeros(256, np.int32)
_STEP[[ord("["), ord("{")]] = 1
_STEP[[ord("]"), ord("}")]] = -1


def json_depth(text: str) -> int:
    """How deep the lists and objects of a valid JSON text nest. Escaped backslashes and
    quotes are dropped first (they pair off from the left in valid JSON), then every byte
    but quotes and brackets, then the strings: the depth is the highest count of brackets
    open. A walk over the parsed document would visit every number."""
    if "\\" in text:
        text = text.replace("\\\\", "").replace('\\"', "")
    rest = text.encode("utf-8", "surrogatepass").translate(None, _NOT_STRUCTURE)
    if b'"' in rest:
        rest = _BARE_STRING.sub(b"", rest)
    if not rest:
        return 0
    return int(np.cumsum(_STEP[np.frombuffer(rest, np.uint8)]).max())


def read_json(path: str | Path) -> Any:
    """A JSON file (see :func:`parse_json`), or a one-line UserError naming it."""
    return parse_json(read_text(path), path)


def parse_yaml(text: str, path: str | Path) -> Any:
    """``text`` parsed as YAML (safe loader), nested at most :data:`MAX_NESTING` deep.

    Raises:
        UserError: naming ``path``, with the line and column of a syntax error.
    """
    import yaml  # here: JSON readers (evaluate, export) need not pay for it

    text = text.removeprefix(_BOM)
    # libyaml parses ten times faster than the pure-Python loader. A text it refuses is
    # parsed again by the pure-Python loader, which decides (and words the error with its
    # line and column), as it does where PyYAML was built without libyaml.
    fast = getattr(yaml, "CSafeLoader", None)
    if fast is not None:
        try:
            doc = yaml.load(text, Loader=fast)  # CSafeLoader: a safe loader
        except (yaml.YAMLError, RecursionError):
            pass
        else:
            return _checked(doc, path)
    try:
        doc = yaml.safe_load(text)
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
    return _checked(doc, path)


def _checked(doc: Any, path: str | Path) -> Any:
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
