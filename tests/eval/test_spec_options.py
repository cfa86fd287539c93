"""The experiment commands' shared vocabulary: a spec file, a preset, ``--set`` overrides, ``--seed``, ``--cache``,
``-o``, ``--json``; every shipped preset is a valid spec."""

from __future__ import annotations

import json

import pytest

from semloc_core.experiments.detector_calibration import CalibrationSpec
from semloc_core.experiments.detector_training import TrainingSpec
from semloc_core.experiments.localization import LocalizationSpec
from semloc_core.experiments.loopclosure import LoopClosureSpec
from semloc_core.experiments.mapping import MappingSpec
from semloc_core.experiments.spec import DATA, PRESETS_DIR, load_preset
from semloc_core.experiments.template_selection import SelectionSpec
from services.cli import main
from services.demo_run import DemoSpec

SPECS = {"loopclosure": LoopClosureSpec, "localization": LocalizationSpec, "mapping": MappingSpec,
         "calibrate": CalibrationSpec, "select-templates": SelectionSpec, "train-detector": TrainingSpec,
         "demo": DemoSpec}
PRESETS = sorted((path.parent.name, path.stem) for path in PRESETS_DIR.glob("*/*.yaml"))


def test_every_preset_folder_belongs_to_a_command():
    assert {kind for kind, _ in PRESETS} <= set(SPECS)
    assert ("demo", "fast") in PRESETS and ("demo", "full") in PRESETS


@pytest.mark.parametrize("kind, name", PRESETS)
def test_every_preset_is_a_valid_spec(kind, name, request):
    if DATA in (PRESETS_DIR / kind / f"{name}.yaml").read_text():
        request.getfixturevalue("shared_data")  # the data folder its paths name, or skip
    document = load_preset(kind, name)
    spec = SPECS[kind].model_validate(document)
    assert f'"{DATA}' not in json.dumps(spec.model_dump())  # every data: path resolved


def test_loopclosure_thesis_preset_is_the_thesis_dp():
    """--preset thesis keeps §3.6.2's DP: every pair within t_match = 1000 matches, fixed, features as they come;
    the default aligns the threshold's and the mutual ratio-test matches."""
    thesis = LoopClosureSpec.model_validate(load_preset("loopclosure", "thesis"))
    f = thesis.features
    assert (f.match, f.t_match, f.calibration, f.repeated_threshold) == ("threshold", 1000, "fixed", 0)
    assert (thesis.mrf.potential, thesis.mrf.coupling) == ("thesis", "thesis")
    assert LoopClosureSpec().features.match == "threshold_or_mutual"


def test_spec_file_then_set_then_seed_and_the_json_on_stdout(tmp_path, capsys):
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text("dataset: tabletop\ntrajectories: [orbit:100]\nframes: 30\nstride: 5\nheatmaps: oracle\n"
                         "extraction: {min_views: 4, support: table}\n")
    out = tmp_path / "out" / "r.json"
    assert main(["eval", "mapping", "--spec", str(spec_file), "--set", "stride=6", "--seed", "3", "-o", str(out),
                 "--json", "--quiet"]) == 0
    printed = json.loads(capsys.readouterr().out)
    report = json.loads(out.read_text())
    assert printed == report
    # --set beats the spec file, which beats the defaults; --seed is the spec's seed
    assert (report["stride"], report["min_views"], report["seed"]) == (6, 4, 3)
    scene = report["scenes"]["orbit100"]
    assert scene["frames_used"] == 5 and scene["sources"]["oracle"]["normalised"]["extraction"]["support_z"]


def test_help_lists_the_presets_and_an_unknown_one_is_refused(capsys):
    with pytest.raises(SystemExit):
        main(["eval", "mapping", "--help"])
    assert "calibrate-templates" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "mapping", "--preset", "no-such-preset", "-o", "x.json"])
    assert exit_info.value.code == 2


def test_a_bad_spec_file_is_one_line(tmp_path, capsys):
    spec_file = tmp_path / "spec.yaml"
    spec_file.write_text("- not a mapping\n")
    assert main(["train-detector", "tabletop", "--spec", str(spec_file), "-o", str(tmp_path / "m")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("semloc train-detector: ") and "mapping of spec fields" in error
    assert main(["train-detector", "--spec", str(tmp_path / "missing.yaml"), "-o", str(tmp_path / "m")]) == 2
    assert "spec file not found" in capsys.readouterr().err


def test_the_detector_source_on_a_dataset_folder_says_how_to_get_its_likelihoods(tmp_path, capsys, sim_dataset):
    """README's `semloc eval localization DATASET` on a `semloc sim` folder: the detector's score likelihoods can
    only be fitted on other seeds of a simulated scenario, so the one line says where a file comes from."""
    dataset = sim_dataset("tabletop", frames=3)
    assert main(["eval", "localization", str(dataset), "-o", str(tmp_path / "out.json"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("semloc eval localization: the detector source needs calibration.file")
    assert "`semloc calibrate DATASET -o FILE`" in err and "--set sources=[synthetic,dpm]" in err



def _sets(*settings: str) -> list[str]:
    return [part for setting in settings for part in ("--set", setting)]


@pytest.mark.parametrize("kind, options, table", [
    ("loopclosure", _sets("window=3", "engine.enabled=false", "jobs=1"), "| dp |"),
    ("localization", [*_sets("frames=4", "stride=5", "sources=synthetic", "models=B", "variants=soft",
                             "particles=500"), "--cache", "{tmp}/cache"], "| B-soft-synthetic |"),
    ("mapping", _sets("trajectories=[orbit:100]", "frames=30", "stride=5", "heatmaps=oracle",
                      "extraction.min_views=4", "extraction.support=table"), "| orbit100 | oracle |"),
])
def test_each_evaluation_prints_its_table_and_quiet_only_silences_the_progress(kind, options, table, tmp_path, capsys,
                                                                               sim_dataset):
    """`--quiet` is "no progress on stderr": the three evaluations print their Markdown table on stdout with it
    (loop closure printed nothing at all), the same table as the report's ``.md`` beside the JSON."""
    dataset = {"loopclosure": str(sim_dataset("tabletop", frames=20)), "localization": "sim:tabletop",
               "mapping": "tabletop"}[kind]
    out = tmp_path / "r.json"
    assert main(["eval", kind, dataset, *(o.format(tmp=tmp_path) for o in options), "-o", str(out), "--quiet"]) == 0
    printed = capsys.readouterr()
    assert printed.err == "" and table in printed.out, printed
    assert printed.out.strip() == out.with_suffix(".md").read_text().strip()


def test_calibration_frames_beside_calibration_trajectories_is_refused(tmp_path):
    """The tabletop-scene preset calibrates along trajectory files, used whole: `--set calibration.frames=10` did
    nothing (805 calibration frames, 3 minutes); it is refused, naming both fields."""
    pose = tmp_path / "06.pose"
    pose.write_text("1 0 0 0 0 0 0\n")
    LocalizationSpec.model_validate({"dataset": "sim:tabletop", "calibration": {"trajectories": [str(pose)]}})
    LocalizationSpec.model_validate({"dataset": "sim:hall", "calibration": {"frames": 10}})
    with pytest.raises(ValueError, match="calibration.frames does nothing with calibration.trajectories"):
        LocalizationSpec.model_validate({"dataset": "sim:tabletop",
                                         "calibration": {"trajectories": [str(pose)], "frames": 10}})
