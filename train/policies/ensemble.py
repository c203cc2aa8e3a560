"""Policies trained apart acting as one: the mean of their actions.

``lcrl ensemble OUT RUN RUN [RUN ...]`` writes a checkpoint folder that acts like any other
(``lcrl eval``, ``lcrl act``, :func:`lcrl.load`, a teacher of ``lcrl distill``). Each row's
action is the mean of the members' actions for it (their means when acting
deterministically, their samples otherwise): students distilled with other seeds err on
different episodes, and their mean errs less often than each.

The folder is a copy of the first member's checkpoint (its weights, config, instruction
table and, for a camera student, the perception model it acts through; the replay buffer
is left out) with the other members' copies under ``members/I`` and their list in its
``meta.json`` (``ensemble``). Every member reads the same observation features, goal
embeddings and actions, with the same perception model held the same way (checked when the
folder is written): the env shows every member one observation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lcrl.checkpoint import META_FILE
from lcrl.errors import LcrlError
from train.evaluation.evaluate import load_single, resolve_checkpoint
from train.policies.composite import check_same_inputs, write_composite

#: The key of an ensemble checkpoint's ``meta.json`` that lists its other members.
ENSEMBLE = "ensemble"
#: Where the other members' checkpoints are, inside an ensemble checkpoint folder.
MEMBERS_DIR = "members"


class EnsembleAgent:
    """Acts like an :class:`lcrl.algos.base.Agent`: the mean of its members' actions.

    Args:
        agents: the members' agents (the first one's attributes stand for the ensemble's).
    """

    def __init__(self, agents: Sequence[Any]) -> None:
        if len(agents) < 2:
            raise LcrlError("an ensemble needs at least two members")
        self.members = list(agents)

    def __getattr__(self, name: str) -> Any:
        # device, problem, modules() ...: those of the first member
        if name == "members":
            raise AttributeError(name)
        return getattr(self.members[0], name)

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: Any,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """The mean of the members' actions for a batch."""
        acts = [
            np.asarray(a.act(obs, goal, deterministic=deterministic, embedded=embedded))
            for a in self.members
        ]
        return np.mean(acts, axis=0).astype(acts[0].dtype)


def _reading(policy: Any) -> tuple[dict[str, np.ndarray], float] | None:
    """The perception model a policy acts through, as arrays, and the radius it holds
    objects at (None: it reads the simulator's state); the model is loaded once."""
    if not policy.cfg.env.perception:
        return None
    from lcrl.perception import load_model

    model, _ = load_model(policy.cfg.env.perception)
    radius = policy.cfg.env.perception_hold_radius
    weights = {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}
    return weights, model.cfg.hold_radius if radius is None else radius


def check_plain(member: Any, where: str) -> None:
    """Refuse a member that is itself made of others."""
    if ENSEMBLE in member.checkpoint.meta or "router" in member.checkpoint.meta:
        raise LcrlError(
            f"the member {where} is itself an ensemble or routed: name plain runs instead"
        )


def check_member(first: Any, member: Any, where: str) -> None:
    """Refuse a member that cannot act beside ``first``, naming both."""
    here = str(first.checkpoint.path)
    check_plain(member, where)
    check_same_inputs(member, f"the member {where}", first, here, "members")
    if member.task.problem().discrete:
        raise LcrlError(
            f"the member {where} has discrete actions: an ensemble averages continuous ones"
        )
    mine, theirs = _reading(first), _reading(member)
    same = (mine is None) == (theirs is None) and (
        mine is None
        or (
            mine[0].keys() == theirs[0].keys()
            and all(np.array_equal(mine[0][k], theirs[0][k]) for k in mine[0])
            and mine[1] == theirs[1]
        )
    )
    if not same:

        def how(p: Any, reading: tuple[dict, float] | None) -> str:
            if reading is None:
                return "the simulator's state"
            source = p.checkpoint.meta.get("perception", {}).get("source", "?")
            return f"perception from {source} held at {reading[1]}"

        raise LcrlError(
            f"the member {where} acts through {how(member, theirs)}, {here} through "
            f"{how(first, mine)}: members must read one estimate (the same perception model, "
            "held the same way)"
        )


def write_ensemble(out: str | Path, runs: Sequence[str], overwrite: bool = False) -> Path:
    """Write the ensemble checkpoint folder ``out`` (see the module's docstring).

    Raises:
        LcrlError: fewer than two members, ``out`` exists (without ``overwrite``) or holds
            a member, or a member that cannot act beside the first (:func:`check_member`).
    """
    out = Path(out)
    if len(runs) < 2:
        raise LcrlError(f"name at least two runs to average, got {len(runs)}")
    if out.exists() and not overwrite:
        raise LcrlError(f"{out} already exists: choose another folder or pass --overwrite")
    paths = [resolve_checkpoint(r) for r in runs]
    if len({Path(p).resolve() for p in paths}) < len(paths):
        raise LcrlError("a run is named twice: its mean with itself is itself")
    policies = [load_single(p) for p in paths]
    try:
        check_plain(policies[0], str(paths[0]))
        for path, member in zip(paths[1:], policies[1:], strict=True):
            check_member(policies[0], member, str(path))
    finally:
        for p in policies:
            p.env.close()
    entry = {
        "members": [f"{MEMBERS_DIR}/{i}" for i in range(1, len(paths))],
        "sources": [str(p) for p in paths],
    }
    parts = {f"{MEMBERS_DIR}/{i}": p for i, p in enumerate(paths[1:], start=1)}
    return write_composite(out, paths[0], parts, ENSEMBLE, entry)


def ensembled(loaded: Any, device: str | None = None) -> Any:
    """``loaded`` (a LoadedPolicy of an ensemble folder's first member) acting as the mean
    of all its members."""
    entry: Mapping[str, Any] = loaded.checkpoint.meta[ENSEMBLE]
    agents = [loaded.agent]
    for rel in entry.get("members", []):
        path = Path(loaded.checkpoint.path) / rel
        if not (path / META_FILE).is_file():
            raise LcrlError(f"the ensemble checkpoint {loaded.checkpoint.path} lacks {path}")
        member = load_single(path, device=device)
        member.env.close()
        agents.append(member.agent)
    loaded.agent = EnsembleAgent(agents)
    return loaded
