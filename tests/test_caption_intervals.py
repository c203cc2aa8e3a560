"""Intervals of ``lcrl caption eval``: an episode's frames are not independent draws, so
its rates and reward AUCs are resampled (or counted) by episode."""

from __future__ import annotations

import numpy as np
import pytest

from captioner.learned.metrics import auc_interval, rate_interval
from lcrl.statistics import wilson_interval


def test_independent_observations_keep_wilsons_interval():
    hits = [True] * 30 + [False] * 10
    plain = rate_interval(hits)
    alone = rate_interval(hits, clusters=list(range(40)))  # each its own episode
    assert plain["ci"] == list(wilson_interval(30, 40))
    assert alone["ci"] == pytest.approx(plain["ci"], abs=0.02)
    assert alone["clusters"] == 40


def test_frames_that_agree_within_episodes_count_as_their_episodes():
    # 10 episodes of 50 frames, every frame of an episode alike: 7 read, 3 not
    hits = [e < 7 for e in range(10) for _ in range(50)]
    episode = [e for e in range(10) for _ in range(50)]
    naive = rate_interval(hits)["ci"]
    out = rate_interval(hits, clusters=episode)
    assert out["rate"] == pytest.approx(0.7) and out["n"] == 500
    assert out["effective_n"] == pytest.approx(10, abs=0.5)
    lo, hi = out["ci"]
    assert (lo, hi) == pytest.approx(wilson_interval(7, 10), abs=0.01)
    assert hi - lo > 3 * (naive[1] - naive[0])
    # where every frame is read, the interval is that of the episodes, not of the frames
    every = rate_interval([True] * 500, clusters=episode)
    assert every["ci"][0] == pytest.approx(wilson_interval(10, 10)[0])
    assert every["ci"][0] < rate_interval([True] * 500)["ci"][0] - 0.1


def test_auc_intervals_resample_whole_episodes():
    rng = np.random.default_rng(0)
    # 20 episodes, each 30 copies of one positive and one negative pair
    pos, neg = rng.normal(1.0, 1.0, 20), rng.normal(0.0, 1.0, 20)
    scores = np.concatenate([np.repeat(pos, 30), np.repeat(neg, 30)])
    labels = np.concatenate([np.ones(600, bool), np.zeros(600, bool)])
    episode = np.concatenate([np.repeat(np.arange(20), 30)] * 2)
    lo, hi = auc_interval(scores, labels, seed=1)
    clo, chi = auc_interval(scores, labels, seed=1, clusters=episode)
    assert clo <= chi and chi - clo > 2 * (hi - lo)


def test_a_long_episode_weighs_as_its_length_says():
    # one episode of 100 frames, every one read; 100 episodes of one frame, none read
    hits = [True] * 100 + [False] * 100
    episode = [0] * 100 + list(range(1, 101))
    out = rate_interval(hits, clusters=episode)
    # about four independent draws' worth, not the 101 episodes
    assert out["effective_n"] < 10
    lo, hi = out["ci"]
    assert hi - lo > 0.4
