"""A captioner and reward model factored by the grammar's slots (``--model.head factored``).

The sequence captioner writes an instruction word by word from features pooled over the
scene, and its reward model reads the instruction's text embedding: both learn each
combination of colour, shape and family they are shown, and read a new combination of
known words poorly. The policy's object slots showed the way out: what a predicate
means should not depend on which object it is about.

:class:`SlotPredicates` reads perception's estimated object slots of the episode's first
frame and the current one and scores every instruction the grammar can form:

* a **unary** network, shared by every object slot, scores the predicates of one object:
  ``reach``, ``push`` in each of the four directions and ``lift``;
* a **pair** network, shared by every ordered pair of slots, scores the predicates of
  two: ``put`` in each of the four relations and ``stack``.

A slot's inputs are the object's presence, its position relative to the gripper, its
displacement since the first frame, its position, its shape (a one-hot) and the robot's
proprioception; a pair adds the offset between the two objects now and in the first
frame. The colour enters nowhere: slot ``k`` *is* the object
``OBJECT_KINDS[k]`` (perception estimates every kind in its own slot), so "push the red
cylinder left" is the unary network's "push left" on the red cylinder's slot, whether or
not that combination was ever a training label. Absent objects score nothing.

Each output gives two numbers:

* a **reward logit**: the probability that the instruction is satisfied, an independent
  sigmoid (trained on positives and negatives weighted equally);
* a **caption score**: the captioner is a softmax over every output and ``<none>`` (a
  learned score), trained with the cross-entropy of one achieved instruction, or
  ``<none>``. Instructions that are not training targets (the split's held-out
  combinations) are left out of the softmax in training, so they are never pushed down.

An instruction is any text the grammar parses (:func:`instruction_index`); the output
table covers every family of both tabletops, and an instruction that the dataset never
names simply never receives a target.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from captioner.grammar import DIRECTIONS, RELATIONS, Instruction, try_parse
from captioner.learned.models import split_slots
from envs.scene import OBJECT_KINDS, SHAPES
from lcrl.errors import LcrlError
from lcrl.perception import Perception

#: Predicates of one object: (family, direction).
UNARY: tuple[tuple[str, str | None], ...] = (
    ("reach", None),
    *(("push", d) for d in DIRECTIONS),
    ("lift", None),
)
#: Predicates of an ordered pair of objects: (family, relation).
PAIR: tuple[tuple[str, str | None], ...] = (*(("put", r) for r in RELATIONS), ("stack", None))


def _mlp(inp: int, width: int, out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inp, width),
        nn.LayerNorm(width),
        nn.ReLU(),
        nn.Linear(width, width),
        nn.ReLU(),
        nn.Linear(width, out),
    )


class SlotPredicates(nn.Module):
    """Estimated object slots of (first, current) frames -> a reward logit and a caption
    score per instruction of the grammar (see the module's text).

    Args:
        perception: the frozen perception model (kept outside this module's parameters:
            the checkpoint saves it once, as ``perception``).
        proprio_dim: proprioception values per frame (standardised before they come in).
        hidden: width of both networks.
        use_proprio: read the proprioception at both frames.
    """

    kind = "perception"
    #: The smallest spread an input is divided by (see :class:`SlotPairEncoder`).
    MIN_STD = 0.02

    def __init__(
        self, perception: Perception, proprio_dim: int, hidden: int = 256, use_proprio: bool = True
    ) -> None:
        super().__init__()
        self._perception = [perception]
        for param in perception.parameters():
            param.requires_grad_(False)
        self.layout = lay = perception.layout
        if lay.count > len(OBJECT_KINDS):
            raise LcrlError(
                f"perception estimates {lay.count} object slots; the grammar names "
                f"{len(OBJECT_KINDS)} object kinds"
            )
        d, k = lay.position_dims, lay.count
        self.proprio_dim = proprio_dim if use_proprio else 0
        self.slot_dim = 1 + 3 * d  # presence, relative position, displacement, position
        shapes = torch.zeros(k, len(SHAPES))
        for i in range(k):
            shapes[i, SHAPES.index(OBJECT_KINDS[i][1])] = 1.0
        self.register_buffer("shapes", shapes)
        self.register_buffer("feat_mean", torch.zeros(self.slot_dim))
        self.register_buffer("feat_std", torch.ones(self.slot_dim))
        self.register_buffer("pair_mean", torch.zeros(2 * d))
        self.register_buffer("pair_std", torch.ones(2 * d))
        pairs = [(i, j) for i in range(k) for j in range(k) if i != j]
        self.register_buffer("pair_i", torch.as_tensor([i for i, _ in pairs]))
        self.register_buffer("pair_j", torch.as_tensor([j for _, j in pairs]))
        own = self.slot_dim + len(SHAPES)
        self.unary = _mlp(own + 2 * self.proprio_dim, hidden, 2 * len(UNARY))
        self.pair = _mlp(2 * own + 2 * d + 2 * self.proprio_dim, hidden, 2 * len(PAIR))
        self.none_score = nn.Parameter(torch.zeros(()))
        self.num_unary = k * len(UNARY)
        self.num_outputs = self.num_unary + len(pairs) * len(PAIR)

    @property
    def perception(self) -> Perception:
        """The frozen perception model."""
        return self._perception[0]

    # -- inputs
    def _raw(
        self, first: torch.Tensor, current: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-slot inputs ``(B, K, 1 + 3d)``, pair offsets now and at the first frame
        ``(B, P, 2d)``, and presence ``(B, K)``, all unstandardised."""
        _, pos0, on0 = split_slots(first.float(), self.layout)
        g, pos, on = split_slots(current.float(), self.layout)
        both = on * on0
        rel = (pos - g[:, None]) * on[..., None]
        disp = (pos - pos0) * both[..., None]
        x = torch.cat([on[..., None], rel, disp, pos * on[..., None]], -1)
        offset = pos[:, self.pair_i] - pos[:, self.pair_j]
        offset0 = pos0[:, self.pair_i] - pos0[:, self.pair_j]
        pair = torch.cat([offset, offset0], -1)
        return x, pair, on > 0.5, both > 0.5

    def fit(self, first: torch.Tensor, current: torch.Tensor) -> None:
        """Standardise the inputs with their mean and spread over the slots (and pairs)
        that hold an object in these frame pairs."""
        x, pair, on, both = self._raw(first, current)
        xs = x[on]
        self.feat_mean.copy_(xs.mean(0))
        self.feat_std.copy_(xs.std(0).clamp_min(self.MIN_STD))
        ok = both[:, self.pair_i] & both[:, self.pair_j]
        if bool(ok.any()):
            ps = pair[ok]
            self.pair_mean.copy_(ps.mean(0))
            self.pair_std.copy_(ps.std(0).clamp_min(self.MIN_STD))

    # -- outputs
    def forward(
        self, first: torch.Tensor, current: torch.Tensor, p0: torch.Tensor, p: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(reward logits, caption scores)``, each ``(B, num_outputs)``; outputs about an
        absent object are -1e4."""
        x, pair, on, _ = self._raw(first, current)
        b, k = on.shape
        own = torch.cat(
            [(x - self.feat_mean) / self.feat_std, self.shapes.expand(b, -1, -1)], -1
        )  # (B, K, own)
        extra = [p0, p] if self.proprio_dim else []
        u_in = torch.cat([own, *(e[:, None].expand(-1, k, -1) for e in extra)], -1)
        u = self.unary(u_in).view(b, k, 2, len(UNARY))
        n_pairs = self.pair_i.shape[0]
        p_in = torch.cat(
            [
                own[:, self.pair_i],
                own[:, self.pair_j],
                (pair - self.pair_mean) / self.pair_std,
                *(e[:, None].expand(-1, n_pairs, -1) for e in extra),
            ],
            -1,
        )
        v = self.pair(p_in).view(b, n_pairs, 2, len(PAIR))
        reward = torch.cat([u[:, :, 0].reshape(b, -1), v[:, :, 0].reshape(b, -1)], 1)
        caption = torch.cat([u[:, :, 1].reshape(b, -1), v[:, :, 1].reshape(b, -1)], 1)
        present = torch.cat(
            [
                on[..., None].expand(-1, -1, len(UNARY)).reshape(b, -1),
                (on[:, self.pair_i] & on[:, self.pair_j])[..., None]
                .expand(-1, -1, len(PAIR))
                .reshape(b, -1),
            ],
            1,
        )
        return reward.masked_fill(~present, -1e4), caption.masked_fill(~present, -1e4)


def output_index(ins: Instruction, count: int) -> int | None:
    """The output of :class:`SlotPredicates` (over ``count`` object slots) that scores an
    instruction; None where the scene has no slot for one of its objects."""
    i = OBJECT_KINDS.index(ins.obj)
    if i >= count:
        return None
    if ins.family in ("put", "stack"):
        assert ins.target is not None
        j = OBJECT_KINDS.index(ins.target)
        if j >= count:
            return None
        pair = i * (count - 1) + (j if j < i else j - 1)
        return count * len(UNARY) + pair * len(PAIR) + PAIR.index((ins.family, ins.relation))
    return i * len(UNARY) + UNARY.index((ins.family, ins.direction))


def output_objects(index: int, count: int) -> tuple[int, ...]:
    """The object slots output ``index`` is about (one or two)."""
    if index < count * len(UNARY):
        return (index // len(UNARY),)
    pair = (index - count * len(UNARY)) // len(PAIR)
    i, r = divmod(pair, count - 1)
    return (i, r if r < i else r + 1)


def instruction_index(text: str, count: int) -> int:
    """The output scoring any phrasing the grammar parses.

    Raises:
        LcrlError: text the grammar does not parse, or about an object without a slot.
    """
    ins = try_parse(text)
    if ins is None:
        raise LcrlError(
            f"the factored models read instructions of the grammar; {text!r} does not parse "
            "(lcrl caption eval takes the dataset's instructions; lcrl act --canonical-reader "
            "maps free text onto them)"
        )
    index = output_index(ins, count)
    if index is None:
        raise LcrlError(f"{text!r} names an object this scene has no slot for")
    return index


def output_indices(texts: Sequence[str], count: int) -> np.ndarray:
    """:func:`instruction_index` of each text."""
    return np.asarray([instruction_index(t, count) for t in texts], np.int64)


def factored_loss(
    model: SlotPredicates,
    inputs: tuple[torch.Tensor, ...],
    targets: torch.Tensor,
    caption_target: torch.Tensor,
    trainable: torch.Tensor,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The training loss of a batch.

    Args:
        inputs: ``(first, current, p0, p)`` as :meth:`SlotPredicates.forward` takes them.
        targets: ``(B, num_outputs)`` 1 where the observation achieved the output's
            instruction.
        caption_target: ``(B,)`` the output the captioner should say, ``num_outputs`` for
            ``<none>``.
        trainable: ``(num_outputs,)`` the outputs that are training instructions (the
            others enter neither loss).
    """
    reward, caption = model(*inputs)
    bce = F.binary_cross_entropy_with_logits(reward, targets, reduction="none")
    valid = trainable[None].expand_as(targets) & (reward > -1e3)
    pos = valid & (targets > 0.5)
    neg = valid & (targets < 0.5)
    r_loss = (bce * pos).sum() / pos.sum().clamp_min(1) + (bce * neg).sum() / neg.sum().clamp_min(1)
    scores = caption.masked_fill(~trainable[None], -1e4)
    scores = torch.cat([scores, model.none_score.expand(scores.shape[0], 1)], 1)
    c_loss = F.cross_entropy(scores, caption_target)
    loss = r_loss + c_loss
    return loss, {"reward": float(r_loss.detach()), "caption": float(c_loss.detach())}


def train_factored(
    model: SlotPredicates,
    pairs: Any,
    sampler: Any,
    table: Sequence[Instruction],
    seen: np.ndarray,
    steps: int,
    batch_size: int,
    lr: float,
    none_fraction: float,
    near_fraction: float,
    device: torch.device,
    progress: bool = True,
) -> list[float]:
    """Train :class:`SlotPredicates` on a caption dataset's training pairs.

    Args:
        pairs, sampler: the dataset's frame pairs (perception's estimates) and the
            sampler of training observations (:mod:`captioner.learned.data`).
        table: the dataset's instructions (ids as in its labels).
        seen: ``(len(table),)`` which instructions are training targets.
    Returns:
        The loss at every step.
    """
    from tqdm import tqdm

    count = model.layout.count
    where = np.asarray(
        [-1 if (i := output_index(ins, count)) is None else i for ins in table], np.int64
    )
    trainable = torch.zeros(model.num_outputs, dtype=torch.bool)
    trainable[torch.as_tensor(where[(where >= 0) & seen])] = True
    trainable = trainable.to(device)
    opt = torch.optim.Adam([q for q in model.parameters() if q.requires_grad], lr)
    losses: list[float] = []
    bar = tqdm(range(steps), disable=not progress, desc="factored")
    for _ in bar:
        idx, said = sampler.caption_batch(batch_size, none_fraction, near_fraction)
        targets = np.zeros((len(idx), model.num_outputs), np.float32)
        caption = np.full(len(idx), model.num_outputs, np.int64)
        for r, (j, t) in enumerate(zip(idx, said, strict=True)):
            out = where[sampler.labels(int(j))]
            targets[r, out[out >= 0]] = 1.0
            if t is not None and where[t] >= 0:
                caption[r] = where[t]
        loss, _ = factored_loss(
            model,
            pairs.tensors(idx, device),
            torch.as_tensor(targets, device=device),
            torch.as_tensor(caption, device=device),
            trainable,
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
        bar.set_postfix_str(f"loss {np.mean(losses[-50:]):.3f}", refresh=False)
    return losses
