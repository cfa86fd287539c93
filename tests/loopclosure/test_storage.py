"""What the loop-closure engine keeps besides its files: bounded samples of records."""

from __future__ import annotations

import numpy as np
import pytest

from semloc_core.loopclosure.storage import RecentRecords


@pytest.mark.parametrize("size, chunks", [(5, [3, 0, 4, 9, 1, 2, 2, 7]), (64, [10] * 30 + [200, 3])])
def test_recent_records_hold_the_latest_in_order(size, chunks):
    """The engine's bounded samples (background scores, released lattice cells): the latest ``size`` records
    appended, oldest first, as a list trimmed after every append would hold them."""
    recent = RecentRecords(np.int64, size)
    everything: list[int] = []
    for count in chunks:
        records = np.arange(len(everything), len(everything) + count)
        recent.append(records)
        everything.extend(records.tolist())
        assert recent.read().tolist() == everything[-size:] and len(recent) == min(size, len(everything))
