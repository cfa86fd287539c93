"""deploy/two-machines/ on one machine: two zenoh routers on different loopback ports, the robot's workers behind one,
the base station's behind the other. Frames published at the robot's router reach the localizer behind the base
station's router, and its poses come back to a client of the robot's router."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.e2e.two_machines import plain_launchers, position_errors, run_split_graph

pytestmark = pytest.mark.service


def test_graph_split_over_two_routers(tmp_path, sim_dataset):
    dataset = Path(sim_dataset("tabletop", frames=24, seed=0))
    run = run_split_graph(*plain_launchers(tmp_path, dataset))
    heatlines = run.localizer.inputs["heatlines"]
    assert heatlines.received >= 10 and heatlines.rejected == 0
    assert len(run.images_at_base) >= 10
    # The poses are the localizer's answers to these frames: each carries the stamp of a frame of the data set and
    # lies near the camera's true position then (a sanity bound: the camera circles a table ~1.5 m away; accuracy
    # is the demo's business).
    errors = [error for _, error in position_errors(dataset, run.poses)]
    assert len(errors) == len(run.poses) >= 10
    assert max(errors) < 1.0, json.dumps(errors)
