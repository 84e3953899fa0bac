"""Experiments run from Python return deform's report as Python data."""

import pytest

import deform


def test_an_experiment_returns_its_report(assets, tmp_path):
    e = deform.Experiment.load(assets / "experiments" / "fit_material.ron")
    assert e.name == "fit_material"
    report = e.run(out=tmp_path)
    assert report["material"] == {"NeoHookean": {"Young": {"e": 1e5, "nu": 0.4}}}
    rows = {r["estimate"]: r for r in report["task"]["FitMaterial"]["rows"]}
    # Stage 2 recovers E and nu from data with 1 % position noise (the Rust test suite
    # checks the same figure on the same experiment).
    fit = rows["OutputError"]
    assert abs(fit["young"] / 1e5 - 1) < 0.01 and abs(fit["poisson"] / 0.4 - 1) < 0.01
    # The dataset is written where asked.
    assert report["files"] and all((tmp_path / f).exists() for f in report["files"])


def test_bad_experiments_raise(tmp_path):
    with pytest.raises(deform.LearnError):
        deform.Experiment.load(tmp_path / "missing.ron")
    bad = tmp_path / "bad.ron"
    bad.write_text("Experiment(name: 1)")
    with pytest.raises(deform.LearnError, match="bad.ron"):
        deform.Experiment.load(bad)
