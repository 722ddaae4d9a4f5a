"""The docstrings' examples that take seconds (a rig calibrated, scenes rendered or estimated
whole) are marked ``slow`` like the tests that do: ``make test`` runs them, ``make
test-fast`` leaves them out."""

from __future__ import annotations

import pytest

#: Examples (the objects whose docstrings hold them) that take seconds.
SLOW_EXAMPLES = {
    "annotator.calibration.workflow.calibrate_rig",
    "annotator.sites.survey.measure_sites",
    "annotator.twins.dataset.synthesize_twins",
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if isinstance(item, pytest.DoctestItem) and item.name in SLOW_EXAMPLES:
            item.add_marker(pytest.mark.slow)
