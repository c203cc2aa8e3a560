"""benchmarks.distill_data: how a DAgger dataset is split into instruction segments."""

from __future__ import annotations

import numpy as np

from benchmarks import distill_data as dd


def test_a_segment_starts_where_the_instruction_or_its_first_observation_changes():
    initial = np.array([[0, 0], [0, 0], [1, 0], [1, 0], [1, 0], [1, 0]], np.float32)
    goal = np.array([3, 3, 3, 3, 5, 5])
    # a new first observation at row 2 (a new scene or the next link of a chain), a new
    # instruction at row 4 with the same first observation
    assert dd.segments(initial, goal).tolist() == [0, 0, 1, 1, 2, 2]


def test_held_out_segments_are_whole_the_same_for_every_fraction_and_nested():
    seg = np.repeat(np.arange(400), 5)
    held_rows = None
    kept = []
    for fraction in (0.25, 0.5, 1.0):
        train, held = dd.split_rows(seg, 0.1, fraction, seed=3)
        assert not set(seg[train]) & set(seg[held])  # no segment on both sides
        for s in set(seg[held]):  # a held-out segment is held out whole
            assert (seg[held] == s).sum() == 5
        if held_rows is None:
            held_rows = held
        assert np.array_equal(held, held_rows)
        kept.append(set(seg[train]))
    assert kept[0] <= kept[1] <= kept[2]
    assert 0.15 < len(kept[0]) / len(kept[2]) < 0.35
    assert len(kept[2]) + len(set(seg[held_rows])) == 400


def test_the_action_error_sums_over_dimensions():
    pred = np.zeros((2, 4), np.float32)
    target = np.array([[1, 0, 0, -1], [0.5, 0.5, 0, 0]], np.float32)
    assert dd.action_error(pred, target).tolist() == [2.0, 0.5]
