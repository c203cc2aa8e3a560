"""Learned captioner and reward model: vocabulary, metrics, training, loading, evaluation."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch
from helpers import oracle_perception, tiny

from captioner.dataset import CaptionDataset, CollectConfig
from captioner.grammar import Instruction
from captioner.learned import (
    NONE_TEXT,
    CaptionModelConfig,
    CaptionTrainConfig,
    LearnedCaptioner,
    Vocabulary,
    bleu4,
    evaluate_models,
    roc_auc,
    slot_matches,
    train_models,
)
from lcrl.checkpoint import seal_checkpoint
from lcrl.errors import LcrlError
from train.commands.captions import collect
from train.commands.cli import main

TINY = CaptionModelConfig(channels=(16, 16, 16, 16), features=64, hidden=64, embed=32)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("lc") / "d.h5"
    collect(
        CollectConfig(
            out=str(path), episodes=80, image_size=32, families=("reach", "push"), progress=False
        )
    )
    return path


@pytest.fixture(scope="module")
def trained(dataset, tmp_path_factory, one_thread):
    out = tmp_path_factory.mktemp("lc") / "ckpt"
    cfg = CaptionTrainConfig(data=str(dataset), out=str(out), steps=400, model=TINY, progress=False)
    return train_models(cfg)


def test_vocabulary_round_trip_and_errors():
    v = Vocabulary.from_grammar()
    for text in ("push the red cube left", "put the blue cylinder in front of the red cube"):
        ids = v.encode(text, 12)
        assert len(ids) == 12 and v.decode(ids) == text
    assert v.decode(v.encode(NONE_TEXT, 12)) == NONE_TEXT
    with pytest.raises(LcrlError, match="vocabulary"):
        v.encode("push the red banana left", 12)
    with pytest.raises(LcrlError, match="longer"):
        v.encode("push the red cube left", 4)


def test_metrics():
    assert bleu4("push the red cube left", ["push the red cube left"]) == pytest.approx(1.0)
    assert bleu4("lift", ["push the red cube left"]) == 0.0
    one_word_off = bleu4("push the red cube right", ["push the red cube left"])
    assert 0.3 < one_word_off < 1.0
    # multiple references: the best matching n-grams count
    assert bleu4("reach the red cube", ["push the red cube left", "reach the red cube"]) == (
        pytest.approx(1.0)
    )
    rng = np.random.default_rng(0)
    s, y = rng.normal(size=200), rng.random(200) < 0.4
    s[y] += 1.0
    brute = np.mean([(a > b) + 0.5 * (a == b) for a in s[y] for b in s[~y]])
    assert roc_auc(s, y) == pytest.approx(brute)
    assert roc_auc(np.array([1, 1, 1.0]), np.array([1, 0, 1], bool)) == pytest.approx(0.5)
    assert np.isnan(roc_auc(np.ones(3), np.ones(3, bool)))
    lab = Instruction("push", "red", "cube", direction="left")
    gen = Instruction("push", "red", "cylinder", direction="left")
    assert slot_matches(gen, lab) == {
        "verb": True, "object": False, "colour": True, "shape": False, "direction": True
    }  # fmt: skip
    assert not any(slot_matches(None, lab).values())


def test_training_learns_and_checkpoints_load(trained, dataset):
    lc = LearnedCaptioner.load(trained)
    assert lc.captioner is not None and lc.reward is not None
    with CaptionDataset(dataset) as data:
        results = evaluate_models(lc, data)
        assert results["episodes"] == 16  # the held-out 20% of 80 episodes
        seen = results["seen"]
        # Chance is about 1 in 30 instructions; the reward model sees balanced pairs with
        # hard negatives (same object, other instruction).
        assert seen["exact_match"] >= 0.1
        assert seen["auc"] >= 0.7
        assert set(seen["slot_accuracy"]) >= {"verb", "object"}
        # inference on raw frames: captions are vocabulary sentences, scores probabilities
        f, c = data.frames[0:3], data.frames[5:8]
        p0, p = data.proprio[0:3], data.proprio[5:8]
        caps = lc.caption(f, c, p0, p)
        assert len(caps) == 3 and all(isinstance(t, str) and lp <= 0 for t, lp in caps)
        words = set(lc.vocab.words)
        assert all(set(t.split()) <= words for t, _ in caps)
        beams = lc.caption(f, c, p0, p, beam=3)
        assert len(beams) == 3
        probs = lc.score(["reach the red cube", "shove the blue block left", "hello"], f, c, p0, p)
        assert probs.shape == (3,) and np.all((probs >= 0) & (probs <= 1))
        with pytest.raises(LcrlError, match="frame pairs"):
            lc.score(["reach the red cube"], f, c, p0, p)
        with pytest.raises(LcrlError, match="uint8 pairs"):
            lc.caption(f[:, :16], c[:, :16], p0, p)
        with pytest.raises(LcrlError, match="proprioception"):
            lc.caption(f, c)


def test_beam_search_agrees_with_greedy_at_width_one(trained, dataset):
    lc = LearnedCaptioner.load(trained)
    with CaptionDataset(dataset) as data:
        idx = np.arange(10, 20)
        first = data.read_frames(data.first_of(idx))
        cur = data.read_frames(idx)
        args = (first, cur, data.proprio[data.first_of(idx)], data.proprio[idx])
        greedy = lc.caption(*args)
        with torch.no_grad():
            ctx = lc.captioner.encoder(*lc._inputs(*args))
            beam1 = [b[0] for b in lc.captioner.beam(ctx, 1)]
        assert [t for t, _ in greedy] == [lc.vocab.decode(ids) for ids, _ in beam1]
        np.testing.assert_allclose([s for _, s in greedy], [s for _, s in beam1], atol=1e-4)
        # wider beams: up to 4 distinct finished captions per pair, best first
        wide = lc.captions(*args, beam=4)
        for row in wide:
            scores = [sc for _, sc in row]
            assert 1 <= len(row) <= 4 and scores == sorted(scores, reverse=True)
            assert len({t for t, _ in row}) == len(row)


def test_errors(trained, dataset, tmp_path):
    with pytest.raises(LcrlError, match="models must be"):
        train_models(CaptionTrainConfig(data=str(dataset), out=str(tmp_path), models=("x",)))
    with pytest.raises(LcrlError, match="already holds"):
        train_models(CaptionTrainConfig(data=str(dataset), out=str(trained), steps=1))
    with pytest.raises(LcrlError, match="no caption dataset"):
        train_models(CaptionTrainConfig(data=str(tmp_path / "none.h5"), out=str(tmp_path / "o")))
    with pytest.raises(LcrlError):
        LearnedCaptioner.load(tmp_path / "missing")
    other = tmp_path / "big.h5"
    collect(CollectConfig(out=str(other), episodes=2, image_size=48, progress=False))
    lc = LearnedCaptioner.load(trained)
    with CaptionDataset(other) as data, pytest.raises(LcrlError, match="32x32x3 frames"):
        evaluate_models(lc, data)


def test_cli_train_and_eval(dataset, tmp_path, capsys, one_thread):
    out = tmp_path / "cli"
    args = ["caption", "train", "--data", str(dataset), "--out", str(out), "--steps", "5"]
    args += ["--models", "reward", "--model.channels", "8", "8", "8", "8", "--no-progress"]
    main(args)
    text = capsys.readouterr().out
    assert "reward model AUC" in text and "exact match" not in text
    js = tmp_path / "r.json"
    main(["caption", "eval", str(out), "--json", str(js)])
    assert "seen" in json.loads(js.read_text())
    lc = LearnedCaptioner.load(out)
    with pytest.raises(LcrlError, match="no captioner"):
        lc.caption(np.zeros((1, 32, 32, 3), np.uint8), np.zeros((1, 32, 32, 3), np.uint8))
    with pytest.raises(SystemExit) as e:
        main(["caption", "eval", str(tmp_path / "nothing")])
    assert e.value.code == 2


def _small_run(out, checkpoint, **relabel):
    from train.configs.config import RelabelConfig

    relabel_cfg = RelabelConfig(checkpoint=str(checkpoint), **relabel)
    return tiny("lang2d", out, scripted_fraction=0.5, eval_episodes=2, relabel=relabel_cfg)


def test_push_misses_score_each_step_with_the_reward_model(trained, tmp_path, one_thread):
    from benchmarks.push_misses import run_pushes, summarise_rewards
    from train.training.loop import Trainer

    out = tmp_path / "run"
    Trainer(tiny("lang2d", out, total_steps=120, learning_starts=100)).run()
    eps = run_pushes(out, 2, captioner=trained, threshold=0.5, stochastic=True)
    for e in eps:
        keys = {"rule", "learned", "prob", "along", "at_object"}
        assert e["steps"] and keys <= set(e["steps"][0])
        assert all((st["prob"] >= 0.5) == st["learned"] for st in e["steps"])
        assert e["steps"][-1]["rule"] == e["success"]  # the last step is the env's verdict
    steps = [st for e in eps for st in e["steps"]]
    assert summarise_rewards(steps)["steps"] == len(steps)


def test_reach_rewards_score_reach_on_a_policys_own_episodes(trained, tmp_path, one_thread):
    from benchmarks.reach_rewards import run_episodes, summarise
    from train.training.loop import Trainer

    out = tmp_path / "run"
    Trainer(tiny("lang2d", out, total_steps=120, learning_starts=100)).run()
    steps = run_episodes(out, trained, "push", 2)
    assert steps and {"rule", "prob", "moving", "gap"} <= set(steps[0])
    assert all(0.0 <= st["prob"] <= 1.0 for st in steps)
    # the rule's reach holds within reach_margin (2 cm) of the object's edge (and where the
    # pusher touches it, which a box's corner allows further out)
    assert all(st["rule"] for st in steps if st["gap"] <= 0.02 - 1e-6)
    assert summarise(steps)["steps"] == len(steps)


def test_training_with_learned_captioner_and_reward(trained, tmp_path, one_thread):
    from train.training.loop import Trainer

    cfg = _small_run(
        tmp_path / "run", trained, captioner="learned", reward="learned", min_logprob=-1e9
    )
    trainer = Trainer(cfg)
    trainer.run()
    lab = trainer.task.labeller
    assert lab is not None and lab.use_captioner and lab.use_reward
    assert lab.kept + lab.skipped > 0  # the captioner read the episodes' frames
    gs = trainer.buffer.goal_space
    n = trainer.buffer.size
    assert gs._total[:n].max() > 0  # some stored episode has learned labels to relabel with
    # progress.csv reports how far the learned labels and rewards agree with the rule's
    with (tmp_path / "run" / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert rows and {"labels_precision", "labels_recall", "rewards_precision"} <= set(rows[0])
    assert any(0.0 <= float(r["rewards_recall"]) <= 1.0 for r in rows)


def test_confirmed_labels_are_rewarded_where_they_were_read(trained, tmp_path, one_thread):
    from train.training.loop import Trainer

    cfg = _small_run(
        tmp_path / "run", trained, captioner="learned", reward="learned", min_logprob=-1e9,
        threshold=0.3, confirm=True,
    )  # fmt: skip
    trainer = Trainer(cfg)
    trainer.run()
    gs = trainer.buffer.goal_space
    slots = np.flatnonzero(gs._nlab[: trainer.buffer.high] > 0)
    assert slots.size > 0  # something was confirmed
    for j in slots:  # every stored candidate carries its reward bit at its own observation
        ids = gs._labels[j, : gs._nlab[j]].astype(np.int64)
        assert gs.achieved(np.full(ids.size, j), ids).all()


def test_agreement_counts_against_the_rule_labels(trained):
    from captioner.learned import LearnedLabeller

    lab = LearnedLabeller(LearnedCaptioner.load(trained), ["a", "b", "c"], 3)
    lab.compare("labels", [[], [0, 1], [2]], [[], [0], [1, 2]])  # tp 2, fp 1, fn 1
    lab.compare("rewards", [[0, 2]], [[1, 2]], among=[0, 2])  # 1 is not a candidate
    got = lab.agreement()
    assert got["labels_precision"] == pytest.approx(2 / 3)
    assert got["labels_recall"] == pytest.approx(2 / 3)
    assert got["rewards_precision"] == 0.5 and got["rewards_recall"] == 1.0
    assert all(np.isnan(v) for v in lab.agreement().values())  # reset after reading


def test_agreement_per_family(trained):
    from captioner.learned import LearnedLabeller

    table = ["reach the red cube", "push the red cube left", "reach the blue cube"]
    lab = LearnedLabeller(LearnedCaptioner.load(trained), table, 3)
    # reach: tp 1 (0), fp 1 (2), fn 0; push: tp 0, fp 0, fn 1 (1)
    lab.compare("rewards", [[0, 2]], [[0, 1]])
    got = lab.agreement()
    assert got["rewards_precision"] == 0.5 and got["rewards_recall"] == 0.5
    assert got["rewards_reach_precision"] == 0.5 and got["rewards_reach_recall"] == 1.0
    assert np.isnan(got["rewards_push_precision"]) and got["rewards_push_recall"] == 0.0
    assert np.isnan(got["labels_push_recall"])  # no labels compared


def test_labeller_thresholds_and_candidates(trained, dataset):
    from captioner.learned import LearnedLabeller

    lc = LearnedCaptioner.load(trained)
    with CaptionDataset(dataset) as data:
        ep = max(range(data.num_episodes), key=lambda e: sum(map(len, data.episode(e)["labels"])))
        e = data.episode(ep)
        frames, proprio = e["frames"], e["proprio"]
        table = data.instructions
        num_train = data.instruction_set.index("heldout")
        everything = LearnedLabeller(lc, table, num_train, min_logprob=-1e9, beam=3)
        labels = everything.labels(frames, proprio)
        assert len(labels) == len(frames) and labels[0] == []
        assert any(labels) and all(0 <= i < num_train for ids in labels for i in ids)
        nothing = LearnedLabeller(lc, table, num_train, min_logprob=1.0, beam=3)
        assert not any(nothing.labels(frames, proprio)) and nothing.skipped > 0
        greedy = LearnedLabeller(lc, table, num_train, min_logprob=-1e9, beam=0)
        assert all(len(ids) <= 1 for ids in greedy.labels(frames, proprio))
        cands = sorted({i for ids in labels for i in ids})
        achieved = everything.achieved(frames, proprio, cands)
        assert achieved[0] == [] and all(set(a) <= set(cands) for a in achieved)
        strict = LearnedLabeller(lc, table, num_train, threshold=1.01)
        assert not any(strict.achieved(frames, proprio, cands))
        # a family's own threshold: that family never counts, the others as by default
        family = next(table[c].split()[0] for a in achieved for c in a)
        of_family = {c for c in cands if table[c].split()[0] == family}
        without = LearnedLabeller(lc, table, num_train, family_thresholds={family: 1.01})
        assert without.achieved(frames, proprio, cands) == [
            [c for c in a if c not in of_family] for a in achieved
        ]
        assert LearnedLabeller(
            lc, table, num_train, threshold=1.01, family_thresholds={family: 0.5}
        ).achieved(frames, proprio, cands) == [[c for c in a if c in of_family] for a in achieved]
        # confirm: a caption stays a relabelling candidate only where it is rewarded too
        confirming = LearnedLabeller(lc, table, num_train, min_logprob=-1e9, confirm=True)
        assert confirming.confirmed(labels, achieved) == [
            [i for i in ids if i in hit] for ids, hit in zip(labels, achieved, strict=True)
        ]
        assert everything.confirmed(labels, achieved) == labels  # off by default
        strict_confirm = LearnedLabeller(lc, table, num_train, threshold=1.01, confirm=True)
        nothing_hit = strict_confirm.achieved(frames, proprio, cands)
        assert not any(strict_confirm.confirmed(labels, nothing_hit))
        # reward labels: the training ids judged achieved, with the captions too (both)
        every = everything.achieved(frames, proprio, range(len(table)))
        judged = [[c for c in a if c < num_train] for a in every]
        alone = LearnedLabeller(lc, table, num_train, captioner=False, reward_labels=True)
        assert alone.judged(labels, every) == judged
        union = LearnedLabeller(lc, table, num_train, reward_labels=True)
        assert union.judged(labels, every) == [
            sorted(set(a) | set(b)) for a, b in zip(labels, judged, strict=True)
        ]
        pairs = list(zip(labels, judged, strict=True))
        assert any(set(a) - set(b) for a, b in pairs) and any(set(b) - set(a) for a, b in pairs)
        with pytest.raises(LcrlError, match="reward-model labels need"):
            LearnedLabeller(lc, table, num_train, reward=False, reward_labels=True)
        with pytest.raises(LcrlError, match="confirmation needs both"):
            LearnedLabeller(lc, table, num_train, reward=False, confirm=True)
        # the online check of one pair agrees with the episode's batch scoring
        n = len(frames)
        for goal in cands[:3]:
            got = everything.satisfied(
                [goal] * n, np.repeat(frames[:1], n, 0), frames, np.repeat(proprio[:1], n, 0),
                proprio,
            )  # fmt: skip
            assert got[1:].tolist() == [goal in a for a in achieved[1:]]
        assert everything.satisfied([], frames[:0], frames[:0], proprio[:0], proprio[:0]).shape == (
            0,
        )
        # agreement: what the reward model judges achieved where the captioner reads it too
        both = LearnedLabeller(lc, table, num_train, min_logprob=-1e9, beam=3, agree=True)
        agreed = both.achieved(frames, proprio, cands, labels)
        assert agreed == [
            [c for c in a if c in lab] for a, lab in zip(achieved, labels, strict=True)
        ]
        # an observation whose labels are cleared keeps nothing
        cleared = [[] if t % 2 else lab for t, lab in enumerate(labels)]
        assert any(achieved[1::2])  # the reward model alone judges some of those achieved
        assert all(not a for a in both.achieved(frames, proprio, cands, cleared)[1::2])
        with pytest.raises(LcrlError, match="captioner labels"):
            both.achieved(frames, proprio, cands)
        with pytest.raises(LcrlError, match="both the learned captioner"):
            LearnedLabeller(lc, table, num_train, reward=False, agree=True)


def test_learned_rewards_do_not_end_training_episodes_at_the_privileged_success(trained, tmp_path):
    from train.environments.tasks import find_language_wrapper
    from train.training.loop import Trainer

    for reward, ends in (("learned", False), ("captioner", False), ("rule", True)):
        cfg = _small_run(tmp_path / reward, trained, captioner="learned", reward=reward)
        trainer = Trainer(cfg)
        assert cfg.env.train_until_success  # the setting stays; the learned rewards win
        assert find_language_wrapper(trainer.envs[0]).terminate_on_success is ends, reward


@pytest.mark.parametrize("labels", ["reward", "both"])
def test_reward_model_labels_relabel_with_every_instruction_it_rewards(
    trained, tmp_path, one_thread, labels
):
    from train.training.loop import Trainer

    cfg = _small_run(tmp_path / "run", trained, captioner=labels, reward="learned", threshold=0.3)
    trainer = Trainer(cfg)
    trainer.run()
    lab = trainer.task.labeller
    assert lab.reward_labels and lab.use_captioner is (labels == "both")
    assert (lab.kept + lab.skipped > 0) is (labels == "both")  # captions read or not
    gs = trainer.buffer.goal_space
    high = trainer.buffer.high
    slots = np.flatnonzero(gs._nlab[:high] > 0)
    assert slots.size > 0
    num_train = trainer.task.num_train
    every = np.arange(num_train)
    for j in range(high):  # every training id rewarded there is a candidate
        ids = set(gs._labels[j, : gs._nlab[j]].tolist())
        rewarded = set(every[gs.achieved(np.full(num_train, j), every)].tolist())
        if labels == "reward":  # ... and nothing else
            assert ids <= rewarded and len(ids) == min(len(rewarded), gs.max_labels), j
        elif len(ids) < gs.max_labels:
            assert rewarded <= ids, j


def test_learned_rewards_can_end_training_episodes_where_they_judge_success(
    trained, tmp_path, one_thread
):
    from train.training.loop import Trainer

    ends = {}
    for name, threshold, end in (("always", 0.0, "learned"), ("never", 1.01, "learned"),
                                 ("limit", 0.0, "limit")):  # fmt: skip
        cfg = _small_run(
            tmp_path / name, trained, captioner="learned", reward="learned", threshold=threshold,
            end=end,
        )  # fmt: skip
        trainer = Trainer(cfg)
        trainer.run()
        b = trainer.buffer
        n = b.high  # slots written (an episode of T steps takes T + 1)
        ends[name] = (trainer.episodes, int(b.terminated[:n].sum()))
        if name == "always":  # each episode ended at its first step, as a terminal one
            assert trainer.episodes >= cfg.total_steps - 1
            assert ends[name][1] >= trainer.episodes - 1
            # and its last reward is its own goal's, so the terminal step is rewarded
            gs = b.goal_space
            starts = np.flatnonzero(b.terminated[:n])
            assert gs.reward(starts, gs.desired(starts)).min() > 0
    limit = _small_run(tmp_path / "x", trained).env.max_episode_steps
    for name in ("never", "limit"):  # to the time limit, never terminal
        episodes, terminal = ends[name]
        assert episodes <= 300 // limit + 1 and terminal == 0, (name, ends)
    # only push episodes end where the reward model says so: reach ones run to the limit
    cfg = _small_run(
        tmp_path / "push", trained, captioner="learned", reward="learned", threshold=0.0,
        end="learned", end_families=("push",),
    )  # fmt: skip
    trainer = Trainer(cfg)
    trainer.run()
    b = trainer.buffer
    n = b.high
    families = trainer.task.labeller.families
    starts = np.flatnonzero(b.terminated[:n])
    assert len(starts) > 0  # push episodes ended at their first step
    assert all(families[int(g)] == "push" for g in b.goal_space.desired(starts))
    assert ends["never"][0] < trainer.episodes < ends["always"][0]


def test_learned_relabelling_settings_are_checked(trained, tmp_path):
    import dataclasses

    from train.configs.config import RelabelConfig
    from train.configs.presets import PRESETS
    from train.training.loop import Trainer

    with pytest.raises(LcrlError, match=r"relabel\.checkpoint"):
        Trainer(_small_run(tmp_path / "a", "", captioner="learned"))
    with pytest.raises(LcrlError, match=r"end_families needs relabel\.end=learned"):
        Trainer(_small_run(tmp_path / "e", trained, reward="learned", end_families=("push",)))
    with pytest.raises(LcrlError, match=r"end_families must be among"):
        Trainer(
            _small_run(
                tmp_path / "f", trained, reward="learned", end="learned", end_families=("grab",)
            )
        )
    with pytest.raises(LcrlError, match=r"relabel\.reward"):
        Trainer(_small_run(tmp_path / "b", trained, reward="clip"))
    with pytest.raises(LcrlError, match=r"relabel\.agree"):
        Trainer(_small_run(tmp_path / "g", trained, reward="rule", agree=True))
    with pytest.raises(LcrlError, match=r"relabel\.confirm .* needs relabel\.captioner=learned"):
        Trainer(_small_run(tmp_path / "d", trained, reward="learned", confirm=True))
    for labels in ("reward", "both"):
        needs = rf"relabel\.captioner={labels} .* needs relabel\.reward"
        with pytest.raises(LcrlError, match=needs):
            Trainer(_small_run(tmp_path / "r", trained, captioner=labels))
    with pytest.raises(LcrlError, match=r"relabel\.end must be one of"):
        Trainer(_small_run(tmp_path / "e", trained, reward="learned", end="success"))
    with pytest.raises(LcrlError, match=r"relabel\.end=learned .* needs relabel\.reward=learned"):
        Trainer(_small_run(tmp_path / "f", trained, captioner="learned", end="learned"))
    for bad in ("push", "push=2", "shove=0.9", "push=high"):
        with pytest.raises(LcrlError, match=r"relabel\.family_thresholds entry .*FAMILY=P"):
            Trainer(_small_run(tmp_path / "h", trained, family_thresholds=(bad,)))
    state = dataclasses.replace(
        PRESETS["state2d"][1],
        out=str(tmp_path / "c"),
        relabel=RelabelConfig(captioner="learned", checkpoint=str(trained)),
    )
    with pytest.raises(LcrlError, match="language goals"):
        Trainer(state)


def test_random_shift_moves_both_frames_of_a_pair_together():
    from captioner.learned.training import _augment

    gen = torch.Generator().manual_seed(0)
    frames = torch.randint(0, 255, (8, 16, 16, 3), dtype=torch.uint8, generator=gen)
    p = torch.zeros(8, 2)
    same = _augment((frames, frames.clone(), p, p), 3, gen)
    assert same[0].shape == (8, 16, 16, 3)
    torch.testing.assert_close(same[0], same[1])  # one offset per pair
    assert not torch.equal(same[0], frames.float())  # and it did shift
    assert _augment((frames, frames, p, p), 0, gen)[0] is frames
    with pytest.raises(LcrlError, match="augment_pad"):
        train_models(CaptionTrainConfig(augment_pad=-1))


def test_spatial_softmax_finds_a_peak():
    from lcrl.nets import spatial_softmax

    h = torch.full((1, 2, 9, 9), -50.0)
    h[0, 0, 0, 8] = 50.0  # top right: y = -1, x = +1
    h[0, 1, 4, 4] = 50.0  # centre
    kp = spatial_softmax(h, torch.tensor(1.0))
    torch.testing.assert_close(kp, torch.tensor([[-1.0, 0.0, 1.0, 0.0]]), atol=1e-4, rtol=0)


@pytest.mark.parametrize("encoder", ["spatial", "flatten"])
def test_reward_model_scores_agree_between_pairs_and_matrix(encoder, tmp_path, one_thread):
    """score() (one text per frame pair) and score_matrix() (every text against every pair,
    frames encoded once) are the same function; the instruction changes the score."""
    from captioner.learned import Captioner, RewardModel

    strides = (1, 2, 2, 1) if encoder == "spatial" else ()
    cfg = CaptionModelConfig(
        encoder=encoder, channels=(8, 8, 8, 8), strides=strides, features=32, hidden=32
    )
    torch.manual_seed(0)
    vocab = Vocabulary.from_grammar()
    texts = [
        "reach the red cube",
        "push the blue cylinder left",
        "put the red cube behind the green cube",
    ]
    lc = LearnedCaptioner(
        vocab, texts, ["train"] * 3, (24, 24, 3), 4, cfg, np.zeros(4), np.ones(4), "", {}
    )
    lc.captioner = Captioner((24, 24, 3), 4, len(vocab), cfg)
    emb = lc.encode_texts(texts)
    lc.reward = RewardModel((24, 24, 3), 4, emb.shape[1], cfg)
    for prm in lc.reward.film.parameters():  # FiLM starts at the identity: perturb it
        torch.nn.init.normal_(prm, std=0.5)
    rng = np.random.default_rng(0)
    first = rng.integers(0, 255, (5, 24, 24, 3), dtype=np.uint8)
    cur = rng.integers(0, 255, (5, 24, 24, 3), dtype=np.uint8)
    p0 = rng.normal(size=(5, 4)).astype(np.float32)
    p = rng.normal(size=(5, 4)).astype(np.float32)
    mat = lc.score_matrix(texts, first, cur, p0, p)
    assert mat.shape == (5, 3)
    for k, t in enumerate(texts):
        np.testing.assert_allclose(lc.score([t] * 5, first, cur, p0, p), mat[:, k], atol=1e-5)
    assert np.ptp(mat, axis=1).max() > 1e-3  # the instruction matters
    # a saved checkpoint loads with its encoder kind and gives the same scores
    lc.meta["text_dim"] = int(emb.shape[1])
    lc.save(tmp_path / "ck")
    back = LearnedCaptioner.load(tmp_path / "ck")
    assert back.cfg.encoder == encoder
    np.testing.assert_allclose(back.score_matrix(texts, first, cur, p0, p), mat, atol=1e-5)
    back.save(tmp_path / "again")  # a loaded checkpoint saves again
    again = LearnedCaptioner.load(tmp_path / "again")
    np.testing.assert_allclose(again.score_matrix(texts, first, cur, p0, p), mat, atol=1e-5)


def test_bad_model_config_is_refused():
    with pytest.raises(LcrlError, match=r"model\.encoder"):
        train_models(CaptionTrainConfig(model=CaptionModelConfig(encoder="vit")))
    with pytest.raises(LcrlError, match="at least two"):
        train_models(CaptionTrainConfig(model=CaptionModelConfig(channels=(8,))))
    with pytest.raises(LcrlError, match="one stride"):
        train_models(CaptionTrainConfig(model=CaptionModelConfig(strides=(1, 2))))


def _random_episode(trainer, steps=6):
    """A few random steps of the trainer's env, recorded as the loop records them, and the
    episode's stored fields (labels, rewards)."""
    task, env = trainer.task, trainer.env
    obs, _ = env.reset(seed=0)
    goal = task.goal(obs, env)
    records = [task.step_record(obs, env)]
    for _ in range(steps):
        obs, *_ = env.step(env.action_space.sample())
        records.append(task.step_record(obs, env))
    return records, task.episode_fields(records, goal, env)


def _frames(records):
    """The camera frames and proprioception of recorded steps, stacked."""
    return np.stack([r[1] for r in records]), np.stack([r[2] for r in records])


def test_captioner_rewards_store_the_captions_as_rewards(trained, tmp_path, one_thread):
    """reward=captioner: the learned captions are both the relabelling candidates and the
    rewards (no reward model, no rule rewards)."""
    from train.training.loop import Trainer

    with pytest.raises(LcrlError, match="captioner=learned"):
        Trainer(_small_run(tmp_path / "bad", trained, reward="captioner"))
    cfg = _small_run(
        tmp_path / "run", trained, captioner="learned", reward="captioner", min_logprob=-1e9
    )
    cfg = dataclasses.replace(cfg, total_steps=120, learning_starts=100)
    trainer = Trainer(cfg)
    task = trainer.task
    assert task.labeller.captioner_rewards and not task.labeller.use_reward
    records, fields = _random_episode(trainer)
    assert "achieved" not in fields  # the buffer rewards the labels themselves
    assert fields["labels"] == task.labeller.labels(*_frames(records))
    trainer.run()
    assert trainer.buffer.size >= 120


def test_learned_candidates_with_rule_rewards(trained, tmp_path, one_thread):
    """captioner=learned, reward=rule: the learned captions are the relabelling candidates
    and the rule captioner's labels are the rewards."""
    from train.training.loop import Trainer

    cfg = _small_run(
        tmp_path / "run", trained, captioner="learned", reward="rule", min_logprob=-1e9
    )
    trainer = Trainer(cfg)
    task = trainer.task
    assert task.labeller.use_captioner and not task.labeller.use_reward
    records, fields = _random_episode(trainer)
    assert fields["labels"] == task.labeller.labels(*_frames(records))
    s0 = records[0][0]
    rule = [[]] + [
        [
            task.label_ids[c.text]
            for c in task.captioner.caption(s0, r[0])
            if c.text in task.label_ids
        ]
        for r in records[1:]
    ]
    assert fields["achieved"] == rule  # rewarded by the rule captioner, not the captions


# --- the models over perception -----------------------------------------------------------
@pytest.fixture(scope="module")
def slots_dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("lc") / "slots.h5"
    collect(
        CollectConfig(
            out=str(path), episodes=400, image_size=32, families=("reach", "push"), progress=False
        )
    )
    return path


def test_models_over_perception_learn_from_the_slots(slots_dataset, tmp_path, monkeypatch, capsys):
    """``--model.encoder perception``: the models read perception's estimates of the first
    and current frame; given exact estimates (the simulator's state) they caption held-out
    episodes and rank their rewards far above chance."""
    from captioner.learned import saved, training
    from train.environments.perception import PerceptionTrainConfig, save_model

    oracle = oracle_perception(slots_dataset)
    save_model(tmp_path / "oracle", oracle, PerceptionTrainConfig(), {}, 0, [], np.zeros(0, int))
    for module in (training, saved):  # where the models are trained, and loaded again
        monkeypatch.setattr(module, "load_model", lambda path, device="cpu": (oracle, {}))
    model = dataclasses.replace(TINY, encoder="perception")
    cfg = CaptionTrainConfig(
        data=str(slots_dataset), out=str(tmp_path / "ckpt"), steps=800, model=model,
        perception=str(tmp_path / "oracle"), progress=False,
    )  # fmt: skip
    path = train_models(cfg)
    lc = LearnedCaptioner.load(path)
    saved = json.loads((path / "meta.json").read_text())["perception"]
    assert lc.perception is oracle and saved["format"] == "lcrl-perception"
    with CaptionDataset(slots_dataset) as data:  # read from the file a batch at a time
        capsys.readouterr()
        est = lc.perceive(data.frames, data.proprio[:], batch=64, progress=True)
        assert "perception" in capsys.readouterr().err  # a progress bar on long work
        np.testing.assert_allclose(est, lc.perceive(data.frames[:], data.proprio[:]), atol=1e-6)
    with CaptionDataset(slots_dataset) as data:
        seen = evaluate_models(lc, data)["seen"]
    # chance is about 1 in 30 instructions for the captioner, 0.5 for the reward AUC
    assert seen["exact_match"] >= 0.5 and seen["auc"] >= 0.85, seen
    # the reward model's instruction picks the slot of the object it names (0.85 here)
    assert lc.reward.slot_query
    from envs.scene import OBJECT_KINDS

    with CaptionDataset(slots_dataset) as data:
        j = np.arange(1, data.num_observations, 7)
        first, current = data.read_frames(data.first_of(j)), data.read_frames(j)
        p0, p = data.proprio[data.first_of(j)], data.proprio[j]
        state = data.state[j]
    present = state[:, 2:].reshape(len(j), 8, 3)[..., 2] > 0.5
    hits = total = 0
    with torch.no_grad():
        ctx = lc._context("reward model", first, current, p0, p)
        for slot, (colour, shape) in enumerate(OBJECT_KINDS):
            rows = present[:, slot]
            if not rows.any():
                continue
            t = lc.reward.text_features(lc.encode_texts([f"reach the {colour} {shape}"]))
            attn = lc.reward.pick(ctx[rows], t.expand(int(rows.sum()), -1))[0]
            hits += int((attn.argmax(1) == slot).sum())
            total += int(rows.sum())
    assert hits >= 0.75 * total, (hits, total)  # chance: 1 in 2 or 3 objects on the table


def test_first_presence_keeps_the_objects_the_arm_hides(slots_dataset):
    """With ``first_presence`` (the default) the models read every frame with the presence
    flags of its episode's first frame: an object perception loses under the arm keeps
    its place instead of reading as gone (position 0), in training data and when
    scoring alike."""
    from captioner.learned import Vocabulary
    from captioner.learned.training import _perceive_dataset

    oracle = oracle_perception(slots_dataset)
    read = oracle.observation
    with CaptionDataset(slots_dataset) as data:
        firsts = {data.frames[int(a)].tobytes() for a in data.episode_start[:-1]}
        lay = oracle.layout

        def hiding(frames, proprio, present=None):
            """Loses every object in frames after an episode's first, unless told."""
            out = read(frames, proprio, present).copy()
            if present is None:
                later = [f.tobytes() not in firsts for f in np.asarray(frames, np.uint8)]
                out[np.asarray(later), lay.start :] = 0.0
            return out

        oracle.observation = hiding
        dim = data.proprio.shape[1]
        results = {}
        for pin in (True, False):
            lc = LearnedCaptioner(
                Vocabulary.from_grammar(), data.instructions, data.instruction_set,
                data.frame_shape, dim, dataclasses.replace(TINY, encoder="perception",
                first_presence=pin), np.zeros(dim, np.float32), np.ones(dim, np.float32), "", {},
            )  # fmt: skip
            lc.perception = oracle
            j = np.flatnonzero(np.diff(data.label_start) > 0)[:40]  # later frames
            first, current = data.read_frames(data.first_of(j)), data.read_frames(j)
            p0, p = data.proprio[data.first_of(j)], data.proprio[j]
            est = lc._inputs(first, current, p0, p)[1].numpy()
            every = _perceive_dataset(lc, data, data.frames, data.proprio[:], progress=False)
            results[pin] = (est, every)
        truth = read(data.frames[:], data.proprio[:])  # what perception reads unhidden
        np.testing.assert_allclose(results[True][0], truth[j], atol=1e-6)
        np.testing.assert_allclose(results[True][1], truth, atol=1e-6)
        assert not results[False][0][:, lay.start :].any()  # every object read as gone
        assert not results[False][1][j, lay.start :].any()


def test_checkpoints_saved_before_slot_query_read_without_it(trained, tmp_path):
    import shutil

    assert LearnedCaptioner.load(trained).cfg.slot_query  # saved with the option: on
    old = tmp_path / "old"
    shutil.copytree(trained, old)
    meta = json.loads((old / "meta.json").read_text())
    del meta["model"]["slot_query"]
    (old / "meta.json").write_text(json.dumps(meta))
    seal_checkpoint(old)  # as such a checkpoint was saved: its own sums
    assert LearnedCaptioner.load(old).cfg.slot_query is False


def test_models_over_perception_refuse_another_camera(dataset, tmp_path):
    from lcrl.perception import Perception, SlotLayout
    from train.environments.perception import PerceptionTrainConfig, save_model

    other = Perception((48, 48, 3), SlotLayout(2, 8, 3, 2))
    save_model(tmp_path / "p", other, PerceptionTrainConfig(), {}, 0, [], np.zeros(0, int))
    model = dataclasses.replace(TINY, encoder="perception")
    cfg = CaptionTrainConfig(
        data=str(dataset), out=str(tmp_path / "c"), steps=2, model=model,
        perception=str(tmp_path / "p"), progress=False,
    )  # fmt: skip
    with pytest.raises(LcrlError, match=r"reads \(48, 48, 3\) frames; .* has \(32, 32, 3\)"):
        train_models(cfg)
    with pytest.raises(LcrlError, match="--perception MODEL"):
        train_models(dataclasses.replace(cfg, perception=""))


def test_relabel_agreement_counts_pairs_as_the_training_loop_does(trained, dataset, capsys):
    from captioner.learned import LearnedLabeller, relabel_agreement
    from train.commands.cli import main

    lc = LearnedCaptioner.load(trained)
    with CaptionDataset(dataset) as data:
        result = relabel_agreement(lc, data, [0.9, 0.5, 0.2], families=("reach",))
        rows = result["rewards"]
        assert [r["threshold"] for r in rows] == [0.2, 0.5, 0.9]
        recalls = [r["recall"] for r in rows]
        assert all(np.isfinite(recalls)) and recalls[0] > 0  # there were pairs to find
        assert recalls == sorted(recalls, reverse=True)  # a higher bar accepts fewer pairs
        assert result["best_threshold"] in (0.2, 0.5, 0.9) and result["episodes"] > 0
        # the same counts by hand, through the labeller the loop uses, at threshold 0.5
        texts = data.instructions
        train = [
            t
            for t, k in zip(texts, data.instruction_set, strict=True)
            if k == "train" and t.startswith("reach")
        ]
        table = train + [t for t in texts if t not in train]
        lab = LearnedLabeller(lc, table, len(train), beam=3)
        for e in np.asarray(lc.meta["val_episodes"]):
            ep = data.episode(int(e))
            labels = lab.labels(ep["frames"], ep["proprio"])
            rule = [[table.index(texts[i]) for i in ids] for ids in ep["labels"]]
            rule = [[i for i in ids if i < len(train)] for ids in rule]
            own = table.index(texts[ep["instruction"]]) if ep["instruction"] >= 0 else -1
            cands = sorted(
                {i for ids in labels for i in ids} | ({own} if 0 <= own < len(train) else set())
            )
            if cands:
                got = lab.achieved(ep["frames"], ep["proprio"], cands)
                lab.compare("rewards", got, rule, among=cands)
        by_hand = lab.agreement()
        assert rows[1]["precision"] == pytest.approx(by_hand["rewards_precision"], nan_ok=True)
        assert rows[1]["recall"] == pytest.approx(by_hand["rewards_recall"], nan_ok=True)
        with pytest.raises(LcrlError, match="no instruction of family 'stack'"):
            relabel_agreement(lc, data, [0.5], families=("stack",))
    main(["caption", "eval", str(trained), "--thresholds", "0.5", "0.9", "--families", "reach"])
    out = capsys.readouterr().out
    assert "threshold 0.90: precision" in out and "best F1 at --relabel.threshold" in out
    with pytest.raises(SystemExit):
        main(["caption", "eval", str(trained), "--thresholds", "1.5"])
    assert "--thresholds are probabilities in (0, 1), got 1.5" in capsys.readouterr().err


class _Labels:
    """A caption dataset's labels alone: two episodes, observations 0-4 and 5-8."""

    def __init__(self, labels):
        self._labels = [np.asarray(x, np.int64) for x in labels]

    def labels(self, j):
        return self._labels[j]

    def first_of(self, j):
        return 0 if j < 5 else 5


def test_onset_delay_moves_an_achievements_first_steps_to_the_negatives():
    from captioner.learned import delayed_labels, onset_delays

    # instruction 0 is a push, 1 a reach; push accepted from step 2 of episode one and
    # from the first step of episode two (never at two steps in a row before step 7)
    data = _Labels([[], [1], [0, 1], [0], [0], [], [0], [0], [0]])
    families = ["push", "reach"]
    got = delayed_labels(data, np.arange(9), {"push": 1}, families)
    assert [got[j].tolist() for j in range(9)] == [[], [1], [1], [0], [0], [], [], [0], [0]]
    got = delayed_labels(data, np.arange(9), {"push": 2}, families)
    assert [got[j].tolist() for j in range(9)] == [[], [1], [1], [], [0], [], [], [], [0]]
    same = delayed_labels(data, np.arange(9), {}, families)
    assert all(same[j].tolist() == data.labels(j).tolist() for j in range(9))
    assert onset_delays(["push=1", "reach=0"]) == {"push": 1, "reach": 0}
    for bad in ("push", "push=-1", "push=0.5", "grab=1"):
        with pytest.raises(LcrlError, match="FAMILY=STEPS"):
            onset_delays([bad])


def test_reward_positives_follow_the_onset_delay(dataset):
    from captioner.learned.data import _Pairs, _Sampler
    from captioner.learned.training import _parse

    with CaptionDataset(dataset) as data:
        pairs = _Pairs(data, 0.2, 0)
        table = [_parse(t) for t in data.instructions]
        push = [i for i, ins in enumerate(table) if ins.family == "push"]
        sampler = _Sampler(pairs, table, np.random.default_rng(0), 10, {"push": 1})
        plain = _Sampler(pairs, table, np.random.default_rng(0), 10)
        obs = pairs.observations(pairs.train_episodes)
        dropped = 0
        for j in obs:
            full, kept = set(plain.labels(j).tolist()), set(sampler.labels(j).tolist())
            assert kept <= full and {i for i in full - kept} <= set(push)
            for i in kept & set(push):  # a kept push was accepted a step before too
                assert j - 1 > data.first_of(j) and i in data.labels(j - 1)
            dropped += len(full - kept)
        assert dropped > 0  # the first accepted step of every push
        idx, ids, y = sampler.reward_batch(512, 0.5, 0.5)
        for j, i, t in zip(idx, ids, y, strict=True):
            assert (int(i) in sampler.labels(int(j))) == bool(t)


def test_demonstrations_are_relabelled_by_the_learned_models_from_their_frames(
    trained, tmp_path, capsys, one_thread
):
    """``--finetune.demos`` beside learned relabelling: the demonstrations' stored camera
    frames are read by the learned captioner and reward model like the run's own episodes
    (never the rule captioner's labels); a file without frames is refused in one line."""
    from helpers import cli, error_line

    from train.training.loop import Trainer

    demos, plain = tmp_path / "demos.h5", tmp_path / "plain.h5"
    args = ["demos", "record", "--preset", "lang2d", "--families", "reach", "push"]
    args += ["--episodes", "4", "--no-progress"]
    assert cli(*args, "--images", "--image-size", "32", "--out", str(demos)) == 0
    assert cli(*args, "--out", str(plain)) == 0
    cfg = _small_run(
        tmp_path / "run", trained, captioner="learned", reward="learned", min_logprob=-1e9
    )
    cfg = dataclasses.replace(cfg, total_steps=120, learning_starts=100)
    cfg.finetune.demos, cfg.finetune.pretrain_updates = str(demos), 4
    trainer = Trainer(cfg)
    trainer.run()
    lab = trainer.task.labeller
    assert lab.kept + lab.skipped >= 4  # the four demonstrations were read from their frames
    assert trainer.buffer.demo[: trainer.buffer.size].any()

    args = ["train", "lang2d", "--relabel.captioner", "learned", "--relabel.reward", "learned"]
    args += ["--relabel.checkpoint", str(trained), "--finetune.demos", str(plain)]
    assert cli(*args, "--out", str(tmp_path / "p"), "--total-steps", "50") == 2
    line = error_line(capsys.readouterr().err)
    assert "stores no camera frames" in line and "--images" in line


def test_an_episode_is_perceived_once_for_its_captions_and_rewards():
    """The labeller reads an episode's captions and rewards from the same frames against
    its first: perception sees each frame once (N + 1 frames, not 4N), and the scores are
    those of perceiving every pair on its own."""
    from pathlib import Path

    from captioner.learned import LearnedLabeller

    model = Path(__file__).parents[1] / "benchmarks/models/captioner-factored-robosuite-policy"
    lc = LearnedCaptioner.load(model / "seed0" / "model")
    assert lc.perception is not None
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (5, *lc.frame_shape), dtype=np.uint8)
    proprio = rng.normal(size=(5, lc.proprio_dim)).astype(np.float32)
    seen = []
    observe = lc.perception.observation
    lc.perception.observation = lambda x, *a, **k: seen.append(len(x)) or observe(x, *a, **k)
    table = ["reach the red cube", "push the red cube left", "lift the red cube"]
    lab = LearnedLabeller(lc, table, 3, min_logprob=-1e9, threshold=0.0)
    lab.labels(frames, proprio)
    lab.achieved(frames, proprio, [0, 1, 2])
    assert sum(seen) == len(frames) + 1
    first, p0 = np.repeat(frames[:1], 5, 0), np.repeat(proprio[:1], 5, 0)
    together = lc.score_matrix(table, first, frames, p0, proprio)
    alone = [lc.score_matrix(table, frames[:1], frames[i : i + 1], proprio[:1], proprio[i : i + 1])
             for i in range(5)]  # fmt: skip
    np.testing.assert_allclose(together, np.concatenate(alone), rtol=1e-4, atol=1e-5)
