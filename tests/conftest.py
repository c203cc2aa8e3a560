"""Fixtures shared by the test modules."""

from __future__ import annotations

import os

import pytest
import torch

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Two test workers share two cores: each (and what it starts) takes one thread, as two
    # training runs side by side do; two threads each would fight for the cores.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")
    torch.set_num_threads(1)

#: The test files that take longest (2-7 minutes each on a 2-core machine), longest first.
#: They are collected first, so that ``make test``'s two workers (``--dist loadfile``:
#: whole files, handed out in collection order) start them early instead of ending the
#: run with one worker busy on a long file while the other waits.
LONG_FILES = (
    "test_text_reader.py",
    "test_pipeline.py",
    "test_learning.py",
    "test_perception.py",
    "test_learned_captioner.py",
    "test_docs.py",
    "test_bench_models.py",
    "test_factored_captioner.py",
)


def pytest_collection_modifyitems(config, items):
    """Long files first (:data:`LONG_FILES`); every other file, and the tests within a
    file, keep their order."""
    rank = {name: i for i, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for the module: tiny updates are many times slower when two
    threads fight other processes for two cores."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def tiny_canonical_reader(monkeypatch):
    """Canonical readers fitted in the test at tiny size (2 members of 40 steps) where what
    is checked is that one is fitted, saved and loaded; how well a full one reads is
    tests/test_text_reader.py's own test."""
    monkeypatch.setattr("train.environments.text_reading.CANONICAL_MEMBERS", 2)
    monkeypatch.setattr("train.environments.text_reading.READER_STEPS", 40)
