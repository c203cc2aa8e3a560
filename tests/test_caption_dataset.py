"""Caption datasets: collection on the registered simulators, the HDF5 format, reading,
errors."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest

from captioner import dataset as ds
from captioner.dataset import CaptionDataset, CaptionDatasetWriter, CollectConfig
from captioner.grammar import FAMILIES_2D, parse
from captioner.rule import RuleCaptioner
from lcrl.errors import LcrlError
from train.commands.captions import caption_simulator, collect
from train.commands.cli import main


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("cap") / "d.h5"
    collect(CollectConfig(out=str(path), episodes=16, progress=False, heldout_fraction=0.5))
    return path


def test_collected_file_layout_and_labels(small):
    with CaptionDataset(small) as data:
        assert data.num_episodes == 16
        assert data.frame_shape == (64, 64, 3)
        assert data.proprio.shape == (data.num_observations, 2)
        c = data.counts()
        assert c["episodes_per_source"] == {"random": 8, "scripted": 8, "policy": 0}
        assert set(data.instruction_set) == {"train", "heldout"}
        # the table is the split's train set first, then its held-out combinations
        first_heldout = data.instruction_set.index("heldout")
        assert set(data.instruction_set[first_heldout:]) == {"heldout"}
        cap = RuleCaptioner(("reach", "push", "put"))
        saw_heldout_target = False
        succeeded = 0
        for e in range(data.num_episodes):
            ep = data.episode(e)
            n = len(ep["frames"])
            assert ep["frames"].dtype == np.uint8 and len(ep["labels"]) == n
            # pusher positions: proprio rows are the pusher's x, y on the table
            assert np.all(np.abs(ep["proprio"]) <= 0.25)
            if ep["source"] == "scripted":
                target = ep["instruction"]
                assert target >= 0
                # scripted episodes stop at success (or at the time limit)
                assert target not in ep["labels"][0]
                if n <= 50:
                    assert target in ep["labels"][-1]
                    succeeded += 1
                saw_heldout_target |= data.instruction_set[target] == "heldout"
                meaning = parse(data.instructions[target])
                assert meaning.family in cap.families
            else:
                assert ep["instruction"] == -1
        assert saw_heldout_target
        assert succeeded >= 6  # of 8 scripted episodes, with action noise
        # frames read in any order with repeats come back in that order
        idx = np.array([5, 2, 5, 0])
        np.testing.assert_array_equal(data.read_frames(idx)[0], data.frames[5])
        np.testing.assert_array_equal(data.read_frames(idx)[1], data.frames[2])
        assert data.episode_of(data.episode_start[3]) == 3
        pairs = list(ds.iter_pairs(data, np.array([0, 1])))
        assert all(data.first_of(j) == a and lab.size for a, j, lab in pairs)
        assert "16 episodes" in data.summary()


def test_scripted_episodes_go_on_after_success(tmp_path):
    """With after_success, a scripted episode runs that many held random steps past the
    step its instruction was first satisfied (bounded by the time limit)."""
    cfg = CollectConfig(
        out=str(tmp_path / "a.h5"),
        sources=("scripted",),
        families=("reach", "push"),
        episodes=8,
        image_size=32,
        max_episode_steps=40,
        after_success=6,
        progress=False,
    )
    collect(cfg)
    went_on = 0
    with CaptionDataset(cfg.out) as data:
        for e in range(data.num_episodes):
            ep = data.episode(e)
            hit = [t for t, lab in enumerate(ep["labels"]) if ep["instruction"] in lab]
            if not hit:  # never satisfied: the time limit ended it
                assert len(ep["frames"]) == cfg.max_episode_steps + 1
                continue
            # the observation after the success step, then six more (or the time limit)
            assert len(ep["frames"]) == min(hit[0] + 1 + 6, cfg.max_episode_steps + 1)
            went_on += 1
    assert went_on >= 6
    with pytest.raises(LcrlError, match="after_success"):
        CollectConfig(after_success=-1).validate()


def test_scripted_pushes_can_stop_short(tmp_path):
    """With stop_short, scripted pushes end part of the way (held random actions follow),
    so fewer reach the push distance than whole pushes from the same layouts do."""

    def own_successes(stop_short: float) -> tuple[float, list[int]]:
        cfg = CollectConfig(
            out=str(tmp_path / f"{stop_short}.h5"),
            sources=("scripted",),
            families=("push",),
            episodes=16,
            image_size=32,
            stop_short=stop_short,
            progress=False,
        )
        collect(cfg)
        with CaptionDataset(cfg.out) as data:
            eps = [data.episode(e) for e in range(data.num_episodes)]
        hit = [any(ep["instruction"] in lab for lab in ep["labels"]) for ep in eps]
        return float(np.mean(hit)), [len(ep["frames"]) for ep in eps]

    whole, _ = own_successes(0.0)
    short, lengths = own_successes(1.0)
    assert whole >= 0.9 and short <= whole - 0.25, (whole, short)
    assert min(lengths) > 10  # at least the ten held random steps after stopping
    for bad in (-0.1, 1.5):
        with pytest.raises(LcrlError, match="stop_short must be in"):
            CollectConfig(stop_short=bad).validate()


def test_labels_name_what_the_rule_captioner_says(tmp_path):
    """An episode's label ids, written and read back, name the captioner's instructions."""
    cfg = CollectConfig(out=str(tmp_path / "x.h5"), sources=("scripted",), progress=False)
    simulator = caption_simulator(cfg.env)
    src = ds._Source(cfg, simulator, cfg.resolved_families(simulator))
    texts, sets = ds.instruction_table(ds.make_split(0, FAMILIES_2D))
    table = [parse(t) for t in texts]
    writer = CaptionDatasetWriter(cfg.out, texts, sets, (64, 64, 3), 2, {"test": True})
    ep, scenes = ds._episode(src, "scripted", cfg, 5, np.random.default_rng(1), table, sets, writer)
    writer.add_episode(**ep)
    writer.close()
    cap = RuleCaptioner(("reach", "push", "put"))
    with CaptionDataset(cfg.out) as data:
        assert data.meta == {"test": True}
        back = data.episode(0)
        assert len(back["labels"]) == len(scenes) > 1
        for ids, scene in zip(back["labels"], scenes, strict=True):
            said = {i.text for i in cap.caption(scenes[0], scene)}
            assert {data.instructions[i] for i in ids} == said
        assert any(back["labels"])  # the scripted episode achieved something
        assert data.instructions[back["instruction"]] in said  # its target, at the end


def interrupt_at_episode(monkeypatch, n):
    """Ctrl-C as the ``n``-th episode of a collection starts (the first is 1)."""
    real = ds._episode
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(ds, "_episode", flaky)


def test_interrupt_keeps_finished_episodes(tmp_path, monkeypatch):
    path = tmp_path / "cut.h5"
    interrupt_at_episode(monkeypatch, 4)
    with pytest.raises(KeyboardInterrupt):
        collect(CollectConfig(out=str(path), episodes=10, progress=False))
    with CaptionDataset(path) as data:
        assert data.num_episodes == 3
    assert not path.with_name(path.name + ".part").exists()


def test_an_interrupted_collection_resumes_where_it_stopped(tmp_path, monkeypatch):
    path = tmp_path / "cut.h5"
    interrupt_at_episode(monkeypatch, 4)
    cfg = CollectConfig(out=str(path), episodes=6, progress=False, resume=True, overwrite=True)
    with pytest.raises(KeyboardInterrupt):
        collect(cfg)  # no file yet: --resume starts one
    with CaptionDataset(path) as data:
        kept = [data.episode(e)["frames"] for e in range(data.num_episodes)]
    assert len(kept) == 3
    collect(cfg)
    with CaptionDataset(path) as data:
        assert data.num_episodes == 6 and data.meta["collect"]["episodes"] == 6
        for e, frames in enumerate(kept):
            np.testing.assert_array_equal(data.episode(e)["frames"], frames)
        assert data.counts()["episodes_per_source"] == {"random": 3, "scripted": 3, "policy": 0}
        size = data.num_observations
    collect(cfg)  # nothing left to add
    with CaptionDataset(path) as data:
        assert data.num_episodes == 6 and data.num_observations == size
    other = dataclasses.replace(cfg, seed=3, episodes=2, overwrite=False)
    with pytest.raises(LcrlError, match=r"other settings \(collect.seed\).*--overwrite"):
        collect(other)
    collect(dataclasses.replace(other, overwrite=True))  # replaced, not resumed
    with CaptionDataset(path) as data:
        assert data.num_episodes == 2 and data.meta["collect"]["seed"] == 3
    assert not path.with_name(path.name + ".part").exists()


def test_bad_settings_and_files(tmp_path, small):
    with pytest.raises(LcrlError, match="unknown env 'mars' for caption datasets"):
        collect(CollectConfig(out=str(tmp_path / "a.h5"), env="mars"))
    with pytest.raises(LcrlError, match="unknown env 'gym' for caption datasets"):
        collect(CollectConfig(out=str(tmp_path / "a.h5"), env="gym"))  # no instructions
    with pytest.raises(LcrlError, match="--policy"):
        collect(CollectConfig(out=str(tmp_path / "a.h5"), sources=("policy",)))
    with pytest.raises(LcrlError, match="supports the families"):
        collect(CollectConfig(out=str(tmp_path / "a.h5"), families=("stack",)))
    with pytest.raises(LcrlError, match="--overwrite"):
        collect(CollectConfig(out=str(small), episodes=1, progress=False))
    with pytest.raises(LcrlError, match="no caption dataset"):
        CaptionDataset(tmp_path / "missing.h5")
    (tmp_path / "junk.h5").write_text("not hdf5")
    with pytest.raises(LcrlError, match="not an HDF5 file"):
        CaptionDataset(tmp_path / "junk.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "something else"
    with pytest.raises(LcrlError, match="not an lcrl caption dataset"):
        CaptionDataset(tmp_path / "other.h5")
    w = CaptionDatasetWriter(tmp_path / "w.h5", ["reach the red cube"], ["train"], (8, 8, 3), 2, {})
    with pytest.raises(LcrlError, match="label ids"):
        w.add_episode(np.zeros((2, 8, 8, 3)), np.zeros((2, 2)), [[], [3]], "random")
    with pytest.raises(LcrlError, match="as many frames"):
        w.add_episode(np.zeros((2, 8, 8, 3)), np.zeros((1, 2)), [[], []], "random")
    with pytest.raises(LcrlError, match="nothing written"):
        w.close()


def test_cli_collect(tmp_path, capsys):
    out = tmp_path / "cli.h5"
    main(["caption", "collect", "--out", str(out), "--episodes", "4", "--no-progress"])
    assert "4 episodes" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["caption", "collect", "--out", str(out), "--episodes", "4", "--no-progress"])
    assert e.value.code == 2
    assert "lcrl: error:" in capsys.readouterr().err


def test_robosuite_collection(tmp_path):
    pytest.importorskip("robosuite")
    path = tmp_path / "robo.h5"
    collect(
        CollectConfig(
            out=str(path), env="robosuite", episodes=2, max_episode_steps=6, progress=False
        )
    )
    with CaptionDataset(path) as data:
        assert data.num_episodes == 2 and data.proprio.shape[1] == 4
        assert data.frame_shape == (64, 64, 3)
        assert data.frames[0].std() > 0  # a rendered picture, not a blank frame


def test_a_registered_simulator_collects_through_its_registry_entry(tmp_path, monkeypatch):
    """A simulator added to train.environments.simulators.ENVS collects caption datasets: the
    collector takes it from the caller, and the file records the entry's name."""
    import dataclasses

    from train.environments.simulators import ENVS

    calls = []

    def make(cfg):
        calls.append(cfg)
        return ENVS["tabletop2d"].make(cfg)

    spec = dataclasses.replace(ENVS["tabletop2d"], make=make, caption_name="")
    monkeypatch.setitem(ENVS, "flat", spec)
    path = tmp_path / "flat.h5"
    main(["caption", "collect", "--env", "flat", "--out", str(path), "--episodes", "2",
          "--image-size", "32", "--no-progress"])  # fmt: skip
    assert calls and calls[0].kind == "flat" and calls[0].image_obs
    with CaptionDataset(path) as data:
        assert data.meta["env"] == "flat" and data.frame_shape == (32, 32, 3)
        assert data.meta["slot_layout"] == [2, 8, 3, 2]
    # the 2D tabletop under its kind records the name its datasets always had
    path = tmp_path / "tabletop2d.h5"
    collect(CollectConfig(out=str(path), env="tabletop2d", episodes=1, progress=False))
    with CaptionDataset(path) as data:
        assert data.meta["env"] == "lang2d"
    # without a scripted controller: random episodes only
    monkeypatch.setitem(ENVS, "flat", dataclasses.replace(spec, scripted=None))
    with pytest.raises(LcrlError, match="no scripted controller"):
        collect(CollectConfig(out=str(tmp_path / "x.h5"), env="flat", progress=False))


def test_old_dataset_files_still_load(small):
    """Files name their simulator as they always did (lang2d, robosuite): such a file is
    read, and its name maps to the registered simulator."""
    from train.environments.simulators import canonical_kind

    with CaptionDataset(small) as data:
        assert data.meta["env"] == "lang2d"
    assert canonical_kind("lang2d") == "tabletop2d"
    assert canonical_kind("robosuite") == "robosuite"


def test_merge_concatenates_episodes_and_refuses_mismatches(tmp_path, small, capsys):
    other = tmp_path / "other.h5"
    collect(CollectConfig(out=str(other), episodes=5, seed=7, progress=False))
    out = tmp_path / "merged.h5"
    main(["caption", "merge", str(small), str(other), "--out", str(out), "--no-progress"])
    assert "21 episodes" in capsys.readouterr().out
    with CaptionDataset(small) as a, CaptionDataset(other) as b, CaptionDataset(out) as m:
        assert m.num_episodes == a.num_episodes + b.num_episodes
        assert m.num_observations == a.num_observations + b.num_observations
        assert m.instructions == a.instructions
        assert [x["collect"]["seed"] for x in m.meta["merged"]] == [0, 7]
        for src, e, me in ((a, 3, 3), (b, 4, a.num_episodes + 4)):
            x, y = src.episode(e), m.episode(me)
            np.testing.assert_array_equal(x["frames"], y["frames"])
            np.testing.assert_array_equal(x["proprio"], y["proprio"])
            assert x["labels"] == y["labels"]
            assert (x["source"], x["instruction"]) == (y["source"], y["instruction"])
            sa, sb = int(src.episode_start[e]), int(src.episode_start[e + 1])
            ma = int(m.episode_start[me])
            np.testing.assert_array_equal(src.state[sa:sb], m.state[ma : ma + sb - sa])
    with pytest.raises(LcrlError, match="at least two"):
        ds.merge([small], tmp_path / "x.h5")
    with pytest.raises(LcrlError, match="named twice"):
        ds.merge([small, small], tmp_path / "x.h5")
    with pytest.raises(LcrlError, match="one of the inputs"):
        ds.merge([small, other], other, overwrite=True)
    with pytest.raises(LcrlError, match="--overwrite"):
        ds.merge([small, other], out)
    reach = tmp_path / "reach.h5"
    collect(CollectConfig(out=str(reach), episodes=2, families=("reach",), progress=False))
    with pytest.raises(LcrlError, match="different instruction tables"):
        ds.merge([small, reach], tmp_path / "x.h5")
    big = tmp_path / "big.h5"
    collect(CollectConfig(out=str(big), episodes=2, image_size=32, progress=False))
    with pytest.raises(LcrlError, match=r"has image_size 64, .*big.h5 has 32"):
        ds.merge([small, big], tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()


def test_interrupted_merge_leaves_no_file(tmp_path, small, monkeypatch):
    calls = {"n": 0}
    real = CaptionDatasetWriter.add_episode

    def add(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(CaptionDatasetWriter, "add_episode", add)
    out = tmp_path / "m.h5"
    with pytest.raises(KeyboardInterrupt):
        ds.merge([small, _copy(small, tmp_path / "c.h5")], out, progress=False)
    assert not out.exists() and not out.with_name("m.h5.part").exists()


def _copy(src, dst):
    import shutil

    shutil.copy(src, dst)
    return dst


def test_policy_episodes_are_labelled_with_every_family_of_the_dataset(tmp_path):
    """A policy trained on one family (a put or stack teacher) also reaches and moves
    objects: its episodes carry the labels of every family the dataset holds, so that no
    frame teaches the captioner a false negative."""
    from helpers import tiny

    from train.commands.captions import PolicyEpisodes
    from train.training.loop import Trainer

    cfg = tiny("lang2d-quick", tmp_path / "run", total_steps=60, learning_starts=30)
    cfg.env.families = ("reach",)
    Trainer(cfg).run()
    out = tmp_path / "p.h5"
    config = CollectConfig(
        out=str(out), sources=("policy",), policy=str(tmp_path / "run"), episodes=3,
        max_episode_steps=8, progress=False,
    )  # fmt: skip
    episodes = PolicyEpisodes(config, FAMILIES_2D)
    assert episodes.captioner.families == FAMILIES_2D
    assert PolicyEpisodes(config).captioner.families == ("reach",)  # the policy's own
    said = []  # what the dataset-family captioner said of each frame of an episode
    caption = episodes.captioner.caption
    episodes.captioner.caption = lambda s0, s: said.append(caption(s0, s)) or said[-1]
    texts, sets = ds.instruction_table(ds.make_split(0, FAMILIES_2D))
    writer = CaptionDatasetWriter(tmp_path / "w.h5", texts, sets, (64, 64, 3), 2, {})
    got = episodes.episode(config, 3, writer)
    writer.discard()
    assert len(said) == len(got["frames"]) > 1
    assert got["labels"] == [writer.ids([m.text for m in c]) for c in said]
    collect(config)
    with CaptionDataset(out) as data:
        assert data.meta["families"] == list(FAMILIES_2D)
        assert data.num_episodes == 3
        assert data.meta["policy_checkpoint"] == episodes.checkpoint_name
        first = [data.episode(e)["frames"] for e in range(3)]
    collect(dataclasses.replace(config, episodes=4, resume=True))  # one more episode
    with CaptionDataset(out) as resumed:
        assert resumed.num_episodes == 4
        for e in range(3):
            np.testing.assert_array_equal(resumed.episode(e)["frames"], first[e])
    Trainer(dataclasses.replace(cfg, total_steps=70, resume=True)).run()  # a later checkpoint
    with pytest.raises(LcrlError, match="policy_checkpoint"):
        collect(dataclasses.replace(config, episodes=5, resume=True))
