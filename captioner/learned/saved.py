"""A trained captioner and/or reward model with what it needs to run (:class:`LearnedCaptioner`)."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from captioner.dataset import CaptionDataset
from captioner.grammar import try_parse
from captioner.learned.data import _text_encoder
from captioner.learned.factored import SlotPredicates, output_index, output_indices
from captioner.learned.models import Captioner, CaptionModelConfig, RewardModel
from captioner.learned.vocabulary import CHECKPOINT_KIND, NONE_TEXT, Vocabulary
from lcrl.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from lcrl.errors import LcrlError
from lcrl.perception import Perception, embedded_meta, load_model


class LearnedCaptioner:
    """A trained captioner and/or reward model with what they need to run.

    Load one with :meth:`load`; :meth:`caption` and :meth:`score` take uint8 frames.
    """

    def __init__(
        self,
        vocab: Vocabulary,
        instructions: list[str],
        instruction_set: list[str],
        frame_shape: tuple[int, ...],
        proprio_dim: int,
        cfg: CaptionModelConfig,
        p_mean: np.ndarray,
        p_std: np.ndarray,
        text_model: str,
        meta: dict[str, Any],
        device: str = "cpu",
    ) -> None:
        self.vocab = vocab
        self.instructions = instructions
        self.instruction_set = instruction_set
        self.frame_shape = tuple(int(v) for v in frame_shape)
        self.proprio_dim = int(proprio_dim)
        self.cfg = cfg
        self.p_mean = np.asarray(p_mean, np.float32)
        self.p_std = np.asarray(p_std, np.float32)
        self.text_model = text_model
        self.meta = meta
        self.device = torch.device(device)
        self.captioner: Captioner | None = None
        self.reward: RewardModel | None = None
        #: The factored models (``head=factored``): one network that captions and scores.
        self.factored: SlotPredicates | None = None
        self._outputs: tuple[torch.Tensor, list[str]] | None = None  # see _caption_outputs
        self._encoder: Any = None
        #: The frozen perception model both models read through (``encoder=perception``).
        self.perception: Perception | None = None
        #: The last frame pairs perceived and what perception made of them: an episode's
        #: captions and rewards are read from the same frames (see :meth:`_inputs`).
        self._last: tuple[bytes, tuple[torch.Tensor, ...]] | None = None

    # -- inputs
    def _inputs(
        self, first: np.ndarray, current: np.ndarray, p0: np.ndarray | None, p: np.ndarray | None
    ) -> tuple[torch.Tensor, ...]:
        first = np.asarray(first, np.uint8)
        current = np.asarray(current, np.uint8)
        if first.shape[1:] != self.frame_shape or current.shape != first.shape:
            raise LcrlError(
                f"frames must be (B, {', '.join(map(str, self.frame_shape))}) uint8 pairs; got "
                f"{first.shape} and {current.shape}"
            )
        b = first.shape[0]
        if p0 is None or p is None:
            if self.cfg.use_proprio:
                raise LcrlError("this model reads proprioception: pass p0 and p")
            p0 = p = np.zeros((b, self.proprio_dim), np.float32)
        p0, p = np.asarray(p0, np.float32), np.asarray(p, np.float32)
        key = None
        if self.perception is not None:  # what the models read: the estimated slots
            key = _digest(first, current, p0, p)
            if self._last is not None and self._last[0] == key:
                return self._last[1]
            first = self._perceive_first(first, p0)
            present = self.perception.presence(first) if self.cfg.first_presence else None
            current = self.perceive(current, p, present=present)
        p0 = (p0 - self.p_mean) / self.p_std
        p = (p - self.p_mean) / self.p_std
        dev = self.device
        inputs = tuple(torch.as_tensor(x, device=dev) for x in (first, current, p0, p))
        if key is not None:
            self._last = (key, inputs)
        return inputs

    def _perceive_first(self, first: np.ndarray, p0: np.ndarray) -> np.ndarray:
        """Perception of the first frames of the pairs: once where every pair starts from
        the same frame and robot state (an episode's frames against its first)."""
        if len(first) > 1 and (first == first[:1]).all() and (p0 == p0[:1]).all():
            return np.repeat(self.perceive(first[:1], p0[:1]), len(first), 0)
        return self.perceive(first, p0)

    def perceive(
        self,
        frames: Any,
        proprio: np.ndarray,
        batch: int = 256,
        progress: bool = False,
        present: np.ndarray | None = None,
    ) -> np.ndarray:
        """Perception's estimated observations ``(N, dim)`` of frames (an array, or any
        sequence that slices into arrays, such as a file's dataset) and their robot state
        (``encoder=perception``), with presence flags ``(N, count)`` to use instead of the
        estimated ones if given; ``progress`` shows a bar."""
        if self.perception is None:
            raise LcrlError("these models read camera frames, not a perception model's slots")
        from tqdm import tqdm

        start = self.perception.layout.start
        n = len(frames)
        bar = tqdm(total=n, desc="perception", unit="frame", disable=not progress or n == 0)
        out = []
        for i in range(0, n, batch):
            x = np.asarray(frames[i : i + batch])
            flags = None if present is None else present[i : i + batch]
            out.append(self.perception.observation(x, proprio[i : i + batch, :start], flags))
            bar.update(len(x))
        bar.close()
        return np.concatenate(out).astype(np.float32) if out else np.zeros((0, 0), np.float32)

    def encode_texts(self, texts: Sequence[str]) -> torch.Tensor:
        """Frozen text embeddings of instructions (any free text)."""
        if self._encoder is None:
            self._encoder = _text_encoder(self.text_model)
        return torch.as_tensor(self._encoder.encode(list(texts)), device=self.device)

    # -- inference
    def has(self, model: str) -> bool:
        """Whether this checkpoint can caption (``captioner``) or score instructions
        (``reward``)."""
        if self.factored is not None:
            return True
        return (self.captioner if model == "captioner" else self.reward) is not None

    def _factored(self, *frames: Any) -> tuple[torch.Tensor, torch.Tensor]:
        assert self.factored is not None
        self.factored.eval()
        return self.factored(*self._inputs(*frames))

    def _caption_outputs(self) -> tuple[torch.Tensor, list[str]]:
        """The factored outputs a caption may be (the checkpoint's instruction table) and
        their texts, parsed once."""
        assert self.factored is not None
        if self._outputs is None:
            count = self.factored.layout.count
            parsed = ((t, try_parse(t)) for t in self.instructions)
            rows = [(output_index(ins, count), t) for t, ins in parsed if ins is not None]
            rows = [(i, t) for i, t in rows if i is not None]
            index = torch.as_tensor([i for i, _ in rows], device=self.device)
            self._outputs = (index, [t for _, t in rows])
        return self._outputs

    def _context(self, model: str, *frames: Any) -> torch.Tensor:
        net = self.captioner if model == "captioner" else self.reward
        if net is None:
            other = "reward" if model == "captioner" else "captioner"
            raise LcrlError(
                f"this checkpoint has no {model} (it was trained with --models {other})"
            )
        net.eval()
        inputs = self._inputs(*frames)
        return net.encoder(*inputs) if isinstance(net, Captioner) else net.context(*inputs)

    @torch.no_grad()
    def captions(
        self,
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
        beam: int = 0,
    ) -> list[list[tuple[str, float]]]:
        """Captions and their log-likelihoods per frame pair, best first: one greedy
        caption, or up to ``beam`` from a beam search (``beam > 1``). ``<none>``: nothing
        achieved."""
        if self.factored is not None:
            _, scores = self._factored(first, current, p0, p)
            outputs, texts = self._caption_outputs()
            none = self.factored.none_score.expand(scores.shape[0], 1)
            logp = torch.log_softmax(torch.cat([scores[:, outputs], none], 1), 1)
            texts = [*texts, NONE_TEXT]
            top_lp, top_id = logp.topk(min(max(beam, 1), logp.shape[1]), 1)
            return [
                [(texts[i], float(lp)) for lp, i in zip(lps, ids, strict=True)]
                for lps, ids in zip(top_lp.tolist(), top_id.tolist(), strict=True)
            ]
        ctx = self._context("captioner", first, current, p0, p)
        assert self.captioner is not None
        if beam > 1:
            return [
                [(self.vocab.decode(ids), float(sc)) for ids, sc in beams]
                for beams in self.captioner.beam(ctx, beam)
            ]
        ids, logp = self.captioner.greedy(ctx)
        return [
            [(self.vocab.decode(row), float(lp))]
            for row, lp in zip(ids.tolist(), logp.tolist(), strict=True)
        ]

    def caption(
        self,
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
        beam: int = 0,
    ) -> list[tuple[str, float]]:
        """The best caption and its log-likelihood per frame pair (see :meth:`captions`)."""
        return [
            c[0] if c else ("", float("-inf")) for c in self.captions(first, current, p0, p, beam)
        ]

    @torch.no_grad()
    def score(
        self,
        texts: Sequence[str],
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
    ) -> np.ndarray:
        """Probability that each ``texts[i]`` is satisfied by the change from
        ``first[i]`` to ``current[i]``."""
        if len(texts) != len(first):
            raise LcrlError(f"{len(texts)} instructions for {len(first)} frame pairs")
        if self.factored is not None:
            idx = output_indices(texts, self.factored.layout.count)
            logits, _ = self._factored(first, current, p0, p)
            rows = torch.arange(len(idx), device=logits.device)
            return torch.sigmoid(logits[rows, torch.as_tensor(idx)]).cpu().numpy()
        ctx = self._context("reward model", first, current, p0, p)
        return torch.sigmoid(self.reward(ctx, self.encode_texts(texts))).cpu().numpy()

    @torch.no_grad()
    def score_matrix(
        self,
        texts: Sequence[str],
        first: np.ndarray,
        current: np.ndarray,
        p0: np.ndarray | None = None,
        p: np.ndarray | None = None,
    ) -> np.ndarray:
        """``(len(current), len(texts))`` probabilities: every instruction against every
        frame pair (the frames are encoded once)."""
        if self.factored is not None:
            idx = output_indices(texts, self.factored.layout.count)
            logits, _ = self._factored(first, current, p0, p)
            return torch.sigmoid(logits[:, torch.as_tensor(idx)]).cpu().numpy()
        ctx = self._context("reward model", first, current, p0, p)
        emb = self.encode_texts(texts)
        n, m = ctx.shape[0], emb.shape[0]
        # row-major: frame i against text k at i * m + k
        logits = self.reward(ctx.repeat_interleave(m, 0), emb.repeat(n, 1))
        return torch.sigmoid(logits).view(n, m).cpu().numpy()

    # -- saving
    def save(self, directory: str | Path) -> Path:
        modules: dict[str, nn.Module] = {}
        if self.captioner is not None:
            modules["captioner"] = self.captioner
        if self.reward is not None:
            modules["reward"] = self.reward
        if self.factored is not None:
            modules["factored"] = self.factored
        if self.perception is not None:
            modules["perception"] = self.perception
        meta = {
            "kind": CHECKPOINT_KIND,
            "models": sorted(modules),
            "frame_shape": list(self.frame_shape),
            "proprio_dim": self.proprio_dim,
            "model": asdict(self.cfg),
            "text_model": self.text_model,
            "proprio_mean": self.p_mean.tolist(),
            "proprio_std": self.p_std.tolist(),
            **self.meta,
        }
        if self.perception is not None:  # rebuilt from here when loading
            meta["perception"] = embedded_meta(
                self.perception, str(self.meta.get("train", {}).get("perception", ""))
            )
        json_files = {
            "vocabulary": {"words": self.vocab.words},
            "instructions": {"texts": self.instructions, "sets": self.instruction_set},
        }
        return save_checkpoint(directory, modules=modules, meta=meta, json_files=json_files)

    @classmethod
    def load(cls, path: str | Path, device: str = "cpu") -> LearnedCaptioner:
        """Load a checkpoint written by :meth:`save` (or ``lcrl caption train``)."""
        try:
            ckpt = load_checkpoint(path)
        except CheckpointError as e:
            raise LcrlError(str(e)) from None
        meta = ckpt.meta
        if meta.get("kind") != CHECKPOINT_KIND:
            raise LcrlError(
                f"{path} is not a learned-captioner checkpoint (kind {meta.get('kind')!r}); "
                "policy checkpoints go to lcrl eval / act"
            )
        words = ckpt.json("vocabulary")["words"]
        vocab = Vocabulary([])
        vocab.words = list(words)
        vocab.index = {w: i for i, w in enumerate(words)}
        table = ckpt.json("instructions")
        # checkpoints from before an option read as they were trained
        saved = {
            "encoder": "flatten",
            "slot_query": False,
            "first_presence": False,
            **meta["model"],
        }
        mcfg = CaptionModelConfig(
            **{
                **saved,
                "channels": tuple(saved["channels"]),
                "strides": tuple(saved.get("strides", ())),
            }
        )
        known = {"kind", "models", "frame_shape", "proprio_dim", "model", "text_model",
                 "proprio_mean", "proprio_std", "format_version", "perception"}  # fmt: skip
        lc = cls(
            vocab,
            list(table["texts"]),
            list(table["sets"]),
            tuple(meta["frame_shape"]),
            int(meta["proprio_dim"]),
            mcfg,
            np.asarray(meta["proprio_mean"], np.float32),
            np.asarray(meta["proprio_std"], np.float32),
            meta.get("text_model", ""),
            {k: v for k, v in meta.items() if k not in known},
            device,
        )
        try:
            if mcfg.encoder == "perception":
                lc.perception = load_model(path, device)[0]
            if "captioner" in meta["models"]:
                lc.captioner = Captioner(
                    lc.frame_shape, lc.proprio_dim, len(vocab), mcfg, lc.perception
                )
                ckpt.load_module("captioner", lc.captioner)
                lc.captioner.to(lc.device)
            if "factored" in meta["models"]:
                assert lc.perception is not None
                lc.factored = SlotPredicates(
                    lc.perception, lc.proprio_dim, mcfg.hidden, mcfg.use_proprio
                )
                ckpt.load_module("factored", lc.factored)
                lc.factored.to(lc.device)
            if "reward" in meta["models"]:
                dim = int(meta["text_dim"])
                lc.reward = RewardModel(lc.frame_shape, lc.proprio_dim, dim, mcfg, lc.perception)
                ckpt.load_module("reward", lc.reward)
                lc.reward.to(lc.device)
        except CheckpointError as e:
            raise LcrlError(str(e)) from None
        return lc

    def check_dataset(self, data: CaptionDataset) -> None:
        """Refuse a dataset whose frames or robot state differ from the training data's."""
        if data.frame_shape != self.frame_shape or data.proprio.shape[1] != self.proprio_dim:
            raise LcrlError(
                f"the models read {'x'.join(map(str, self.frame_shape))} frames and "
                f"{self.proprio_dim} proprioception values; {data.path} has "
                f"{'x'.join(map(str, data.frame_shape))} frames and {data.proprio.shape[1]}"
            )


def _digest(*arrays: np.ndarray) -> bytes:
    """A fingerprint of arrays' shapes and contents (the frames perceived last)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.digest()
