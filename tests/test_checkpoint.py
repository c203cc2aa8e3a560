"""Tests for lcrl.checkpoint: pickle-free, atomic checkpoints."""

import errno
import json
import os
import pickle
import random
import shutil
from collections import OrderedDict
from pathlib import Path

import numpy as np
import pytest
import safetensors
import safetensors.torch
import torch
from torch import nn

from lcrl.checkpoint import (
    FORMAT_VERSION,
    CheckpointError,
    CheckpointWriteError,
    find_latest,
    flatten_state,
    load_checkpoint,
    save_checkpoint,
    unflatten_state,
    write_latest,
    write_problem,
)
from lcrl.errors import LcrlError


@pytest.fixture(scope="module", autouse=True)
def _import_torch_optim() -> None:
    """Pay torch's one-off lazy imports on first optimiser construction (~1.5 s) outside tests."""
    torch.optim.Adam([nn.Parameter(torch.zeros(1))])


def _model(in_dim: int = 6) -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(in_dim, 16), nn.LayerNorm(16), nn.ReLU(), nn.Linear(16, 3))


def _train(model: nn.Module, opt: torch.optim.Optimizer, steps: int, seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        x = torch.randn(8, 6, generator=gen)
        loss = model(x).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()


def _json_round_trip(skeleton):
    return json.loads(json.dumps(skeleton))


def _assert_same(a, b) -> None:
    """Deep equality, with exact types (tuple vs list, int vs str keys, numpy dtypes)."""
    assert type(a) is type(b), (type(a), type(b))
    if isinstance(a, dict):
        assert list(a.keys()) == list(b.keys())
        for key in a:
            _assert_same(a[key], b[key])
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _assert_same(x, y)
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert torch.equal(a, b)
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, float) and a != a:
        assert b != b
    else:
        assert a == b


def _save_basic(directory: Path, **overrides) -> Path:
    model = _model()
    kwargs = {
        "modules": {"actor": model},
        "states": {"counters": {"step": 7}},
        "meta": {"config": {"lr": 1e-3}},
        "json_files": {"instructions": ["push the red cube left"]},
    }
    kwargs.update(overrides)
    return save_checkpoint(directory, **kwargs)


# ---------------------------------------------------------------------------------------------
# flatten_state / unflatten_state
# ---------------------------------------------------------------------------------------------


def test_flatten_round_trip_preserves_types_and_int_keys():
    state = {
        0: {"t": torch.arange(3), "n": None, "b": True, "f": 0.1, "s": "x"},
        "nested": [1, (2.5, float("inf"), float("-inf"), float("nan")), {"k": [torch.ones(2)]}],
        7: (torch.zeros(2, 2, dtype=torch.float64),),
        "big": 2**200 + 1,
        "neg_zero": -0.0,
        "np_scalar": np.float32(1.5),
        "np_int": np.int64(-3),
        "empty": {},
        "a.b": torch.ones(1),
        "a": {"b": torch.zeros(1)},  # same dotted path as "a.b": gets a distinct tensor name
    }
    tensors, skeleton = flatten_state(state, prefix="s")
    assert all(name.startswith("s.") for name in tensors)
    restored = unflatten_state(tensors, _json_round_trip(skeleton))
    _assert_same(state, restored)
    assert 0 in restored and 7 in restored and "0" not in restored
    assert isinstance(restored["np_scalar"], np.float32)
    assert str(restored["neg_zero"]) == "-0.0"


@pytest.mark.parametrize(
    "dtype", [np.uint8, np.int16, np.float32, np.bool_, np.uint32, np.complex64, ">f8", "<U5"]
)
def test_flatten_numpy_dtypes_round_trip(dtype):
    rng = np.random.default_rng(1)
    array = (rng.random((3, 4)) * 100).astype(dtype)
    for value in (array, array[:, ::2], np.asarray(array[0, 0]), array[:0]):
        tensors, skeleton = flatten_state({"a": value})
        restored = unflatten_state(tensors, _json_round_trip(skeleton))["a"]
        assert isinstance(restored, np.ndarray)
        assert restored.dtype == value.dtype and restored.shape == value.shape
        np.testing.assert_array_equal(restored, value)


def test_flatten_rejects_unsupported_values():
    with pytest.raises(CheckpointError, match=r"'a\.1'.*set"):
        flatten_state({"a": [1, {2}]})
    with pytest.raises(CheckpointError, match="object dtype"):
        flatten_state({"a": np.array([1, "x"], dtype=object)})
    with pytest.raises(CheckpointError, match="dict keys"):
        flatten_state({(1, 2): 3})


def test_flatten_shared_tensor_stored_once():
    t = torch.ones(3)
    tensors, skeleton = flatten_state({"a": t, "b": [t]})
    assert len(tensors) == 1
    restored = unflatten_state(tensors, skeleton)
    assert restored["a"] is restored["b"][0]


def test_unflatten_missing_tensor_raises():
    _, skeleton = flatten_state({"a": torch.ones(1)})
    with pytest.raises(CheckpointError, match="expected tensor 'a'"):
        unflatten_state({}, skeleton)


# ---------------------------------------------------------------------------------------------
# Modules, optimisers, RNG
# ---------------------------------------------------------------------------------------------


def test_module_and_adam_round_trip_continue_bit_identical(tmp_path):
    model = _model()
    opt = torch.optim.Adam(model.parameters(), lr=1e-2, betas=(0.8, 0.99))
    _train(model, opt, steps=3, seed=1)

    save_checkpoint(
        tmp_path / "ckpt",
        modules={"actor": model},
        states={"actor_opt": opt.state_dict()},
        meta={"step": 3},
    )
    ckpt = load_checkpoint(tmp_path / "ckpt")
    assert ckpt.meta == {"format_version": FORMAT_VERSION, "step": 3}

    model2 = _model()
    with torch.no_grad():
        for p in model2.parameters():
            p.add_(1.0)
    ckpt.load_module("actor", model2)
    opt2 = torch.optim.Adam(model2.parameters(), lr=0.5)
    restored_state = ckpt.state("actor_opt")
    _assert_same(opt.state_dict(), restored_state)
    opt2.load_state_dict(restored_state)

    _train(model, opt, steps=4, seed=2)
    _train(model2, opt2, steps=4, seed=2)
    for (name, a), b in zip(model.state_dict().items(), model2.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
    _assert_same(opt.state_dict(), opt2.state_dict())


def test_weights_accessor_and_tensor_mapping_modules(tmp_path):
    model = _model()
    critic = {"w": torch.arange(6.0).reshape(2, 3)[:, 1:], "b": torch.zeros(2)}  # non-contiguous
    save_checkpoint(tmp_path / "c", modules={"actor": model, "critic": critic})
    ckpt = load_checkpoint(tmp_path / "c")
    weights = ckpt.weights("actor")
    assert list(weights) == list(model.state_dict())
    assert torch.equal(ckpt.weights("critic")["w"], critic["w"])
    with pytest.raises(CheckpointError, match=r"expected module 'nope'.*actor, critic"):
        ckpt.weights("nope")


def test_tied_and_view_tensors_are_cloned(tmp_path):
    base = torch.arange(10.0)
    shared = nn.Linear(4, 4)
    tied = {"a": shared.weight, "b": shared.weight, "slice": base[2:5], "rest": base}
    save_checkpoint(tmp_path / "c", modules={"m": tied}, states={"s": {"x": base[1:3]}})
    ckpt = load_checkpoint(tmp_path / "c")
    weights = ckpt.weights("m")
    assert torch.equal(weights["a"], shared.weight.detach())
    assert torch.equal(weights["b"], shared.weight.detach())
    assert torch.equal(weights["slice"], base[2:5])
    assert torch.equal(ckpt.state("s")["x"], base[1:3])


def test_rng_states_round_trip(tmp_path):
    torch.manual_seed(123)
    np_rng = np.random.default_rng(0)
    np_rng.random(5)
    legacy = np.random.RandomState(3)
    py_rng = random.Random(4)
    states = {
        "torch": torch.get_rng_state(),
        "numpy": np_rng.bit_generator.state,
        "legacy": legacy.get_state(),
        "python": py_rng.getstate(),
    }
    save_checkpoint(tmp_path / "c", modules={}, states={"rng": states})
    rng = load_checkpoint(tmp_path / "c").state("rng")

    assert rng["numpy"]["state"]["state"] == np_rng.bit_generator.state["state"]["state"]
    expected_torch = torch.rand(5)
    torch.set_rng_state(rng["torch"])
    assert torch.equal(torch.rand(5), expected_torch)

    np_rng2 = np.random.default_rng(99)
    np_rng2.bit_generator.state = rng["numpy"]
    np.testing.assert_array_equal(np_rng2.random(5), np_rng.random(5))

    legacy2 = np.random.RandomState(0)
    legacy2.set_state(rng["legacy"])
    np.testing.assert_array_equal(legacy2.random_sample(5), legacy.random_sample(5))

    py_rng2 = random.Random()
    py_rng2.setstate(rng["python"])
    assert [py_rng2.random() for _ in range(5)] == [py_rng.random() for _ in range(5)]


def test_int_keys_preserved_through_checkpoint(tmp_path):
    state = {0: "a", 1: {2: [3]}, "0": "string key"}
    save_checkpoint(tmp_path / "c", modules={}, states={"s": state})
    restored = load_checkpoint(tmp_path / "c").state("s")
    _assert_same(state, restored)


def test_module_state_dict_metadata_kept():
    model = _model()
    sd = model.state_dict()
    tensors, skeleton = flatten_state(sd)
    restored = unflatten_state(tensors, _json_round_trip(skeleton))
    assert isinstance(restored, OrderedDict)
    assert restored._metadata == sd._metadata
    _model().load_state_dict(restored)


# ---------------------------------------------------------------------------------------------
# load_module mismatches
# ---------------------------------------------------------------------------------------------


def test_shape_mismatch_message_names_parameter_and_shapes(tmp_path):
    save_checkpoint(tmp_path / "c", modules={"actor": _model(in_dim=30)})
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(tmp_path / "c").load_module("actor", _model(in_dim=26))
    message = str(info.value)
    assert "\n" not in message
    assert (
        "actor: parameter '0.weight' has shape (16, 30) in the checkpoint but (16, 26) "
        "in the model" in message
    )
    assert str(tmp_path / "c") in message


def test_missing_and_unexpected_keys_reported(tmp_path):
    save_checkpoint(tmp_path / "c", modules={"actor": {"a": torch.ones(2), "old": torch.ones(1)}})
    module = nn.Module()
    module.a = nn.Parameter(torch.zeros(2))
    module.new = nn.Parameter(torch.zeros(1))
    module.register_buffer("buf", torch.zeros(1))
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(tmp_path / "c").load_module("actor", module)
    message = str(info.value)
    assert "parameter 'new' is in the model but not in the checkpoint" in message
    assert "buffer 'buf' is in the model but not in the checkpoint" in message
    assert "tensor 'old' is in the checkpoint but not in the model" in message
    assert torch.equal(module.a, torch.zeros(2))  # nothing loaded on failure


def test_mismatch_list_truncated_to_five(tmp_path):
    save_checkpoint(tmp_path / "c", modules={"m": {f"p{i}": torch.ones(1) for i in range(8)}})
    with pytest.raises(CheckpointError, match=r"8 mismatch\(es\).*; and 3 more$"):
        load_checkpoint(tmp_path / "c").load_module("m", nn.Module())


def test_load_module_with_device(tmp_path):
    model = _model()
    save_checkpoint(tmp_path / "c", modules={"actor": model})
    model2 = _model(in_dim=6)
    with torch.no_grad():
        model2[0].weight.zero_()
    load_checkpoint(tmp_path / "c").load_module("actor", model2, device="cpu")
    assert torch.equal(model2[0].weight, model[0].weight)


# ---------------------------------------------------------------------------------------------
# Arrays, JSON documents, meta
# ---------------------------------------------------------------------------------------------


def test_arrays_round_trip(tmp_path):
    arrays = {
        "obs": np.arange(24, dtype=np.uint8).reshape(2, 3, 4),
        "action": np.array([[-3, 4]], dtype=np.int16),
        "reward": np.linspace(0, 1, 5, dtype=np.float32),
        "done": np.array([True, False, True]),
        "empty": np.zeros((0, 3), dtype=np.float32),
    }
    save_checkpoint(tmp_path / "c", modules={}, arrays=arrays)
    ckpt = load_checkpoint(tmp_path / "c")
    assert ckpt.has_arrays()
    loaded = ckpt.arrays()
    assert list(loaded) == list(arrays)
    for name, array in arrays.items():
        assert loaded[name].dtype == array.dtype and loaded[name].shape == array.shape
        np.testing.assert_array_equal(loaded[name], array)


def test_no_arrays(tmp_path):
    ckpt = load_checkpoint(_save_basic(tmp_path / "c"))
    assert not ckpt.has_arrays()
    with pytest.raises(CheckpointError, match=r"expected arrays\.npz"):
        ckpt.arrays()


def test_object_arrays_rejected_before_writing(tmp_path):
    bad = np.array([{"a": 1}, None], dtype=object)
    with pytest.raises(CheckpointError, match=r"'replay'.*object"):
        save_checkpoint(tmp_path / "c", modules={}, arrays={"replay": bad})
    assert list(tmp_path.iterdir()) == []


def test_json_files_and_meta(tmp_path):
    split = {"train": ["a", "b"], "test": ["c"]}
    save_checkpoint(
        tmp_path / "c",
        modules={},
        meta={"step": np.int64(5), "spaces": {"obs": [3, 4]}},
        json_files={"split": split, "instructions": ["x", "y"]},
    )
    ckpt = load_checkpoint(tmp_path / "c")
    assert ckpt.meta == {"format_version": FORMAT_VERSION, "step": 5, "spaces": {"obs": [3, 4]}}
    assert ckpt.json("split") == split
    assert ckpt.json("instructions") == ["x", "y"]
    with pytest.raises(CheckpointError, match=r"expected other\.json.*instructions, split"):
        ckpt.json("other")


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"meta": {"format_version": 2}}, "reserved"),
        ({"meta": {"x": object()}}, "JSON-serialisable"),
        ({"json_files": {"meta": {}}}, "reserved"),
        ({"json_files": {"../x": {}}}, "bad json file name"),
        ({"modules": {"a.b": {}}}, "bad module name"),
        ({"modules": {"a": {"w": [1.0]}}}, "expected a tensor for 'w'"),
        ({"states": {"a.b": 1}}, "bad state name"),
        ({"arrays": {"file": np.zeros(1)}}, "bad array name"),
    ],
)
def test_bad_inputs_rejected(tmp_path, kwargs, match):
    kwargs.setdefault("modules", {})
    with pytest.raises(CheckpointError, match=match):
        save_checkpoint(tmp_path / "c", **kwargs)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# Loading errors
# ---------------------------------------------------------------------------------------------


def test_missing_directory(tmp_path):
    with pytest.raises(CheckpointError, match="expected a directory but found nothing") as info:
        load_checkpoint(tmp_path / "nope")
    assert isinstance(info.value, LcrlError) and isinstance(info.value, ValueError)


def test_missing_meta(tmp_path):
    (tmp_path / "c").mkdir()
    with pytest.raises(CheckpointError, match=r"expected meta\.json but found no such file"):
        load_checkpoint(tmp_path / "c")


def test_corrupt_meta(tmp_path):
    path = _save_basic(tmp_path / "c")
    (path / "meta.json").write_text('{"format_version": 1,')
    with pytest.raises(CheckpointError, match=r"corrupt .*meta\.json: expected valid JSON"):
        load_checkpoint(path)
    (path / "meta.json").write_text("[1, 2]")
    with pytest.raises(CheckpointError, match="expected a JSON object but found list"):
        load_checkpoint(path)


def test_wrong_format_version(tmp_path):
    path = _save_basic(tmp_path / "c")
    (path / "meta.json").write_text(json.dumps({"format_version": 99}))
    with pytest.raises(CheckpointError, match=r"expected format_version 1 .* but found 99"):
        load_checkpoint(path)


def test_corrupt_or_missing_tensor_files(tmp_path):
    path = _save_basic(tmp_path / "c")
    ckpt = load_checkpoint(path)
    (path / "weights.safetensors").write_bytes(b"\x00garbage")
    with pytest.raises(CheckpointError, match=r"corrupt .*weights\.safetensors"):
        ckpt.weights("actor")
    (path / "state.safetensors").unlink()
    with pytest.raises(CheckpointError, match=r"expected state\.safetensors"):
        ckpt.state("counters")
    with pytest.raises(CheckpointError, match=r"expected state 'nope'.*counters"):
        ckpt.state("nope")


# ---------------------------------------------------------------------------------------------
# Atomicity
# ---------------------------------------------------------------------------------------------


def _siblings(tmp_path: Path) -> list[str]:
    return sorted(p.name for p in tmp_path.iterdir())


def test_overwrite_leaves_complete_checkpoint_and_no_temp_dirs(tmp_path):
    path = tmp_path / "ckpt"
    _save_basic(path, meta={"v": 1}, arrays={"x": np.ones(3)})
    returned = _save_basic(path, meta={"v": 2}, json_files={"other": 1})
    assert returned == path
    assert _siblings(tmp_path) == ["ckpt"]
    ckpt = load_checkpoint(path)
    assert ckpt.meta["v"] == 2
    assert ckpt.json("other") == 1
    assert not ckpt.has_arrays()  # the old checkpoint's files are gone
    with pytest.raises(CheckpointError):
        ckpt.json("instructions")
    assert ckpt.state("counters") == {"step": 7}


def test_failure_during_save_keeps_previous_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "ckpt"
    _save_basic(path, meta={"v": 1})

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(safetensors.torch, "save_file", boom)
    with pytest.raises(RuntimeError, match="disk on fire"):
        _save_basic(path, meta={"v": 2})
    assert _siblings(tmp_path) == ["ckpt"]
    assert load_checkpoint(path).meta["v"] == 1

    with pytest.raises(RuntimeError, match="disk on fire"):
        _save_basic(tmp_path / "fresh")
    assert _siblings(tmp_path) == ["ckpt"]


def test_failure_while_swapping_restores_previous(tmp_path, monkeypatch):
    path = tmp_path / "ckpt"
    _save_basic(path, meta={"v": 1})
    real_rename = os.rename
    calls = []

    def flaky_rename(src, dst):
        calls.append((Path(src).name, Path(dst).name))
        if len(calls) == 2:  # old moved aside; now moving the new one into place fails
            raise OSError("rename failed")
        real_rename(src, dst)

    monkeypatch.setattr(os, "rename", flaky_rename)  # the one os module the writer uses
    with pytest.raises(CheckpointWriteError, match=f"cannot write {path}: rename failed") as e:
        _save_basic(path, meta={"v": 2})
    assert isinstance(e.value.__cause__, OSError)
    monkeypatch.undo()
    assert _siblings(tmp_path) == ["ckpt"]
    assert load_checkpoint(path).meta["v"] == 1


@pytest.mark.parametrize("target", ["weights.safetensors", "state.safetensors", "arrays.npz"])
def test_write_errors_name_the_file_and_the_problem(tmp_path, monkeypatch, target):
    """A full disk as safetensors reports it (its own error type) and as numpy does (an
    OSError): one CheckpointWriteError naming the file, the previous checkpoint kept."""
    from numpy.lib import format as npy_format

    path = tmp_path / "ckpt"
    _save_basic(path, meta={"v": 1})
    write = safetensors.torch.save_file

    def full_safetensors(tensors, filename, *args, **kwargs):
        if Path(filename).name == target:
            raise safetensors.SafetensorError(
                "Error while serializing: I/O error: No space left on device (os error 28)"
            )
        return write(tensors, filename, *args, **kwargs)

    def full_npz(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(safetensors.torch, "save_file", full_safetensors)
    monkeypatch.setattr(npy_format, "write_array", full_npz)
    with pytest.raises(CheckpointWriteError) as e:
        _save_basic(path, meta={"v": 2}, arrays={"x": np.zeros(3)})
    assert str(e.value) == f"cannot write {path / target}: No space left on device"
    assert (e.value.path, e.value.problem) == (path / target, "No space left on device")
    assert _siblings(tmp_path) == ["ckpt"]
    assert load_checkpoint(path).meta["v"] == 1


def test_write_problem_reads_the_operating_system_message():
    assert write_problem(OSError(errno.EROFS, "Read-only file system")) == "Read-only file system"
    old = 'IoError(Os { code: 28, kind: StorageFull, message: "No space left on device" })'
    assert write_problem(safetensors.SafetensorError(old)) == "No space left on device"
    assert write_problem(RuntimeError("odd\nmore")) == "odd"


def test_interrupted_swap_hint(tmp_path):
    path = _save_basic(tmp_path / "ckpt")
    path.rename(tmp_path / ".ckpt.old-123")
    with pytest.raises(CheckpointError, match=r"previous checkpoint at .*\.ckpt\.old-123"):
        load_checkpoint(path)


def test_refuses_to_replace_non_checkpoint_directory(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "precious.txt").write_text("data")
    with pytest.raises(CheckpointError, match="refusing to replace"):
        save_checkpoint(run, modules={})
    assert (run / "precious.txt").read_text() == "data"
    empty = tmp_path / "empty"
    empty.mkdir()
    save_checkpoint(empty, modules={})
    assert load_checkpoint(empty).meta == {"format_version": FORMAT_VERSION}


# ---------------------------------------------------------------------------------------------
# latest.json
# ---------------------------------------------------------------------------------------------


def test_write_and_find_latest(tmp_path):
    run = tmp_path / "run"
    assert find_latest(run) is None
    first = _save_basic(run / "checkpoints" / "step_100")
    write_latest(run, first)
    assert json.loads((run / "latest.json").read_text()) == {"checkpoint": "checkpoints/step_100"}
    assert find_latest(run) == first
    second = _save_basic(run / "checkpoints" / "step_200")
    write_latest(run, second)
    assert find_latest(run) == second
    assert sorted(p.name for p in run.iterdir()) == ["checkpoints", "latest.json"]
    assert load_checkpoint(find_latest(run)).meta["format_version"] == FORMAT_VERSION

    # The run directory can move: the pointer is relative.
    moved = tmp_path / "moved"
    run.rename(moved)
    assert find_latest(moved) == moved / "checkpoints" / "step_200"

    shutil.rmtree(moved / "checkpoints" / "step_200")
    with pytest.raises(CheckpointError, match=r"step_200.*does not exist"):
        find_latest(moved)


def test_latest_errors(tmp_path):
    with pytest.raises(CheckpointError, match="expected a checkpoint directory"):
        write_latest(tmp_path, tmp_path / "missing")
    (tmp_path / "latest.json").write_text("{not json")
    with pytest.raises(CheckpointError, match=r"corrupt .*latest\.json"):
        find_latest(tmp_path)
    (tmp_path / "latest.json").write_text('{"path": "x"}')
    with pytest.raises(CheckpointError, match="expected"):
        find_latest(tmp_path)


# ---------------------------------------------------------------------------------------------
# No pickle
# ---------------------------------------------------------------------------------------------


def test_loading_never_unpickles(tmp_path, monkeypatch):
    model = _model()
    opt = torch.optim.Adam(model.parameters())
    _train(model, opt, steps=2, seed=0)
    save_checkpoint(
        tmp_path / "c",
        modules={"actor": model},
        states={
            "opt": opt.state_dict(),
            "rng": {
                "np": np.random.default_rng(0).bit_generator.state,
                "legacy": np.random.RandomState(0).get_state(),
            },
        },
        meta={"step": 2},
        json_files={"split": {"train": [1]}},
        arrays={"obs": np.zeros((4, 3), dtype=np.float32), "names": np.array(["a", "bc"])},
    )

    def forbidden(*args, **kwargs):
        raise AssertionError("pickle used while loading a checkpoint")

    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "loads", forbidden)
    monkeypatch.setattr(pickle, "Unpickler", forbidden)
    monkeypatch.setattr(torch, "load", forbidden)

    ckpt = load_checkpoint(tmp_path / "c")
    model2 = _model()
    ckpt.load_module("actor", model2)
    ckpt.weights("actor")
    opt_state = ckpt.state("opt")
    ckpt.state("rng")
    ckpt.json("split")
    assert ckpt.has_arrays()
    arrays = ckpt.arrays()
    assert arrays["names"].tolist() == ["a", "bc"]
    torch.optim.Adam(model2.parameters()).load_state_dict(opt_state)
    find_latest(tmp_path)
