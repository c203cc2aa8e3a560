"""Sequential training over stages of instruction families (``sequential.stages``): the
trainer's part that ends a stage, measures every family (the success matrix and
forgetting), consolidates EWC and keeps the replay of earlier stages."""

from __future__ import annotations

from typing import Any

import numpy as np

from lcrl.errors import LcrlError
from train.configs.run_meta import restoring


class SequentialStages:
    """The stage methods of :class:`train.training.loop.Trainer` (a mixin: it reads the
    trainer's config, task, agent, buffer and counters)."""

    def _stage_labels(self) -> None:
        """Hindsight relabelling names the current stage's instructions only."""
        task = self.task
        if task.train_ids is None:
            raise LcrlError("sequential.stages need instructions (language goals or task ids)")
        families = set(self.stages[self.stage])
        parse = task.captioner.parse
        task.label_ids = {
            parse(t).text: i for t, i in task.train_ids.items() if parse(t).family in families
        }

    def _stage_end(self, stage: int) -> int:
        """The step at which a stage ends (``total_steps`` shared equally)."""
        n = len(self.stages)
        return int(np.ceil(self.cfg.total_steps * (stage + 1) / n))

    def _stage_row(self, after: str) -> None:
        """Evaluate every family (seen instructions) and add a row to the success matrix;
        write sequential.json and sequential.png."""
        from train.evaluation.evaluate import evaluate
        from train.evaluation.sequential import transfer_metrics, write

        cfg = self.cfg
        results = evaluate(
            self.agent, self.task, cfg, episodes=cfg.eval_episodes, seed=cfg.seed, sets=("train",)
        )
        fams = results["train"]["families"]
        families = list(cfg.env.families)
        row = {
            "after": after,
            "step": self.step,
            "success": {f: fams.get(f, 0.0) for f in families},
        }
        self.stage_rows.append(row)
        print(
            f"[sequential, after {after}] "
            + " ".join(f"{f} {row['success'][f]:.2f}" for f in families),
            flush=True,
        )
        matrix = [r["success"] for r in self.stage_rows]
        payload = {
            "stages": [list(s) for s in self.stages],
            "families": families,
            "replay": cfg.sequential.replay,
            "ewc": cfg.sequential.ewc,
            "rows": self.stage_rows,
            "metrics": transfer_metrics(matrix, self.stages),
        }
        self.out.mkdir(parents=True, exist_ok=True)
        write(self.out, payload)

    def next_stage(self) -> None:
        """End the current stage (evaluate every family, consolidate EWC, keep the replay
        memory) and start the next: an empty buffer (plus the replay memory), training
        environments and relabelling restricted to its families."""
        seq = self.cfg.sequential
        self._stage_row("+".join(self.stages[self.stage]))
        if self.agent.ewc is not None:
            self._consolidate()
        if seq.replay:
            self.memory.append(self._stage_episodes)
            self._stage_episodes = []
            share = seq.replay // len(self.memory)
            self.memory = [self._draw(eps, share) for eps in self.memory]
        self.stage += 1
        for env in self.envs:
            env.close()
        self.envs = self._make_envs(self.stage)
        self._stage_labels()
        self.buffer = self._new_buffer()
        for episode in (e for eps in self.memory for e in eps):
            self.buffer.add_episode(episode)
        print(
            f"[sequential] stage {self.stage + 1}/{len(self.stages)}: "
            f"{'+'.join(self.stages[self.stage])} from step {self.step}"
            + (f", {self.buffer.size} replayed transitions" if seq.replay else ""),
            flush=True,
        )

    def _draw(self, episodes: list[dict[str, Any]], budget: int) -> list[dict[str, Any]]:
        """Episodes drawn at random (in their order) while their steps fit ``budget``."""
        kept, used = [], 0
        for i in self.memory_rng.permutation(len(episodes)):
            n = len(episodes[i]["action"])
            if used + n <= budget:
                kept.append(int(i))
                used += n
        return [episodes[i] for i in sorted(kept)]

    def _consolidate(self) -> None:
        """EWC at the end of a stage: the diagonal Fisher information of the critic and
        actor (of their losses, or with ``sequential.ewc_fisher=output`` of their outputs),
        from ``sequential.ewc_samples`` transitions of the stage's data, each one's
        gradient squared on its own."""
        import torch

        from lcrl.buffer import batch_rows

        sums: dict[str, torch.Tensor] = {}
        n = self.cfg.sequential.ewc_samples
        batch = self.buffer.sample(n)
        gradients = (
            self.agent.output_gradients
            if self.cfg.sequential.ewc_fisher == "output"
            else self.agent.loss_gradients
        )
        for i in range(n):
            for name, g in gradients(batch_rows(batch, [i])).items():
                sums[name] = sums.get(name, 0.0) + g * g
        for name, params in self.agent.flat_parameters().items():
            self.agent.ewc.consolidate(name, params, sums[name] / n)

    def _restore_stage(self, ckpt: Any) -> None:
        """The stage, the matrix so far and the EWC state of a checkpoint."""
        with restoring(ckpt, "the state 'sequential'"):
            state = ckpt.state("sequential")
            self.stage, self.stage_rows = int(state["stage"]), list(state["rows"])
        if self.stage > 0 and self.cfg.sequential.replay:
            raise LcrlError(
                "--resume of a sequential run with replay after its first stage is not "
                "supported: the replay memory of earlier stages is not saved"
            )
        if self.agent.ewc is not None and ckpt.has_state("ewc"):
            with restoring(ckpt, "the state 'ewc'"):
                self.agent.ewc.load_state_dict(ckpt.state("ewc"))
        for env in self.envs:
            env.close()
        self.envs = self._make_envs(self.stage)
        self._stage_labels()

    @property
    def _last_episodes(self) -> list[dict[str, Any]]:
        return getattr(self, "_just_stored", [])
