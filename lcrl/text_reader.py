"""A token-level reader of instructions on top of the frozen text encoder.

The mean-pooled sentence vector of the frozen encoder loses which word says what: a linear
probe trained on the training instructions (and their training-only phrasings) reads the
family and direction of unseen paraphrases right 0.79 of the time from it, against 0.91
when a learned attention over the encoder's token states picks the words first
(``benchmarks/grounding_probe.py``). :class:`TokenReader` is that attention: a few learned
queries pool the token states of an instruction, and small heads predict the slot values
its meaning has (family, colours, shapes, direction, relation), supervised by the parse
of the training instructions. With ``per_slot`` each meaning slot has queries of its own,
so the colour is read from the tokens the colour head attends to and the direction from
those of the direction head, rather than all heads from one shared pooling. It is
trained once, before reinforcement learning, and then frozen. :class:`ReadingEncoder`
gives the policy the sentence vector followed by the reader's predicted slot-value
probabilities: a soft parse that unseen phrasings share with the training instructions
they mean.

The encoder stays frozen; the reader's weights travel with the checkpoint.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F


class TokenReader(nn.Module):
    """Learned queries over token states, and one classifier per meaning slot.

    Args:
        dim: width of the token states.
        slots: for each meaning slot (``family``, ``colour`` ...), its number of values.
        queries: attention queries (each pools the tokens once); per slot with ``per_slot``.
        hidden: width of the layer between the pooled tokens and the classifiers.
        per_slot: every slot pools the tokens with queries of its own and has a hidden
            layer of its own; otherwise all slots share the queries and the hidden layer.
    """

    def __init__(
        self,
        dim: int,
        slots: Mapping[str, int],
        queries: int = 4,
        hidden: int = 64,
        per_slot: bool = False,
    ) -> None:
        super().__init__()
        self.slots = dict(slots)
        self.queries, self.width, self.per_slot = int(queries), int(hidden), bool(per_slot)
        if self.per_slot:
            self.query = nn.Linear(dim, queries * len(self.slots))
            self.hidden = nn.ModuleDict(
                {k: nn.Sequential(nn.Linear(queries * dim, hidden), nn.ReLU()) for k in self.slots}
            )
        else:
            self.query = nn.Linear(dim, queries)
            self.hidden = nn.Sequential(nn.Linear(queries * dim, hidden), nn.ReLU())
        self.heads = nn.ModuleDict({k: nn.Linear(hidden, n) for k, n in self.slots.items()})
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    @property
    def out_dim(self) -> int:
        """Width of :meth:`probabilities`' rows."""
        return sum(self.slots.values())

    def forward(self, states: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """Logits per slot for token states ``(B, T, dim)`` with their mask ``(B, T)``."""
        return self.read((states - self.mean) / self.std, mask)

    def read(self, x: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """Logits per slot for token states already standardised by ``mean`` and ``std``."""
        w = self.query(x).masked_fill(~mask.unsqueeze(-1), -1e9).softmax(1)  # (B, T, Q)
        pooled = torch.bmm(w.transpose(1, 2), x)  # (B, Q, dim)
        if not self.per_slot:
            h = self.hidden(pooled.flatten(1))
            return {k: head(h) for k, head in self.heads.items()}
        # slot i reads the pooled vectors of its queries i*q .. (i+1)*q; unbind, not
        # slicing, so that the backward pass stacks the slots' gradients instead of
        # adding each into a zero-filled copy of the whole pooled tensor
        per_slot = pooled.reshape(len(pooled), len(self.slots), -1).unbind(1)
        return {
            k: self.heads[k](self.hidden[k](v)) for k, v in zip(self.slots, per_slot, strict=True)
        }

    def probabilities(self, states: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Every slot's value probabilities, one slot after another, ``(B, out_dim)``."""
        return torch.cat([v.softmax(-1) for v in self(states, mask).values()], -1)


def keep_mask(shape: torch.Size, p: float, gen: torch.Generator) -> torch.Tensor:
    """Dropout's mask: uint8 ones and zeros of ``shape``, each zero with probability ``p``
    rounded to a multiple of 1/256 (exact for 0.5). One random byte per element, drawn as
    64-bit integers eight bytes at a time, and a product with uint8 rather than a
    boolean fill: on a CPU about 4x faster than ``torch.rand`` and ``masked_fill_``."""
    count = int(np.prod(shape))
    words = torch.randint(
        -(2**63), 2**63 - 1, ((count + 7) // 8,), dtype=torch.int64, generator=gen
    )
    drawn = words.view(torch.uint8)[:count].view(shape)
    return (drawn >= min(round(p * 256), 255)).view(torch.uint8)


def fit_reader(
    states: np.ndarray,
    mask: np.ndarray,
    labels: Mapping[str, Sequence[int]],
    slots: Mapping[str, int],
    steps: int = 600,
    seed: int = 0,
    dropout: float = 0.0,
    per_slot: bool = False,
    queries: int = 4,
    hidden: int = 64,
    batch_size: int = 0,
) -> TokenReader:
    """Train a :class:`TokenReader` on token states and the slot values of each text
    (cross-entropy summed over slots), Adam; returned frozen, in eval mode.

    Args:
        states, mask: :meth:`lcrl.text_encoder.FrozenTextEncoder.encode_tokens` of the texts.
        labels: per slot, the value index of every text.
        slots: per slot, its number of values.
        steps: gradient steps.
        seed: the initialisation's seed.
        dropout: the fraction of token-state features zeroed at each step, to 1/256
            (:func:`keep_mask`; a fresh mask every step; none when reading), so that no
            single feature direction of the words seen in training decides a slot alone.
        per_slot, queries, hidden: the reader's design (:class:`TokenReader`).
        batch_size: texts per step, drawn with replacement from the seed's generator; 0
            (or at least the number of texts): every text at every step. Fitted on
            robosuite's 3,201 texts without the held-out words of ``benchmarks/reader.py``'s
            validation set, one reader read that set equally well either way (0.592 right
            after 300 steps of 512 and after 600 full-batch steps, seed 0), in 11 s
            instead of 394.
    """
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"dropout must be in [0, 1), not {dropout}")
    if batch_size < 0:
        raise ValueError(f"batch_size must be 0 (full batch) or positive, not {batch_size}")
    gen = torch.Generator().manual_seed(int(seed))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(gen.initial_seed()))
        reader = TokenReader(states.shape[-1], slots, queries, hidden, per_slot)
    x, m = torch.as_tensor(states), torch.as_tensor(mask)
    real = x[m]
    reader.mean.copy_(real.mean(0))
    reader.std.copy_(real.std(0) + 1e-6)
    # the reader reads (states * keep / (1 - dropout) - mean) / std: scaled once here, a
    # step then zeroes the dropped features (keep_mask) and subtracts mean / std in place
    scaled = x / (reader.std * (1.0 - dropout))
    shift = reader.mean / reader.std
    y = {k: torch.as_tensor(np.asarray(v, np.int64)) for k, v in labels.items()}
    opt = torch.optim.Adam(reader.parameters(), 1e-3)
    n = len(x)
    for _ in range(int(steps)):
        # minibatches and dropout are drawn from the seed's generator: the same seed
        # fits the same reader
        if 0 < batch_size < n:
            rows = torch.randint(0, n, (int(batch_size),), generator=gen)
            xb, mb, yb = scaled[rows], m[rows], {k: v[rows] for k, v in y.items()}
        else:
            xb, mb, yb = scaled.clone(), m, y
        if dropout:
            xb.mul_(keep_mask(xb.shape, dropout, gen))
        logits = reader.read(xb.sub_(shift), mb)
        loss = sum(F.cross_entropy(logits[k], yb[k]) for k in reader.slots)
        opt.zero_grad()
        loss.backward()
        opt.step()
    reader.eval()
    reader.requires_grad_(False)
    return reader


class ReaderEnsemble(nn.Module):
    """Readers fitted from different initialisations, read as one: per slot, the mean of
    their log-probabilities (a reader fitted on few instructions may tie a word to the
    wrong slot by chance; its peers seldom do the same).

    Args:
        members: fitted :class:`TokenReader` of the same slots and sizes.
    """

    def __init__(self, members: Sequence[TokenReader]) -> None:
        super().__init__()
        if not members:
            raise ValueError("an ensemble needs at least one reader")
        self.members = nn.ModuleList(members)
        first = members[0]
        self.slots, self.queries, self.width = dict(first.slots), first.queries, first.width
        self.per_slot = first.per_slot

    @property
    def out_dim(self) -> int:
        """Width of :meth:`probabilities`' rows."""
        return sum(self.slots.values())

    def forward(self, states: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """Mean log-probabilities per slot (logits of the ensemble's distribution)."""
        outs = [m(states, mask) for m in self.members]
        return {k: torch.stack([o[k].log_softmax(-1) for o in outs]).mean(0) for k in self.slots}

    def probabilities(self, states: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Every slot's value probabilities, one slot after another, ``(B, out_dim)``."""
        return torch.cat([v.softmax(-1) for v in self(states, mask).values()], -1)


def fit_ensemble(
    states: np.ndarray,
    mask: np.ndarray,
    labels: Mapping[str, Sequence[int]],
    slots: Mapping[str, int],
    members: int = 5,
    steps: int = 600,
    seed: int = 0,
    dropout: float = 0.0,
    **design: Any,
) -> ReaderEnsemble:
    """``members`` readers (:func:`fit_reader`, ``design``: its ``per_slot``, ``queries``,
    ``hidden`` and ``batch_size``), seeds ``1000 * seed + k``, as one."""
    return ReaderEnsemble(
        [
            fit_reader(states, mask, labels, slots, steps, 1000 * seed + k, dropout, **design)
            for k in range(members)
        ]
    )


class ReadingEncoder:
    """The frozen encoder's sentence vectors followed by a :class:`TokenReader`'s slot
    probabilities: a drop-in for :class:`~lcrl.text_encoder.FrozenTextEncoder` where
    instructions are embedded (``encode``, ``dim``).

    Args:
        encoder: the frozen text encoder.
        reader: a trained reader.
    """

    def __init__(self, encoder: Any, reader: TokenReader) -> None:
        self.encoder = encoder
        self.reader = reader
        self.dim = int(encoder.dim) + reader.out_dim
        self._cache: dict[str, np.ndarray] = {}

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """Rows of ``[sentence vector, slot probabilities]``, float32 ``(len(texts), dim)``."""
        items = list(texts)
        missing = [t for t in dict.fromkeys(items) if t not in self._cache]
        if missing:
            states, mask = self.encoder.encode_tokens(missing)
            with torch.no_grad():
                probs = self.reader.probabilities(torch.as_tensor(states), torch.as_tensor(mask))
            vectors = np.concatenate(
                [np.asarray(self.encoder.encode(missing), np.float32), probs.numpy()], 1
            )
            self._cache.update(zip(missing, vectors.astype(np.float32), strict=True))
        if not items:
            return np.zeros((0, self.dim), np.float32)
        return np.stack([self._cache[t] for t in items])

    def __getattr__(self, name: str) -> Any:
        # everything else (the model's name, its cache) is the encoder's
        return getattr(self.encoder, name)

    def state_dict(self) -> dict[str, Any]:
        """The reader's weights and slot sizes (what a checkpoint keeps)."""
        r = self.reader
        return {
            "slots": dict(r.slots),
            "queries": r.queries,
            "hidden": r.width,
            "per_slot": bool(r.per_slot),
            "members": len(r.members) if isinstance(r, ReaderEnsemble) else 0,
            "weights": {k: v.clone() for k, v in r.state_dict().items()},
        }

    @classmethod
    def from_state(cls, encoder: Any, state: Mapping[str, Any]) -> ReadingEncoder:
        """Rebuild from :meth:`state_dict`."""
        slots = {str(k): int(v) for k, v in state["slots"].items()}

        def one() -> TokenReader:
            return TokenReader(
                int(encoder.dim),
                slots,
                int(state.get("queries", 4)),
                int(state.get("hidden", 64)),
                bool(state.get("per_slot", False)),  # readers saved before it shared queries
            )

        members = int(state.get("members", 0))  # 0: a single reader
        reader: nn.Module = ReaderEnsemble([one() for _ in range(members)]) if members else one()
        reader.load_state_dict({k: torch.as_tensor(v) for k, v in state["weights"].items()})
        reader.eval()
        reader.requires_grad_(False)
        return cls(encoder, reader)
