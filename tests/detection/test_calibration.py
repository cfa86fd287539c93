"""Score likelihoods by KDE (§4.8.2) and their file format (semloc.score_likelihood v1)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semloc_core.bearing import BearingGrid, Heatlines
from semloc_core.detection.calibration import (decision_threshold, fit_score_likelihoods, heatline_samples,
                                               kde_on_grid, robust_bandwidth)
from semloc_core.io.calibration import (CalibrationFormatError, ScoreLikelihoods, load_score_likelihoods,
                                        save_score_likelihoods)


def test_bandwidth_is_the_robust_normal_reference():
    rng = np.random.default_rng(0)
    samples = rng.normal(0.4, 0.1, 4000)
    samples[:100] = 50.0   # gross outliers barely move a MAD-based estimate
    sigma = np.median(np.abs(samples - np.median(samples))) / 0.6745
    assert robust_bandwidth(samples, 1e-3) == pytest.approx(sigma * (4 / (3 * samples.size)) ** 0.2)
    assert 0.09 < sigma < 0.11
    assert robust_bandwidth(np.zeros(10), 1e-3) == pytest.approx(2e-3)   # degenerate: grid resolution


def test_binned_kde_equals_direct_kde_away_from_the_edges():
    rng = np.random.default_rng(1)
    samples = rng.normal(0.5, 0.08, 700)
    z = np.linspace(0, 1, 1000)
    h = robust_bandwidth(samples, z[1] - z[0])
    direct = np.exp(-0.5 * ((z[:, None] - samples[None, :]) / h) ** 2).sum(axis=1)
    direct /= np.trapezoid(direct, z)
    binned = kde_on_grid(samples, z, h)
    assert np.trapezoid(binned, z) == pytest.approx(1.0)
    np.testing.assert_allclose(binned, direct, atol=2e-3 * direct.max())


def test_mass_at_the_boundary_is_kept_inside():
    z = np.linspace(0, 1, 1000)
    density = kde_on_grid(np.zeros(50), z, 0.05)
    assert np.trapezoid(density, z) == pytest.approx(1.0)
    assert density[0] == density.max()


def test_fit_save_load_and_lookup(tmp_path):
    rng = np.random.default_rng(2)
    positives = {"cup": np.clip(rng.normal(0.7, 0.1, 300), 0, 1), "bowl": np.clip(rng.normal(0.6, 0.15, 200), 0, 1)}
    negatives = {"cup": np.clip(rng.normal(0.2, 0.1, 20000), 0, 1), "bowl": np.clip(rng.normal(0.25, 0.1, 9000), 0, 1)}
    fitted = fit_score_likelihoods(positives, negatives, detector={"kind": "test"}, source="unit test")
    assert fitted.count == 1000 and fitted.classes == ("cup", "bowl")
    path = save_score_likelihoods(fitted, tmp_path / "likelihoods.json")
    document = json.loads(path.read_text())
    assert document["format"] == "semloc.score_likelihood" and document["version"] == 1
    loaded = load_score_likelihoods(path)
    np.testing.assert_array_equal(loaded.pdf_d, fitted.pdf_d)
    assert loaded.n_d.tolist() == [300, 200] and loaded.detector == {"kind": "test"}
    p_d, p_not_d = loaded.lookup("cup", [0.7, 0.2])
    assert p_d[0] > p_not_d[0] and p_d[1] < p_not_d[1]
    # Linear interpolation between grid points, clamped outside the grid, floored.
    z = loaded.z
    middle = 0.5 * (z[400] + z[401])
    assert loaded.lookup("cup", middle)[0] == pytest.approx(0.5 * (loaded.pdf_d[0, 400] + loaded.pdf_d[0, 401]))
    assert loaded.lookup("cup", 7.0)[0] == pytest.approx(max(loaded.pdf_d[0, -1], 1e-6))
    assert 0.35 < decision_threshold(loaded, "cup") < 0.6
    with pytest.raises(KeyError, match="not calibrated"):
        loaded.lookup("plate", 0.5)


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(format="other"), "expected format"),
    (lambda d: d.update(version=2), "unsupported version"),
    (lambda d: d["classes"]["a"].update(pdf_d=[0.1, 0.2]), "z.count"),
    (lambda d: d["classes"]["a"].update(pdf_d=[-1.0, 1.0, 1.0]), "non-negative"),
    (lambda d: d.update(classes={}), "non-empty"),
])
def test_malformed_files_raise_one_clear_error(tmp_path, mutate, message):
    document = ScoreLikelihoods(("a",), 0.0, 1.0, [[1.0, 1.0, 1.0]], [[2.0, 0.0, 0.0]]).to_dict()
    mutate(document)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(document))
    with pytest.raises(CalibrationFormatError, match=message):
        load_score_likelihoods(path)


def test_heatline_samples_split_positives_and_negatives():
    grid = BearingGrid()
    centres = np.degrees(grid.centers)
    observed = np.abs(centres) < 60
    scores = np.zeros((2, 360), np.float32)
    scores[0] = np.exp(-0.5 * ((centres - 10.5) / 2) ** 2)
    heatlines = Heatlines(("cup", "bowl"), scores * observed, observed)
    objects = [("cup", np.radians(10.5), True), ("cup", np.radians(-30.5), False), ("bowl", np.radians(40.5), True)]
    positives, negatives = heatline_samples(heatlines, objects, positive_deg=2.2, negative_deg=10.2)
    assert positives["cup"].size == 5 and positives["cup"].min() > 0.5   # bins centred 8.5 .. 12.5
    assert positives["bowl"].size == 5
    # Negatives: observed, not within 10.2 deg of any cup (the unusable one included): 2 x 21 bins left out.
    assert negatives["cup"].size == observed.sum() - 21 - 21
    assert negatives["cup"].max() < 0.01


def test_calibration_on_a_dataset_puts_detection_mass_above_background(tmp_path):
    """`semloc calibrate`'s experiment on a dataset with exact ground truth: p(z|d) lies above p(z|not d)."""
    from semloc_core.detection.features import FeatureParams
    from semloc_core.detection.templates import TemplateDetector, build_templates
    from semloc_core.experiments.detector_calibration import calibrate, likelihoods_png
    from tests.detection.synthetic import SyntheticDataset, make_object

    dataset = SyntheticDataset(10, seed=3)
    params = FeatureParams()
    templates = [t for kind in dataset.kinds for t in build_templates(make_object(kind, 120), kind, params)]
    likelihoods = calibrate(dataset, TemplateDetector(templates, params), range(len(dataset)))
    assert likelihoods.classes == ("clock", "machine") and likelihoods.count == 1000
    z = likelihoods.z
    for k in range(len(likelihoods.classes)):
        assert likelihoods.n_d[k] >= 10 * 3 and likelihoods.n_not_d[k] > 10 * likelihoods.n_d[k]
        cdf_d = np.cumsum(likelihoods.pdf_d[k]) / likelihoods.pdf_d[k].sum()
        cdf_not_d = np.cumsum(likelihoods.pdf_not_d[k]) / likelihoods.pdf_not_d[k].sum()
        # First-order stochastic dominance: at every score, less of p(z|d)'s mass lies below it.
        assert np.all(cdf_d <= cdf_not_d + 1e-6)
        assert z[np.searchsorted(cdf_d, 0.5)] > z[np.searchsorted(cdf_not_d, 0.95)]
        assert z[np.searchsorted(cdf_not_d, 0.5)] < decision_threshold(likelihoods, likelihoods.classes[k]) \
            < z[np.searchsorted(cdf_d, 0.5)]
    assert len(likelihoods_png(likelihoods)) > 10_000


def test_semloc_calibrate_on_a_simulated_dataset(tmp_path):
    """The command end to end: `semloc sim tabletop` then `semloc calibrate DATASET -o FILE`."""
    import subprocess
    import sys

    from tests.conftest import REPO_ROOT

    dataset = tmp_path / "tabletop"
    run = lambda *args: subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO_ROOT,  # noqa: E731
                                       capture_output=True, text=True, timeout=300)
    made = run("sim", "tabletop", "-o", str(dataset), "--frames", "12", "--seed", "4", "--no-multiview")
    assert made.returncode == 0, made.stderr
    output = tmp_path / "likelihoods.json"
    calibrated = run("calibrate", str(dataset), "-o", str(output), "--quiet")
    assert calibrated.returncode == 0, calibrated.stderr
    likelihoods = load_score_likelihoods(output)
    assert output.with_suffix(".png").stat().st_size > 10_000
    assert likelihoods.detector["kind"] == "templates" and likelihoods.source.endswith("tabletop")
    z = likelihoods.z
    for k in range(len(likelihoods.classes)):
        mean_d = np.trapezoid(z * likelihoods.pdf_d[k], z)
        mean_not_d = np.trapezoid(z * likelihoods.pdf_not_d[k], z)
        assert mean_d > mean_not_d + 0.05, likelihoods.classes[k]   # p(z|d)'s mass lies above p(z|not d)'s
    missing = run("calibrate", str(tmp_path / "nope"), "-o", str(output))
    assert missing.returncode == 2 and "does not exist" in missing.stderr
    assert missing.stderr.startswith("semloc calibrate: ") and missing.stderr.count("\n") == 1
