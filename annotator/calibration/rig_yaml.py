"""Putting a calibrated rig into ``dataset.yaml`` (FORMAT.md): the new text, its diff.

Only the top-level ``rig:`` block of an existing file is replaced, as text: every other
section keeps its content, order, comments and formatting. A file without a ``rig:`` block
gets one appended; a missing file becomes a minimal valid dataset (``format``, ``name``,
``markers.dictionary``, ``rig``, ``objects: []``) that ``annotator check`` accepts. The
splice is checked by parsing the result: the rig must read back as written and every other
top-level field must be unchanged, otherwise the whole file is written again from its parsed
content (comments then are lost, values are not). Within the rig, fields a calibration does
not produce are carried over (:func:`keep_other_fields`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from annotator.dataset.model import FORMAT_VERSION, DepthSpec, Rig
from annotator.dataset.write import rig_to_yaml
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.io.documents import parse_yaml, read_text

#: Marker dictionary of a new dataset.yaml (the parts' markers, not the board's).
DEFAULT_DICTIONARY = "DICT_4X4_1000"

_TOP_LEVEL = re.compile(r"^[^\s#]")


def rig_mapping(
    cameras: Sequence[Camera], depth: DepthSpec | None, flipped: Sequence[str] = ()
) -> dict[str, Any]:
    """The ``rig`` mapping of dataset.yaml (FORMAT.md); ``flipped`` names the mirrored
    cameras (``flip: horizontal``)."""
    return rig_to_yaml(Rig(tuple(cameras), depth, frozenset(flipped)))


#: The fields of the rig that a calibration writes; any other is carried over. ``flip`` is
#: the calibration's to decide: the captures show whether a camera is mirrored.
_CAMERA_FIELDS = ("name", "size", "K", "dist", "rig_T_cam", "flip")


def keep_other_fields(rig: dict[str, Any], old_doc: dict[str, Any] | None) -> dict[str, Any]:
    """``rig`` with the fields of the existing rig that a calibration does not produce (any
    key of ``rig`` besides ``cameras`` and ``depth``, of a camera besides its name, size, K,
    dist and rig_T_cam, of ``depth`` besides its camera and scale) carried over unchanged,
    so that fields added to the format later are not lost."""
    old = (old_doc or {}).get("rig")
    if not isinstance(old, dict):
        return rig
    out = dict(rig)
    for key, value in old.items():
        if key not in ("cameras", "depth") and key not in out:
            out[key] = value
    old_cams = {str(c.get("name")): c for c in old.get("cameras") or [] if isinstance(c, dict)}
    out["cameras"] = [
        {
            **cam,
            **{
                k: v
                for k, v in old_cams.get(cam["name"], {}).items()
                if k not in _CAMERA_FIELDS and k not in cam
            },
        }
        for cam in rig["cameras"]
    ]
    if isinstance(out.get("depth"), dict) and isinstance(old.get("depth"), dict):
        out["depth"] = {
            **out["depth"],
            **{
                k: v
                for k, v in old["depth"].items()
                if k not in ("camera", "scale") and k not in out["depth"]
            },
        }
    return out


def rig_yaml_text(rig: dict[str, Any], *, flow: bool = True) -> str:
    """The ``rig:`` block: with ``flow``, each list on one line (``K: [fx, 0, cx, ...]``);
    without, one number per line (the style of ``annotator synth``)."""
    return yaml.safe_dump(
        {"rig": rig}, sort_keys=False, default_flow_style=None if flow else False, width=200
    )


def read_dataset_doc(path: Path) -> tuple[str | None, dict[str, Any] | None]:
    """The text and parsed content of a dataset.yaml, ``(None, None)`` if absent."""
    if not path.exists():
        return None, None
    text = read_text(path)
    doc = parse_yaml(text, path)
    if doc is None:
        return text, {}
    if not isinstance(doc, dict):
        raise UserError("must be a YAML mapping", path=path)
    return text, doc


def existing_rig(doc: dict[str, Any] | None) -> dict[str, Any]:
    """Camera names, sizes and depth settings of an existing dataset.yaml's rig (loosely
    read: the rig is about to be replaced, only what must carry over matters)."""
    out: dict[str, Any] = {"cameras": [], "sizes": {}, "depth": None}
    rig = (doc or {}).get("rig")
    if not isinstance(rig, dict):
        return out
    for cam in rig.get("cameras") or []:
        if isinstance(cam, dict) and cam.get("name") is not None:
            name = str(cam["name"])
            out["cameras"].append(name)
            size = cam.get("size")
            if (
                isinstance(size, list)
                and len(size) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in size)
            ):
                out["sizes"][name] = (int(size[0]), int(size[1]))
    depth = rig.get("depth")
    if isinstance(depth, dict):
        scale = depth.get("scale")
        out["depth"] = {
            "camera": None if depth.get("camera") is None else str(depth["camera"]),
            "scale": float(scale) if isinstance(scale, (int, float)) and scale > 0 else None,
        }
    return out


def updated_text(old: str | None, rig: dict[str, Any], *, name: str) -> str:
    """dataset.yaml's text with ``rig`` as its rig block (see the module docstring), written
    in the style of the block it replaces (lists on one line, or one number per line), so
    that the diff shows the numbers that changed."""
    block_style = old is not None and re.search(r"^\s+K:\s*(#.*)?$", old, re.MULTILINE)
    rig_text = rig_yaml_text(rig, flow=not block_style)
    if old is None or not old.strip():
        head = yaml.safe_dump(
            {"format": FORMAT_VERSION, "name": name, "markers": {"dictionary": DEFAULT_DICTIONARY}},
            sort_keys=False,
        )
        return head + rig_text + "objects: []\n"
    lines = old.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if re.match(r"^rig\s*:", ln)), None)
    if start is None:
        sep = "" if old.endswith("\n") else "\n"
        new = old + sep + rig_text
    else:
        end = start + 1
        while end < len(lines) and not _TOP_LEVEL.match(lines[end]):
            end += 1
        # Comments and blank lines just before the next key belong to that key.
        while end > start + 1 and (
            not lines[end - 1].strip() or lines[end - 1].lstrip().startswith("#")
        ):
            end -= 1
        new = "".join(lines[:start]) + rig_text + "".join(lines[end:])
    if _spliced_correctly(old, new, rig):
        return new
    doc = yaml.safe_load(old) or {}
    doc["rig"] = rig
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=200)


def _spliced_correctly(old: str, new: str, rig: dict[str, Any]) -> bool:
    try:
        before, after = yaml.safe_load(old) or {}, yaml.safe_load(new)
    except yaml.YAMLError:
        return False
    if not isinstance(after, dict) or after.get("rig") != rig:
        return False
    return {k: v for k, v in before.items() if k != "rig"} == {
        k: v for k, v in after.items() if k != "rig"
    }
