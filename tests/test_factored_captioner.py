"""The captioner and reward model factored by the grammar's slots (``--model.head
factored``): the output table, training on exact slots, held-out word combinations read as
seen ones, saving and loading, errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import oracle_perception

from captioner.dataset import CaptionDataset, CollectConfig
from captioner.grammar import DIRECTIONS, FAMILIES, RELATIONS, Instruction, parse
from captioner.learned import (
    CaptionModelConfig,
    CaptionTrainConfig,
    LearnedCaptioner,
    evaluate_models,
    format_results,
    train_models,
)
from captioner.learned.factored import (
    PAIR,
    UNARY,
    instruction_index,
    output_index,
    output_objects,
)
from envs.scene import OBJECT_KINDS
from lcrl.errors import LcrlError
from train.commands.captions import collect

TINY = CaptionModelConfig(
    channels=(16, 16, 16, 16), features=64, hidden=64, embed=32, encoder="perception"
)


def _every_instruction() -> list[Instruction]:
    out = []
    for family in FAMILIES:
        for colour, shape in OBJECT_KINDS:
            directions = DIRECTIONS if family == "push" else (None,)
            for direction in directions:
                if family in ("put", "stack"):
                    for tc, ts in OBJECT_KINDS:
                        if (tc, ts) == (colour, shape):
                            continue
                        rels = RELATIONS if family == "put" else (None,)
                        for rel in rels:
                            out.append(Instruction(family, colour, shape, None, rel, tc, ts))
                else:
                    out.append(Instruction(family, colour, shape, direction))
    return out


def test_every_instruction_has_its_own_output_about_its_objects():
    count = len(OBJECT_KINDS)
    table = _every_instruction()
    idx = [output_index(ins, count) for ins in table]
    assert sorted(idx) == list(range(count * len(UNARY) + count * (count - 1) * len(PAIR)))
    for ins, i in zip(table, idx, strict=True):
        slots = tuple(OBJECT_KINDS.index(o) for o in ins.objects)
        assert output_objects(i, count) == slots
    # any phrasing reads as its canonical instruction's output
    ins = parse("place the red cube to the left of the blue cylinder")
    assert instruction_index("put the red cube left of the blue cylinder", count) == output_index(
        ins, count
    )
    with pytest.raises(LcrlError, match="does not parse"):
        instruction_index("dance with the red cube", count)
    # a scene with fewer slots has no output for an object beyond them
    assert output_index(Instruction("reach", "yellow", "cylinder"), 4) is None


def test_the_factored_head_needs_perception():
    with pytest.raises(LcrlError, match=r"--model\.encoder perception"):
        dataclasses.replace(TINY, encoder="spatial", head="factored").validate()
    with pytest.raises(LcrlError, match=r"model\.head"):
        dataclasses.replace(TINY, head="tree").validate()


@pytest.fixture(scope="module")
def slots_dataset(tmp_path_factory):
    path = tmp_path_factory.mktemp("fc") / "slots.h5"
    collect(
        CollectConfig(
            out=str(path),
            episodes=400,
            image_size=32,
            families=("reach", "push", "put"),
            after_success=5,
            progress=False,
        )
    )
    return path


@pytest.fixture(scope="module")
def heads(slots_dataset, tmp_path_factory, one_thread):
    """Both heads trained on the oracle's slots with the same steps and seed."""
    from captioner.learned import saved, training
    from train.environments.perception import PerceptionTrainConfig, save_model

    tmp = tmp_path_factory.mktemp("fc")
    oracle = oracle_perception(slots_dataset)
    save_model(tmp / "oracle", oracle, PerceptionTrainConfig(), {}, 0, [], np.zeros(0, int))
    mp = pytest.MonkeyPatch()
    for module in (training, saved):
        mp.setattr(module, "load_model", lambda path, device="cpu": (oracle, {}))
    out = {}
    for head in ("factored", "sequence"):
        cfg = CaptionTrainConfig(
            data=str(slots_dataset),
            out=str(tmp / head),
            steps=1200,
            model=dataclasses.replace(TINY, head=head),
            perception=str(tmp / "oracle"),
            progress=False,
        )
        out[head] = train_models(cfg)
    yield out
    mp.undo()


def test_held_out_combinations_are_read_as_seen_ones(heads, slots_dataset):
    """On exact slots the factored head captions held-out word combinations nearly as well
    as seen ones, far better than the word-by-word captioner trained the same way, and
    ranks their rewards nearly perfectly."""
    results = {}
    for head, path in heads.items():
        lc = LearnedCaptioner.load(path)
        with CaptionDataset(slots_dataset) as data:
            results[head] = evaluate_models(lc, data)
    f, s = results["factored"], results["sequence"]
    held, seen = f["heldout_combinations"], f["seen"]
    assert held["observations"] >= 50
    assert held["exact_match"] >= 0.8, format_results(f)
    assert held["exact_match"] >= s["heldout_combinations"]["exact_match"] + 0.2, (
        format_results(f),
        format_results(s),
    )
    assert seen["exact_match"] >= 0.8 and held["auc"] >= 0.95 and seen["auc"] >= 0.95
    assert f["none_accuracy"] >= 0.8
    # intervals and the per-family breakdown
    lo, hi = held["exact_match_ci"]
    assert lo <= held["exact_match"] <= hi and 0 < hi - lo < 0.3
    assert set(held["exact_match_by_family"]) <= {"reach", "push", "put"}
    assert sum(v["n"] for v in held["exact_match_by_family"].values()) == held["observations"]
    lo, hi = held["auc_ci"]
    assert lo <= held["auc"] <= hi
    assert "exact match 95% interval" in format_results(f)


def test_saved_factored_models_score_as_they_were_trained(heads, slots_dataset):
    lc = LearnedCaptioner.load(heads["factored"])
    assert lc.factored is not None and lc.captioner is None and lc.reward is None
    assert lc.has("captioner") and lc.has("reward")
    with CaptionDataset(slots_dataset) as data:
        j = np.arange(3, data.num_observations, 97)[:16]
        first, current = data.read_frames(data.first_of(j)), data.read_frames(j)
        p0, p = data.proprio[data.first_of(j)], data.proprio[j]
    texts = ["reach the red cube", "push the blue cylinder left", "touch the red block"]
    matrix = lc.score_matrix(texts, first, current, p0, p)
    assert matrix.shape == (len(j), 3) and ((matrix >= 0) & (matrix <= 1)).all()
    np.testing.assert_allclose(matrix[:, 0], matrix[:, 2], atol=1e-6)  # a paraphrase
    pairs = lc.score([texts[1]] * len(j), first, current, p0, p)
    np.testing.assert_allclose(pairs, matrix[:, 1], atol=1e-5)
    captions = lc.captions(first, current, p0, p, beam=3)
    assert all(len(c) == 3 for c in captions)
    for row in captions:
        assert [lp for _, lp in row] == sorted((lp for _, lp in row), reverse=True)
        assert all(t in lc.instructions or t == "<none>" for t, _ in row)
    with pytest.raises(LcrlError, match="does not parse"):
        lc.score(["dance"] * len(j), first, current, p0, p)
