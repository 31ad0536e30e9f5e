"""The whole pipeline from the command line: ``gym-coffee run``, then ``fit`` and ``evaluate``
on its files (2 demonstrations, 2 evaluation episodes)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("gym_coffee.teacher")

from lgp_policy.app.cli import main
from lgp_policy.lfd.policy import GPDemonstrationPolicy


def test_run_fit_evaluate(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), "--demos", "2", "--episodes", "2", "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "button_pressed" in printed and "Wilson" in printed
    results = json.loads((out / "results.json").read_text())
    assert results["evaluation"]["n_episodes"] == 2
    assert results["demonstrations"]["n"] == 2
    assert set(results["evaluation"]["stages"]) >= {"cup_grasped", "cup_placed", "button_pressed"}
    for name in (
        "policy.npz",
        "demonstrations.npz",
        "fig1_heteroscedastic.png",
        "fig2_clustering.png",
        "fig4_constraints.png",
        "fig5_reproduction.png",
        "rollout.gif",
    ):
        assert (out / name).stat().st_size > 0, name
    # the constraint report agrees with the demonstrated stages: cup tight at the grasp,
    # machine tight at the place and the press
    checks = {c["stage"]: c for c in results["constraints"]["checks"]}
    assert set(checks) == {"cup_grasped", "cup_placed", "button_pressed"}
    assert all(c["tight"] for c in checks.values()), checks
    policy = GPDemonstrationPolicy.load(out / "policy.npz")
    assert policy.constraints_ == results["constraints"]

    refit = tmp_path / "refit.npz"
    assert main(["fit", str(out / "demonstrations.npz"), "--out", str(refit)]) == 0
    assert main(["fit", str(out / "demonstrations.npz"), "--out", str(refit)]) == 2  # no overwrite
    a = GPDemonstrationPolicy.load(refit)
    np.testing.assert_allclose(a.mean_["joint"], policy.mean_["joint"], atol=1e-8)

    js = tmp_path / "eval.json"
    assert (
        main(
            [
                "evaluate",
                str(refit),
                "--episodes",
                "2",
                "--seed",
                "3",
                "--workers",
                "2",
                "--json",
                str(js),
                "--no-progress",
            ]
        )
        == 0
    )
    again = json.loads(js.read_text())
    assert again["episodes"] == results["evaluation"]["episodes"]
