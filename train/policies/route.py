"""Experts routed by instruction family: one policy made of runs trained apart.

``lcrl route OUT --base RUN --expert put=RUN_PUT --expert stack=RUN_STACK`` writes a
checkpoint folder that acts like any other (``lcrl eval``, ``lcrl act``, :func:`lcrl.load`,
a teacher of ``lcrl distill``). Every instruction goes to the expert of its family, the
others to the base run. The family is that of the base run's nearest training
instruction (cosine similarity of the frozen text encoder's embeddings), so held-out
combinations, paraphrases and free text are routed as well as the encoder places them.
Routing is decided per call and per row: in a chain, the second instruction goes to its
own expert from the scene the first one left.

The folder is a copy of the base checkpoint (its weights, config and instruction table;
the replay buffer is left out) with the experts' copies under ``experts/FAMILY`` and the
routing table in its ``meta.json`` (``router``). Every expert reads the same observation
features, goal embeddings and actions as the base (checked when the folder is written).
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
from train.policies.ensemble import ENSEMBLE, ensembled

#: The key of a routed checkpoint's ``meta.json`` that lists its experts.
ROUTER = "router"
#: Where the experts' checkpoints are, inside a routed checkpoint folder.
EXPERTS_DIR = "experts"


class RoutedAgent:
    """Acts like an :class:`lcrl.algos.base.Agent`, each row by the expert of its family.

    Args:
        base: the base policy (a ``train.evaluation.evaluate.LoadedPolicy``): its training
            instructions and their families are the routing table; it acts for the
            families without an expert.
        experts: ``{family: LoadedPolicy}``.
    """

    def __init__(
        self, base: Any, experts: Mapping[str, Any], families: Sequence[str] | None = None
    ) -> None:
        from train.environments.tasks import find_language_wrapper
        from train.evaluation.eval_suite import goal_vectors

        self.base_agent, self.task, self.experts = base.agent, base.task, dict(experts)
        split = find_language_wrapper(base.env).split
        # the families it was trained on, also when the env is narrowed to fewer
        # (lcrl eval --families): routing then still chooses among all of them
        known = set(families or base.cfg.env.families)
        rows = [
            (t, m.family)
            for t, m in zip(split.texts("train"), split.instructions("train"), strict=True)
            if m.family in known
        ]
        if not rows:
            raise LcrlError("the base policy has no training instructions to route by")
        self.texts = [t for t, _ in rows]
        self.families = [f for _, f in rows]
        vectors = goal_vectors(base.task, self.texts)  # its table's rows, else the encoder's
        table = np.stack([vectors[t] for t in self.texts]).astype(np.float32)
        self._table = table / np.maximum(np.linalg.norm(table, axis=1, keepdims=True), 1e-8)

    def __getattr__(self, name: str) -> Any:
        # device, problem, modules() ...: those of the base agent
        if name == "base_agent":
            raise AttributeError(name)
        return getattr(self.base_agent, name)

    def route(self, vectors: np.ndarray) -> list[str]:
        """The family each goal embedding ``(B, d)`` is routed by."""
        v = np.asarray(vectors, np.float32).reshape(len(vectors), -1)
        v = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-8)
        return [self.families[i] for i in (v @ self._table.T).argmax(1)]

    def expert_of(self, family: str) -> str:
        """``family``'s expert, or ``base``."""
        return family if family in self.experts else "base"

    def act(
        self,
        obs: Mapping[str, np.ndarray],
        goal: Any,
        deterministic: bool = False,
        embedded: bool = False,
    ) -> np.ndarray:
        """Actions for a batch: each row by the expert of its goal's family."""
        vectors = np.asarray(goal if embedded else self.task.embed_goals(goal), np.float32)
        owners = [self.expert_of(f) for f in self.route(vectors)]
        out: np.ndarray | None = None
        for owner in dict.fromkeys(owners):
            rows = np.asarray([i for i, o in enumerate(owners) if o == owner])
            agent = self.base_agent if owner == "base" else self.experts[owner].agent
            part = {k: np.asarray(v)[rows] for k, v in obs.items()}
            a = np.asarray(
                agent.act(part, vectors[rows], deterministic=deterministic, embedded=True)
            )
            if out is None:
                out = np.zeros((len(owners), *a.shape[1:]), a.dtype)
            out[rows] = a
        assert out is not None
        return out


def expert_entries(entries: Sequence[str]) -> dict[str, str]:
    """``FAMILY=RUN`` entries as ``{family: run}``, one line per mistake."""
    from train.configs.config import family_teachers

    return family_teachers(entries, "an expert", "experts")


def _check_language(policy: Any, who: str) -> None:
    """Refuse a policy without language goals, or one that is itself routed."""
    if policy.task.query != "text":
        raise LcrlError(
            f"{who} was not trained with language goals ({policy.cfg.env.goal_type} goals): "
            "routing goes by instruction"
        )
    if ROUTER in policy.checkpoint.meta:
        raise LcrlError(f"{who} is itself routed: name the runs it is made of instead")


def check_expert(base: Any, family: str, expert: Any, where: str) -> None:
    """Refuse an expert that cannot stand in for ``base`` on ``family``, naming both."""
    _check_language(expert, f"the expert {where}")
    if family not in expert.cfg.env.families:
        raise LcrlError(
            f"the expert {where} for {family!r} was trained on the families "
            f"{', '.join(expert.cfg.env.families)}, not {family}"
        )
    check_same_inputs(
        expert, f"the expert {where}", base, f"the base {base.checkpoint.path}", "experts"
    )


def write_router(
    out: str | Path, base_run: str, experts: Mapping[str, str], overwrite: bool = False
) -> Path:
    """Write the routed checkpoint folder ``out`` (see the module's docstring).

    Raises:
        LcrlError: ``out`` exists (without ``overwrite``), no experts, a family the base
            env lacks, or an expert that cannot stand in for the base
            (:func:`check_expert`).
    """
    out = Path(out)
    if not experts:
        raise LcrlError("name at least one expert: --expert FAMILY=RUN")
    if out.exists() and not overwrite:
        raise LcrlError(f"{out} already exists: choose another folder or pass --overwrite")
    base_path = resolve_checkpoint(base_run)
    base = load_member(base_path)
    _check_language(base, f"the base {base_path}")
    paths: dict[str, Path] = {}
    for family, run in experts.items():
        if family not in base.cfg.env.families:
            raise LcrlError(
                f"--expert {family}=...: the base {base_path} follows the families "
                f"{', '.join(base.cfg.env.families)}, not {family}"
            )
        paths[family] = resolve_checkpoint(run)
        expert = load_member(paths[family])
        check_expert(base, family, expert, str(paths[family]))
        expert.env.close()
    base.env.close()
    meta = {
        "base": str(base_path),
        "experts": {f: f"{EXPERTS_DIR}/{f}" for f in paths},
        "sources": {f: str(p) for f, p in paths.items()},
    }
    parts = {f"{EXPERTS_DIR}/{f}": p for f, p in paths.items()}
    return write_composite(out, base_path, parts, ROUTER, meta)


def routed(loaded: Any, device: str | None = None) -> Any:
    """``loaded`` (a LoadedPolicy of a routed folder's base) acting through its experts."""
    entry = loaded.checkpoint.meta[ROUTER]
    experts = {}
    for family, rel in dict(entry.get("experts", {})).items():
        path = Path(loaded.checkpoint.path) / rel
        if not (path / META_FILE).is_file():
            raise LcrlError(f"the routed checkpoint {loaded.checkpoint.path} lacks {path}")
        experts[family] = load_member(path, device=device)
    saved = loaded.checkpoint.meta.get("config", {}).get("env", {}).get("families")
    loaded.agent = RoutedAgent(loaded, experts, saved)
    return loaded


def load_member(path: str | Path, device: str | None = None) -> Any:
    """The base or an expert of a router: one run's policy, or an ensemble's mean."""
    loaded = load_single(path, device=device)
    return ensembled(loaded, device) if ENSEMBLE in loaded.checkpoint.meta else loaded
