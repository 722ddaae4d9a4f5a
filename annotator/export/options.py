"""The modes of an export, named once: what ``annotator export --format``, ``--layout`` and
``--poses`` take, and :func:`annotator.export.dataset.export_dataset` with them."""

from __future__ import annotations

from typing import Literal, get_args

#: The formats an export writes.
ExportFormat = Literal["bop", "sileane"]
EXPORTS: tuple[ExportFormat, ...] = get_args(ExportFormat)

#: How a BOP export lays out its images: BOP's scene folders, bop_toolkit's image-wise
#: files, or those files in webdataset tar shards.
Layout = Literal["scenewise", "imagewise", "webdataset"]
LAYOUTS: tuple[Layout, ...] = get_args(Layout)

#: Where the exported poses come from: annotation.json (with the reviewers' repairs) or
#: gt.json (synthetic scenes).
PosesFrom = Literal["annotation", "gt"]
POSES_FROM: tuple[PosesFrom, ...] = get_args(PosesFrom)
