"""How the online trainer collects episodes: from its own environments stepped together
(one batched forward pass per step, updates between steps) or from Ray rollout workers;
each finished episode labelled and stored whole."""

from __future__ import annotations

from typing import Any

import numpy as np

from train.environments.simulators import env_spec
from train.environments.tasks import (
    ScriptedActor,
    find_language_wrapper,
    switch_in_place,
)
from train.training.episodes import (
    Episode,
    begin_episode,
    episode_record,
    start_episode,
    step_episode,
)


class Collection:
    """The collection methods of :class:`train.training.loop.Trainer` (a mixin: it reads
    the trainer's config, environments, task, agent, buffer and counters)."""

    # --- Ray rollout workers
    #: The Ray actors (``collect.backend ray``), started by the first :meth:`advance`.
    remote: Any = None

    def _weights(self) -> dict[str, Any]:
        """The learner's weights for the workers' policy copies (CPU tensors)."""
        return {
            name: {k: v.detach().cpu() for k, v in module.state_dict().items()}
            for name, module in self.agent.modules().items()
        }

    def start_workers(self) -> None:
        """Start the Ray rollout workers with the learner's weights and instruction table
        (before the loop installs its SIGINT and SIGTERM handlers, which then take
        precedence over those Ray installs)."""
        from train.training.ray_collect import RayCollector

        table = self.task.table
        embeddings = self.task.embeddings if table is not None else None
        table = (list(table), self.task.num_train) if table is not None else None
        self.remote = RayCollector(self.cfg, table, self._weights(), embeddings)
        self._issued = self.episodes
        self._synced = self.agent.updates

    def collect_remote(self) -> None:
        """Keep every Ray worker collecting; take the first episode one returns, run the
        updates due for its steps, then store it (a stop during the updates drops it
        whole), and sync the workers' weights every ``collect.sync_every`` updates."""
        cfg = self.cfg
        if self.remote is None:
            self.start_workers()
        for slot in self.remote.idle():
            task_id = self.sampler.sample(self.task_rng) if self.sampler is not None else None
            self.remote.submit(slot, self._issued, self.step < cfg.learning_starts, task_id)
            self._issued += 1
        _, result = self.remote.next()
        if result is None:  # a worker died: its episode is dropped, the worker replaced
            return
        self._start = self.snapshot()
        episode = result["episode"]  # arrays from Ray's object store are read-only
        episode["obs"] = {k: np.array(v) for k, v in episode["obs"].items()}
        self.step += result["steps"]
        self._update(self._updates_due(result["steps"]))
        with self.holding_signals():  # the episode is stored whole, or not at all
            self.buffer.add_episode(episode)
            self.agent.observe(episode["obs"], episode.get("achieved_goal"))
            info = {"sim_error": result["sim_error"]}
            self._finish_episode(result["scripted"], result["succeeded"], result["task_id"], info)
            self._start = None
        if self.agent.updates - self._synced >= cfg.collect.sync_every:
            self.remote.sync(self._weights())
            self._synced = self.agent.updates

    def collect_episode(self) -> None:
        """Run one episode in each training environment (acting, stepping, updating) and
        store them in the buffer in the order of their episode index.

        The environments step together; the policy acts for all of them in one batched
        forward pass and ``updates_per_step`` updates follow every environment step. An
        episode's reset seed, whether the scripted controller acts it, and its random and
        scripted actions depend only on its index, so one environment and several store
        the same episodes while the policy has not learned. The state at the start is kept
        in memory (:meth:`snapshot`) until the episodes are stored: a run stopped in
        between goes back to it (:meth:`rollback`), so its checkpoint, resumed, collects
        the same episodes with the same updates."""
        self._start = self.snapshot()
        self._just_stored: list[dict[str, Any]] = []
        cfg = self.cfg
        episodes = [self._begin(i, env) for i, env in enumerate(self.envs)]
        active = list(episodes)
        while active:
            if self.step < cfg.learning_starts:
                for ep in active:
                    if not ep.scripted_now and ep.t % cfg.random_action_repeat == 0:
                        ep.random_action = self.task.random_action(ep.rng)
            acting = [
                ep for ep in active if not ep.scripted_now and self.step >= cfg.learning_starts
            ]
            if acting:
                last = [ep.stored[-1] for ep in acting]
                obs = {k: np.stack([o[k] for o in last]) for k in last[0]}
                actions = self.agent.act(obs, np.asarray([ep.goal for ep in acting]))
                for ep, a in zip(acting, actions, strict=True):
                    ep.action = a
            for ep in active:
                if ep.scripted_now:
                    ep.action = self.scripted[ep.slot].act(ep.env, ep.scripted_rng)
                elif self.step < cfg.learning_starts:
                    ep.action = ep.random_action
                self._step(ep)
            self._end_learned(active)
            self.step += len(active)
            self._update(self._updates_due(len(active)))
            active = [ep for ep in active if not ep.done]
            if active and self.step >= cfg.total_steps:
                break  # the budget ends mid-episode: store what was collected
        with self.holding_signals():  # the episodes are stored whole, or not at all
            for ep in episodes:
                self._store(ep)
                self._finish_episode(
                    ep.scripted, ep.succeeded, ep.task_id, ep.info, handover=bool(ep.handover)
                )
                if self.explorer is not None:
                    self._explored(ep)
            self._start = None

    def _begin(self, slot: int, env: Any) -> Episode:
        """Reset ``env`` for the next episode (index ``self.episodes + slot``), with the
        task the sampler draws when the run has a task set; with ``explore``, go on in
        the scene of a chained episode instead, and draw a hand-over."""
        task_id = None
        if self.sampler is not None:
            task_id = self.sampler.sample(self.task_rng)
        scripted = self.scripted[slot] if self.scripted else None
        chained = self.explorer.continuation(slot, env) if self.explorer is not None else None
        if chained is not None:
            obs, index = chained
            ep = start_episode(
                self.cfg, self.task, env, obs, {}, scripted, self.rng, self.scripted_rng
            )
            ep.chain_index = index
        else:
            ep = begin_episode(
                self.cfg,
                self.task,
                env,
                self.episodes + slot,
                scripted,
                task_id,
                rng=self.rng,
                scripted_rng=self.scripted_rng,
            )
            if self.explorer is not None and not ep.scripted and self.explorer.prelude_due():
                after = self._prelude(env, ep.obs)
                if after is not None:
                    ep = start_episode(
                        self.cfg, self.task, env, after, {}, scripted, self.rng, self.scripted_rng
                    )
                    ep.prelude = not ep.scripted
        ep.slot = slot
        if self.explorer is not None:
            ep.family = find_language_wrapper(env).meaning.family
            if not ep.scripted and scripted is not None:
                ep.handover = self.explorer.handover_steps()
                if ep.handover:
                    scripted.reset()
        return ep

    def _prelude(self, env: Any, obs: Any) -> dict[str, Any] | None:
        """The env's scripted teacher follows an instruction of ``explore.prelude_families``
        from ``obs`` (unstored). Returns the observation the run's next instruction starts
        from, in the scene the teacher left (after a fresh reset where none of the run's
        instructions is feasible there), or None when no prelude instruction is feasible
        at ``obs`` (the episode then starts there)."""
        c = self.cfg.explore
        wrapper = find_language_wrapper(env)
        if getattr(self, "_prelude_texts", None) is None:
            families = c.prelude_families or env_spec(self.cfg.env.kind).families
            split = wrapper.split
            self._prelude_texts = [
                t
                for t, m in zip(split.texts("train"), split.instructions("train"), strict=True)
                if m.family in families
            ]
            self._prelude_actor = ScriptedActor(self.cfg.env, self.task, 0.0, teacher=True)
        if wrapper.switch_instruction(candidates=self._prelude_texts) is None:
            return None
        obs = dict(obs)
        obs["instruction"] = wrapper.instruction
        actor, explorer = self._prelude_actor, self.explorer
        actor.reset()
        explorer.preludes += 1
        succeeded = False
        for _ in range(c.prelude_steps):
            action = actor.act(env, self.scripted_rng)
            obs, _, terminated, truncated, info = env.step(self.task.scale_action(action))
            explorer.prelude_steps += 1
            succeeded = bool(info.get("is_success", False))
            if succeeded or terminated or truncated:
                break
        explorer.prelude_successes += int(succeeded)
        after = switch_in_place(env, obs)
        if after is None:
            obs, _ = env.reset(seed=int(self.scripted_rng.integers(2**31)))
            return obs
        return after

    def _explored(self, ep: Episode) -> None:
        """After storing ``ep``: chain its environment's next episode, move the
        curriculum."""
        complete = ep.done
        opened = self.explorer.finished(ep, complete, self.step)
        if opened is not None:
            self.explorer.apply(self.envs)
            print(f"curriculum: {opened} opens at step {self.step}", flush=True)
        else:
            self.explorer.reweigh(self.envs)

    def _step(self, ep: Episode) -> None:
        step_episode(self.task, ep)

    def _end_learned(self, episodes: list[Episode]) -> None:
        """With ``relabel.end=learned``: end the episodes whose own instruction the learned
        reward model judges achieved at the frame just stepped to (scored in one batch)."""
        if self.cfg.relabel.end != "learned":
            return
        live = [ep for ep in episodes if not ep.terms[-1]]
        only = self.cfg.relabel.end_families
        if only:
            families = self.task.labeller.families
            live = [ep for ep in live if families[int(ep.goal)] in only]
        if not live:
            return
        first = [ep.records[0] for ep in live]
        last = [ep.records[-1] for ep in live]
        hit = self.task.labeller.satisfied(
            [ep.goal for ep in live],
            np.stack([r[1] for r in first]),
            np.stack([r[1] for r in last]),
            np.stack([r[2] for r in first]),
            np.stack([r[2] for r in last]),
        )
        for ep, h in zip(live, hit, strict=True):
            if h:
                ep.terms[-1] = ep.done = ep.learned_end = True

    def _store(self, ep: Episode) -> None:
        """Label a finished episode and add it to the buffer."""
        episode = episode_record(self.task, ep)
        if ep.learned_end and ep.goal not in episode["achieved"][-1]:
            # the episode ended where the online check said its goal was reached: its
            # last reward says so too (the batch scoring of the episode may round apart)
            episode["achieved"][-1] = sorted([*episode["achieved"][-1], int(ep.goal)])
        self.buffer.add_episode(episode)
        if self.stages and self.cfg.sequential.replay:
            self._just_stored.append(episode)
        if not (self.stages and self.stage > 0 and self.cfg.sequential.freeze_norm):
            self.agent.observe(episode["obs"], episode.get("achieved_goal"))

    def _finish_episode(
        self,
        scripted: bool,
        succeeded: bool,
        task_id: int | None,
        info: dict[str, Any],
        handover: bool = False,
    ) -> None:
        """Count a stored episode (one the scripted controller began, ``handover``, is not
        the policy's alone: it stays out of the live success rate)."""
        self.episodes += 1
        if scripted:
            self.scripted_episodes += 1
        elif not handover:  # the live success rate is the policy's
            self.recent.append(float(succeeded))
            if task_id is not None:
                self.sampler.update(task_id, succeeded)
        if info.get("sim_error"):
            self.sim_errors += 1
