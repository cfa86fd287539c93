"""Shared test fixtures: where ../shared/data is, and skipping cleanly when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SEMLOC_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data, or skip the test (a user's machine has no ../shared)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data, skipping the test if it is missing."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"shared data not found: {path}")
    return path


@pytest.fixture(scope="session")
def sim_scenario():
    """Factory of simulated scenarios, cached for the session: ``sim_scenario("tabletop", frames=20, seed=0)``.

    Same arguments -> the same (shared, read-only) Scenario object; keep ``frames`` small. Options are passed to
    ``semloc_core.sim.make_scenario`` and must be hashable (use tuples, not lists).
    """
    cache: dict = {}

    def make(name: str, frames: int = 20, seed: int = 0, **options):
        from semloc_core.sim import make_scenario

        key = (name, frames, seed, tuple(sorted(options.items())))
        if key not in cache:
            cache[key] = make_scenario(name, seed=seed, frames=frames, **options)
        return cache[key]

    return make


@pytest.fixture(scope="session")
def sim_dataset(sim_scenario, tmp_path_factory):
    """Factory of simulated datasets written to disk once per session; returns the folder (opened with
    ``semloc_core.io.dataset.open_dataset``). Same arguments as ``sim_scenario`` plus ``multiview=False``."""
    cache: dict = {}

    def make(name: str, frames: int = 20, seed: int = 0, multiview: bool = False, **options):
        key = (name, frames, seed, multiview, tuple(sorted(options.items())))
        if key not in cache:
            folder = tmp_path_factory.mktemp(f"sim-{name}-{seed}")
            cache[key] = sim_scenario(name, frames=frames, seed=seed, **options).write(folder, multiview=multiview)
        return cache[key]

    return make
