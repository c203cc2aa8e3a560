"""The robosuite perception benchmark: with a test dataset its headline is the model's
figures on those episodes, the held-out episodes that chose the build beside as
``validation_*``; its options are checked before any work."""

from __future__ import annotations

import json

import pytest

from benchmarks import perception


def _result(error: float, presence: float = 1.0) -> dict:
    return {
        "position_error_cm": error,
        "presence_accuracy": presence,
        "position_error_cm_without_hold": error + 0.3,
        "hold_radius": 0.06,
        "presence_accuracy_per_frame": 0.98,
        "within_reach_margin": 0.9,
        "within_push_distance": 0.99,
        "frames_all_present_right": 1.0,
        "near_position_error_cm": error * 2,
        "near_frames_all_present_right": 1.0,
        "frames_all_present_right_per_frame": 0.9,
    }


def test_figures_round_and_add_the_new_layouts_only_when_given():
    figures = perception._figures(_result(0.83217), None)
    assert figures["position_error_cm"] == 0.832
    assert figures["near_position_error_cm"] == 1.664
    assert "position_error_cm_new_layouts" not in figures
    with_layouts = perception._figures(_result(0.8), _result(0.69123))
    assert with_layouts["position_error_cm_new_layouts"] == 0.691


def test_models_compared_on_a_test_set_need_the_test_set(capsys):
    with pytest.raises(SystemExit):
        perception.main(["--test-models", "some/model", "--eval-only"])
    assert "--test-models needs --test-data" in capsys.readouterr().err


def test_a_missing_test_set_is_named_before_any_work(tmp_path, capsys):
    with pytest.raises(SystemExit):
        perception.main(["--test-data", str(tmp_path / "none.h5"), "--work", str(tmp_path)])
    assert "no such file or folder" in capsys.readouterr().err


def test_the_perception_swap_reads_push_and_lift_from_an_evaluation_done(tmp_path):
    from benchmarks.perception_swap import _pair

    fams = {
        "push": {"success": 0.62, "ci": [0.5, 0.7], "episodes": 94},
        "lift": {"success": 0.8, "ci": [0.7, 0.9], "episodes": 106},
    }
    doc = {"sets": {"train": {"success": 0.72, "episodes": 200, "families": fams}}}
    (tmp_path / "pushlift-seed1.json").write_text(json.dumps(doc))
    pair = _pair(tmp_path, "no/model/needed", 1, 200, [])  # read, not run again
    assert (pair["push"], pair["lift"], pair["pooled"]) == (0.62, 0.8, 0.72)
    assert pair["family_episodes"] == {"push": 94, "lift": 106}


def test_the_perception_swap_names_a_missing_model(capsys):
    from benchmarks.perception_swap import main

    with pytest.raises(SystemExit):
        main(["--perception", "no/such/model"])
    assert "no such file or folder: no/such/model" in capsys.readouterr().err
