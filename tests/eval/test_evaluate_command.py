"""The `semloc eval` dispatcher offers the evaluation modules that exist and delegates to them."""

import sys
import types

import pytest

from services.commands import evaluate


@pytest.fixture
def fake_kind(monkeypatch):
    module = types.ModuleType("fake_eval_module")
    calls = []

    def add_arguments(parser):
        parser.add_argument("dataset")
        parser.add_argument("--json", required=True)
        parser.add_argument("--window", type=int, default=30)

    def run(args):
        calls.append((args.dataset, args.json, args.window))
        return 0

    module.add_arguments = add_arguments
    module.run = run
    monkeypatch.setitem(sys.modules, "fake_eval_module", module)
    monkeypatch.setattr(evaluate, "KINDS", {"fake": ("fake_eval_module", "a fake evaluation"),
                                            "absent": ("no_such_module_anywhere", "not installed")})
    monkeypatch.setattr(evaluate.importlib.util, "find_spec",
                        lambda name: object() if name == "fake_eval_module" else None)
    return calls


def test_dispatch_to_the_kind_module(fake_kind):
    import argparse

    parser = argparse.ArgumentParser()
    evaluate.add_arguments(parser)
    args = parser.parse_args(["fake", "data/route", "--json", "out.json", "--window", "5"])
    assert evaluate.run(args) == 0
    assert fake_kind == [("data/route", "out.json", 5)]
    with pytest.raises(SystemExit):
        parser.parse_args(["absent", "data", "--json", "x"])
