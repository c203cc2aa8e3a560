"""Where training episodes start and which instructions they follow (``cfg.explore``).

Three aids for long-horizon manipulation, each off by default:

- **Chains** (``explore.chain``): an episode that achieved its instruction may go on in
  the same scene with a new one, as ``lcrl eval --chain`` does, instead of a reset. Each
  instruction is stored as an episode of its own, judged and captioned from the scene at
  the switch, so the policy learns to start from layouts other than reset layouts.
- **Hand-overs** (``explore.handover``): the scripted controller acts the first steps of
  some of the policy's episodes and the policy takes over from there, so its episodes
  start along demonstrations (a cube already held, a gripper next to its target), as
  resets to demonstration states do (Nair et al. 2018) without restoring simulator states.
- **A curriculum over families** (``explore.curriculum``): instructions come from the
  first family until the policy's live success on the family opened last reaches a
  threshold, then the next family opens.
- **Preludes** (``explore.prelude``): the env's scripted teacher first follows an
  instruction of another family (unstored), and the policy's episode starts in the scene
  it left, as the second instruction of a chain does: a run that trains one family learns
  to start from where the others leave the table.
- **Families drawn by failure** (``explore.family_weights failure``): among the open
  families, one is drawn with probability proportional to a floor plus the policy's live
  failure rate on it, so that mastered families give their share of the episodes to
  those still failing.

A run resumed from a checkpoint starts its environments from a reset: a chain in hand
when the checkpoint was written ends there.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from lcrl.errors import LcrlError
from train.configs.config import ExploreConfig
from train.environments.tasks import find_language_wrapper, switch_in_place


class Explorer:
    """The chains, hand-overs and curriculum of one run's training episodes.

    Args:
        cfg: the run's ``explore`` settings.
        families: the env's instruction families (``env.families``).
        rng: the generator of every draw (the trainer's scripted-controller stream, whose
            state checkpoints keep).
    """

    def __init__(
        self, cfg: ExploreConfig, families: Sequence[str], rng: np.random.Generator
    ) -> None:
        self.cfg = cfg
        self.rng = rng
        #: Per environment slot: the last observation and chain position of an episode
        #: whose scene the next one goes on in.
        self.pending: dict[int, tuple[dict[str, Any], int]] = {}
        self.opened = 1 if cfg.curriculum else 0
        #: Families the curriculum does not name: drawn from the start.
        self.others = tuple(f for f in families if f not in cfg.curriculum)
        self.weighted = cfg.family_weights == "failure"
        counted = families if self.weighted else cfg.curriculum
        self.recent: dict[str, deque[float]] = {
            f: deque(maxlen=cfg.curriculum_window) for f in counted
        }
        self.handovers = 0  # episodes the scripted controller began
        self.chained = 0  # episodes that began where the previous one ended
        self.preludes = 0  # episodes that began after a teacher's instruction
        self.prelude_successes = 0  # of those, the teacher's instruction succeeded
        self.prelude_steps = 0  # steps the teacher acted in preludes (not stored)
        #: The policy's own success on its last episodes that began after a prelude.
        self.prelude_recent: deque[float] = deque(maxlen=100)
        #: (step, family) of each family the curriculum opened after the first.
        self.openings: list[tuple[int, str]] = []

    # --- curriculum -------------------------------------------------------------------
    def families(self) -> tuple[str, ...]:
        """The families training instructions are drawn from now."""
        return (*self.cfg.curriculum[: self.opened], *self.others)

    def apply(self, envs: Sequence[Any]) -> None:
        """Make the training environments draw from :meth:`families`, with
        :meth:`weights` (a no-op with neither a curriculum nor family weights)."""
        if self.cfg.curriculum:
            for env in envs:
                find_language_wrapper(env).draw_from(self.families())
        self.reweigh(envs)

    def reweigh(self, envs: Sequence[Any]) -> None:
        """Give the training environments the current :meth:`weights` (a no-op without
        family weights)."""
        if not self.weighted:
            return
        weights = self.weights()
        for env in envs:
            find_language_wrapper(env).weigh_families(weights)

    def weights(self) -> dict[str, float]:
        """Each family's draw weight with ``family_weights failure``: the floor plus its
        live failure rate (1 for a family without counted episodes)."""
        floor = self.cfg.weight_floor
        return {f: floor + (1.0 - float(np.mean(w)) if w else 1.0) for f, w in self.recent.items()}

    def _judge(self, family: str, succeeded: bool, step: int) -> str | None:
        """Count a policy episode of ``family``; the family that opens, if one does."""
        cur = self.cfg.curriculum
        if family in self.recent:
            self.recent[family].append(float(succeeded))
        if not cur or self.opened >= len(cur) or family != cur[self.opened - 1]:
            return None
        window = self.recent[family]
        if len(window) < window.maxlen or np.mean(window) < self.cfg.curriculum_threshold:
            return None
        self.opened += 1
        self.openings.append((int(step), cur[self.opened - 1]))
        return cur[self.opened - 1]

    # --- episodes ---------------------------------------------------------------------
    def handover_steps(self) -> int:
        """Steps the scripted controller acts at the start of a policy episode (0: none)."""
        c = self.cfg
        if c.handover <= 0 or self.rng.random() >= c.handover:
            return 0
        self.handovers += 1
        return int(self.rng.integers(1, c.handover_steps + 1))

    def prelude_due(self) -> bool:
        """Whether the next policy episode from a reset begins with a prelude."""
        return self.cfg.prelude > 0 and self.rng.random() < self.cfg.prelude

    def continuation(self, slot: int, env: Any) -> tuple[dict[str, Any], int] | None:
        """The observation and chain position of the episode that goes on in ``env``'s
        scene, or None when it resets (no chain pending, or no instruction feasible)."""
        pending = self.pending.pop(slot, None)
        if pending is None:
            return None
        obs = switch_in_place(env, pending[0])
        if obs is None:
            return None
        self.chained += 1
        return obs, pending[1] + 1

    def finished(self, ep: Any, complete: bool, step: int) -> str | None:
        """An episode was stored: decide whether the next one in its environment goes on
        in its scene, and count it for the curriculum.

        Args:
            ep: the episode (``slot``, ``obs``, ``succeeded``, ``chain_index``,
                ``scripted``, ``handover``, ``family``).
            complete: it ended by success or its time limit (not by the step budget).
            step: the run's step count.

        Returns:
            The family the curriculum opens now, if one does.
        """
        c = self.cfg
        go_on = c.chain > 0 and complete and ep.succeeded and ep.chain_index + 1 < c.chain_length
        if go_on and self.rng.random() < c.chain:
            self.pending[ep.slot] = (ep.obs, ep.chain_index)
        if ep.scripted or ep.handover:
            return None
        if getattr(ep, "prelude", False):
            self.prelude_recent.append(float(ep.succeeded))
        return self._judge(ep.family, ep.succeeded, step)

    def drop_pending(self) -> None:
        """Forget the chains in hand (the environments are reset next)."""
        self.pending.clear()

    # --- checkpoints --------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "opened": self.opened,
            "recent": {f: list(v) for f, v in self.recent.items()},
            "handovers": self.handovers,
            "chained": self.chained,
            "preludes": [self.preludes, self.prelude_successes, self.prelude_steps],
            "prelude_recent": list(self.prelude_recent),
            "openings": [list(o) for o in self.openings],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        opened = int(state.get("opened", self.opened))
        if self.cfg.curriculum and not 1 <= opened <= len(self.cfg.curriculum):
            raise LcrlError(f"the checkpoint's curriculum opened {opened} families")
        self.opened = opened
        for f, values in state.get("recent", {}).items():
            if f in self.recent:
                self.recent[f].extend(float(v) for v in values)
        self.handovers = int(state.get("handovers", 0))
        self.chained = int(state.get("chained", 0))
        self.preludes, self.prelude_successes, self.prelude_steps = (
            int(x) for x in state.get("preludes", (0, 0, 0))
        )
        self.prelude_recent.clear()
        self.prelude_recent.extend(float(v) for v in state.get("prelude_recent", ()))
        self.openings = [(int(s), str(f)) for s, f in state.get("openings", [])]

    def columns(self) -> dict[str, float]:
        """progress.csv columns: episodes begun by the controller, episodes chained,
        families open and, with family weights, each family's weight."""
        out = {
            "handover_episodes": float(self.handovers),
            "chained_episodes": float(self.chained),
            "families_open": float(len(self.families())),
        }
        if self.cfg.prelude:
            out["prelude_episodes"] = float(self.preludes)
            out["prelude_success"] = self.prelude_successes / max(1, self.preludes)
            out["prelude_steps"] = float(self.prelude_steps)
            # the policy's success from where the preludes left the scene (last 100)
            recent = self.prelude_recent
            out["prelude_policy_success"] = float(np.mean(recent)) if recent else float("nan")
        if self.weighted:  # each family's draw weight
            out.update({f"weight_{f}": w for f, w in self.weights().items()})
        return out
