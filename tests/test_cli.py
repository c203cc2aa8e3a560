"""The lcrl command line: help, subcommands, clear errors without tracebacks."""

import json
import subprocess
import sys

import pytest

from train.commands.cli import main


def run(*args):
    return subprocess.run(
        [sys.executable, "-m", "train.commands.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_help_lists_subcommands():
    r = run("--help")
    assert r.returncode == 0
    for cmd in ("demo", "split", "parse"):
        assert cmd in r.stdout


def test_parse_prints_canonical_form(capsys):
    main(["parse", "shove the red block to the left", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert out[0]["canonical"] == "push the red cube left"
    assert out[0]["slots"]["direction"] == "left"


def test_bad_instruction_is_one_clear_line():
    r = run("parse", "push the purple cube left")
    assert r.returncode == 2
    assert r.stderr.startswith("lcrl: error: cannot parse")
    assert "purple" in r.stderr and "Traceback" not in r.stderr


def test_split_writes_a_loadable_file(tmp_path, capsys):
    from captioner.splits import Split

    main(["split", "--out", str(tmp_path / "s.json"), "--seed", "3", "--families", "reach", "push"])
    split = Split.load(tmp_path / "s.json")
    assert split.seed == 3 and split.families == ("reach", "push")
    assert "held-out combinations" in capsys.readouterr().out


def test_split_bad_family_exits_2(capsys):
    with pytest.raises(SystemExit) as e:
        main(["split", "--families", "fly"])
    assert e.value.code == 2
    assert "unknown" in capsys.readouterr().err


def test_demo_writes_report(tmp_path):
    out = tmp_path / "demo"
    r = run("demo", "--out", str(out), "--episodes", "6", "--image-size", "48")
    assert r.returncode == 0, r.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"]["scripted"]["episodes"] == 3
    assert summary["text_encoder"]["dim"] == 384
    for name in ("report.md", "episodes.png", "families.png", "split.json", "config.json"):
        assert (out / name).stat().st_size > 0
    assert f"outputs in {out}" in r.stdout


def test_demo_bad_option_exits_2(tmp_path):
    r = run("demo", "--out", str(tmp_path / "x"), "--episodes", "1")
    assert r.returncode == 2 and "episodes" in r.stderr and "Traceback" not in r.stderr


def test_resume_warns_of_options_the_saved_config_overrides(tmp_path, capsys):
    import dataclasses
    import json

    from train.commands.cli import ignored_on_resume, main, parse_train_args

    out = tmp_path / "run"
    out.mkdir()
    saved = parse_train_args(["lang2d-quick", "--out", str(out)])
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(saved)))
    argv = ["lang2d-quick", "--out", str(out), "--resume", "--total-steps", "9000"]
    argv += ["--no-progress", "--sac.demo-bc", "1.0", "--sac.no-q-filter", "--seed", "0"]
    argv += [f"--batch-size={saved.batch_size}"]
    ignored = ignored_on_resume(argv, parse_train_args(argv))
    # what differs from the saved run, and only that (the seed and batch size are the same)
    assert ignored == [
        "--sac.demo-bc 1.0 (the run has 0.0)",
        "--sac.no-q-filter False (the run has True)",
    ]
    # without --resume, or without a saved run, nothing is ignored
    assert ignored_on_resume(argv[:3] + argv[4:], parse_train_args(argv[:3] + argv[4:])) == []
    # the command says so before it fails for want of a checkpoint
    with pytest.raises(SystemExit):
        main(["train", *argv])
    err = capsys.readouterr().err
    assert "ignored: --sac.demo-bc 1.0 (the run has 0.0)" in err
