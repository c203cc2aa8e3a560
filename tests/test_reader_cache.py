"""The canonical reader works on any checkpoint, a kept one with weights and configs only
included: it is fitted from the checkpoint's split once and kept beside it."""

from __future__ import annotations

import shutil

from helpers import cli, tiny

from lcrl.checkpoint import find_latest, load_checkpoint
from train.environments.text_reading import READER_CACHE, STATE


def test_the_reader_of_a_weights_only_checkpoint_is_fitted_once_and_kept(
    tmp_path, capsys, monkeypatch
):
    import train.environments.text_reading
    from train.training.loop import Trainer

    # a small reader: what is tested is where it comes from, not how well it reads
    monkeypatch.setattr(train.environments.text_reading, "CANONICAL_MEMBERS", 1)
    monkeypatch.setattr(train.environments.text_reading, "READER_STEPS", 30)

    run = tmp_path / "run"
    Trainer(tiny("lang2d", run, total_steps=200, learning_starts=100)).run()  # reach, push
    kept = tmp_path / "kept"
    kept.mkdir()
    for f in find_latest(run).iterdir():  # weights and configs only, as benchmarks/models
        if f.name != "state.json" and f.name.endswith((".json", "weights.safetensors")):
            shutil.copy2(f, kept / f.name)
    assert not (kept / "state.json").exists()
    capsys.readouterr()
    args = ["act", str(kept), "--canonical-reader", "--episodes", "1"]
    assert cli(*args, "--instruction", "go to the red cube") == 0
    first = capsys.readouterr()
    assert "fitting a canonical reader" in first.err
    assert "canonical sentence" in first.out or "reads" in first.out
    cache = load_checkpoint(kept / READER_CACHE)
    assert cache.has_state(STATE) and cache.meta["reader"]["train"]
    assert cli(*args, "--instruction", "reach for the red cube") == 0
    assert "fitting" not in capsys.readouterr().err  # read from the cache
    # evaluation reads the same reader
    assert cli("eval", str(kept), "--canonical-reader", "--episodes", "1", "--no-progress") == 0
    assert "fitting" not in capsys.readouterr().err
    # an evaluation of some of its families reads the same reader, and leaves it as kept
    before = (kept / READER_CACHE / "meta.json").read_text()
    args = ["eval", str(kept), "--canonical-reader", "--families", "push", "--episodes", "1"]
    assert cli(*args, "--no-progress") == 0
    assert "fitting" not in capsys.readouterr().err
    assert (kept / READER_CACHE / "meta.json").read_text() == before
