"""The tasks of instructions: language goals (:class:`LanguageTask`) and one-hot ids of a
fixed instruction set (:class:`TaskIdTask`) (re-exported by :mod:`train.environments.tasks`)."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl.errors import LcrlError
from lcrl.goals import LabelGoals, TaskGoals
from train.environments.simulators import EnvConfig
from train.environments.task_base import Task, find_language_wrapper, slot_layout_start, task_texts


def vector_shapes(shape: tuple[int, ...], initial: bool) -> dict[str, tuple[int, ...]]:
    """What an instruction-following policy reads of a vector observation: the current
    one, and with ``initial`` the one its instruction started from."""
    return {"observation": shape, "initial": shape} if initial else {"observation": shape}


class LanguageTask(Task):
    """Language-goal envs (:class:`captioner.lang_env.LanguageGoalWrapper`).

    Args:
        env: the wrapped training env (its split and families define the table).
        embed: ``texts -> (N, d)`` float32 embeddings (the frozen text encoder).
        table: the instruction table to use (e.g. from a checkpoint); default: the
            split's training instructions of the env's families first, then held-out and
            paraphrase ones.
        tasks: a fixed task set: the table is exactly these instructions, all of them
            training instructions (relabelled among themselves), and their ids are task
            ids (:attr:`num_tasks`).
        phrasings: training-only phrasings embedded per training instruction
            (``env.phrasings``), 0: none.
    """

    goal_kind = "text"
    sets = ("train", "heldout", "paraphrase")
    instructed = True
    text_goals = True
    query = "text"

    @classmethod
    def from_config(
        cls, cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any
    ) -> LanguageTask:
        """The language task of a config (``embed`` is required; ``kwargs`` may give a
        saved ``table`` and ``num_train``)."""
        if embed is None:
            raise LcrlError("language tasks need a text encoder")
        if cfg.tasks:
            kwargs["tasks"] = task_texts(cfg)
        return cls(
            env,
            embed,
            image_obs=cfg.image_obs,
            phrasings=cfg.phrasings,
            initial=cfg.initial,
            **kwargs,
        )

    def outcome(self, env: gym.Env) -> dict[str, Any]:
        """The episode's instruction and its family (``free`` for unparsed text)."""
        wrapper = find_language_wrapper(env)
        family = wrapper.meaning.family if wrapper.meaning else "free"
        return {"instruction": wrapper.instruction, "family": family}

    def __init__(
        self,
        env: gym.Env,
        embed: Any,
        table: list[str] | None = None,
        num_train: int | None = None,
        image_obs: bool = False,
        tasks: tuple[str, ...] = (),
        phrasings: int = 0,
        initial: bool = True,
    ) -> None:
        super().__init__(env)
        if tasks:
            if table is not None and list(table) != list(tasks):
                raise LcrlError(
                    "the saved instruction table differs from env.tasks: resume with the "
                    "run's own config"
                )
            table, num_train = list(tasks), len(tasks)
            self.num_tasks = len(tasks)
        wrapper = find_language_wrapper(env)
        self.wrapper = wrapper
        self.split = wrapper.split
        self.families = wrapper.families
        self.captioner = wrapper.captioner
        if table is None:
            train = [
                t
                for t, m in zip(self.split.train, self.split.instructions("train"), strict=True)
                if m.family in self.families
            ]
            rest = [
                t
                for name in ("heldout", "paraphrase")
                for t, m in zip(self.split.texts(name), self.split.instructions(name), strict=True)
                if m.family in self.families
            ]
            table = train + [t for t in dict.fromkeys(rest) if t not in set(train)]
            num_train = len(train)
        if num_train is None:
            raise LcrlError("num_train is required with an explicit instruction table")
        self.table = list(table)
        self.num_train = int(num_train)
        self.ids = {t: i for i, t in enumerate(self.table)}
        self.train_ids = {t: i for t, i in self.ids.items() if i < self.num_train}
        # the captioner names achievements in canonical phrasing
        self.label_ids = dict(self.train_ids)
        if tasks:
            self.label_ids = {self.captioner.parse(t).text: i for t, i in self.train_ids.items()}
        self.embed_fn = embed
        self.embeddings = np.asarray(embed(self.table), np.float32)
        self.phrasings = int(phrasings)
        self._phrasing_cache: tuple[np.ndarray, np.ndarray] | None = None
        space = env.observation_space
        shape = tuple(space["observation"].shape)
        self.initial = bool(initial)
        self.obs_shapes = vector_shapes(shape, self.initial)
        self._setup_image_obs(env, image_obs)
        self.goal_space = LabelGoals(
            len(self.table), self.embeddings, num_relabel=self.num_train, terminate_on_success=True
        )

    def phrasing_embeddings(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Embeddings of up to :attr:`phrasings` training-only phrasings of every training
        instruction (:func:`captioner.phrasings.training_phrasings`), ``(num_train,
        phrasings, d)``, and how many each has; None when :attr:`phrasings` is 0. Embedded
        on the first call (training only)."""
        if self.phrasings <= 0:
            return None
        if self._phrasing_cache is None:
            self._phrasing_cache = self._embed_phrasings()
        return self._phrasing_cache

    def _embed_phrasings(self) -> tuple[np.ndarray, np.ndarray]:
        from captioner.grammar import try_parse
        from captioner.phrasings import training_phrasings

        count = self.phrasings
        counts = np.zeros(self.num_train, np.int64)
        texts: list[list[str]] = []
        for i, text in enumerate(self.table[: self.num_train]):
            meaning = try_parse(text)
            found = training_phrasings(meaning, count, seed=i) if meaning is not None else []
            texts.append(found)
            counts[i] = len(found)
        flat = [t for group in texts for t in group]
        d = self.embeddings.shape[1]
        out = np.zeros((self.num_train, count, d), np.float32)
        if flat:
            vectors = np.asarray(self.embed_fn(flat), np.float32)
            k = 0
            for i, group in enumerate(texts):
                out[i, : len(group)] = vectors[k : k + len(group)]
                k += len(group)
        return out, counts

    def grounding_targets(self) -> np.ndarray:
        """Per instruction id, the object slots it names, as the grammar parses it: the
        kind acted on and the reference object of put and stack, ``(ids, 2)``, -1 where
        there is none (slot ``k`` of both tabletops holds ``OBJECT_KINDS[k]``)."""
        from captioner.grammar import try_parse
        from envs.scene import OBJECT_KINDS

        out = np.full((len(self.table), 2), -1, np.int64)
        for i, text in enumerate(self.table):
            meaning = try_parse(text)
            if meaning is None:
                continue
            out[i, 0] = OBJECT_KINDS.index((meaning.colour, meaning.shape))
            if meaning.target_colour is not None and meaning.target_shape is not None:
                out[i, 1] = OBJECT_KINDS.index((meaning.target_colour, meaning.target_shape))
        return out

    def storage_obs(
        self, obs: Mapping[str, Any], first: Mapping[str, Any]
    ) -> dict[str, np.ndarray]:
        """The observation and the one its instruction started from (``initial``; not
        with ``env.initial`` off), or with image observations the image and the
        proprioception."""
        if self.image_obs:
            return self._image_storage(obs)
        out = {"observation": np.asarray(obs["observation"], np.float32)}
        if self.initial:
            out["initial"] = np.asarray(first["observation"], np.float32)
        return out

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> int:
        """The id of the episode's instruction (added to the table if new)."""
        text = obs["instruction"]
        if text not in self.ids:
            raise LcrlError(f"instruction {text!r} is not in the instruction table")
        return self.ids[text]

    # labeller (Task): a learned captioner / reward model
    # (:class:`captioner.learned.LearnedLabeller`) that labels stored episodes from camera
    # frames; None: the rule captioner does.

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """The scene after each step (captioned at the end of the episode), with the
        camera frame and the robot's state when a learned labeller reads them."""
        wrapper = find_language_wrapper(env)  # the env that stepped (one of several)
        scene = wrapper.env.unwrapped.scene()
        if self.labeller is None:
            return scene
        if "image" not in obs:
            raise LcrlError("learned relabelling needs camera frames: the env gives no image")
        start = int(slot_layout_start(wrapper))
        return scene, np.asarray(obs["image"]), np.asarray(obs["observation"][:start], np.float32)

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        """The episode's instruction id and the training instructions each step satisfies
        (rule captioner), or what the learned captioner reads in the frames and what the
        learned reward model judges achieved."""
        lab = self.labeller
        scenes = records if lab is None else [r[0] for r in records]
        s0 = scenes[0]
        labels: list[list[int]] = [[]]
        for s in scenes[1:]:
            texts = (ins.text for ins in self.captioner.caption(s0, s))
            labels.append([self.label_ids[t] for t in texts if t in self.label_ids])
        out: dict[str, Any] = {"goal_id": int(goal), "labels": labels}
        if lab is None:
            return out
        frames = np.stack([r[1] for r in records])
        proprio = np.stack([r[2] for r in records])
        # the rule captioner's labels are kept only to report how far the learned ones agree
        if lab.use_captioner:
            out["labels"] = lab.labels(frames, proprio)
        if lab.use_reward:
            if lab.reward_labels:  # every training instruction is a candidate
                cands = sorted(set(range(lab.num_train)) | {int(goal)})
            else:
                cands = sorted({i for ids in out["labels"] for i in ids} | {int(goal)})
            out["achieved"] = lab.achieved(frames, proprio, cands, out["labels"])
            lab.compare("rewards", out["achieved"], labels, among=cands)
            if lab.reward_labels:  # relabel with what the reward model judges achieved
                out["labels"] = lab.judged(out["labels"], out["achieved"])
            elif lab.use_captioner:  # with confirm: only the labels rewarded where read
                out["labels"] = lab.confirmed(out["labels"], out["achieved"])
        if lab.use_captioner or lab.reward_labels:
            lab.compare("labels", out["labels"], labels)
        if lab.use_captioner and not lab.use_reward and not lab.captioner_rewards:
            out["achieved"] = labels  # learned candidates, rule rewards
        # captioner_rewards: no "achieved", so the learned captions are the rewards too
        return out

    def embed_goals(self, goals: np.ndarray) -> np.ndarray:
        """Instruction ids as text embeddings."""
        return self.embeddings[np.asarray(goals, np.int64)]


class TaskIdTask(Task):
    """A fixed set of ``K`` instructions given to the policy as one-hot task ids.

    Multi-task RL in the same loop: the env is the language-goal env, each episode is
    reset with one task's instruction, the policy sees the observation, the episode's
    first observation and a one-hot id of the task (never its text), and the reward of a
    step is the task's own reward function ``r_i(s0, s)``: the rule captioner's
    ``satisfied`` check of task ``i``'s instruction on the privileged scenes. Nothing is
    relabelled (:class:`lcrl.goals.TaskGoals`).

    Args:
        env: the wrapped env (:class:`captioner.lang_env.LanguageGoalWrapper` inside).
        tasks: the ``K`` instructions; task ``i`` is id ``i``.
        image_obs: the policy sees camera images and proprioception instead.
    """

    goal_kind = "onehot"
    sets = ("train",)
    instructed = True
    query = "task_id"

    @classmethod
    def from_config(
        cls, cfg: EnvConfig, env: gym.Env, embed: Any = None, **kwargs: Any
    ) -> TaskIdTask:
        """The task-id task of a config's task set."""
        return cls(env, task_texts(cfg), image_obs=cfg.image_obs, initial=cfg.initial)

    #: the instruction and family, as language goals report them
    outcome = LanguageTask.outcome

    def __init__(
        self,
        env: gym.Env,
        tasks: tuple[str, ...],
        image_obs: bool = False,
        initial: bool = True,
    ) -> None:
        super().__init__(env)
        if not tasks:
            raise LcrlError("task ids need at least one task (env.tasks)")
        wrapper = find_language_wrapper(env)
        self.wrapper = wrapper
        self.families = wrapper.families
        self.captioner = wrapper.captioner
        self.tasks = list(tasks)
        self.num_tasks = len(self.tasks)
        self.meanings = [self.captioner.parse(t) for t in self.tasks]
        #: ``r_i(s0, s) -> bool``: whether the change from ``s0`` to ``s`` achieves task i.
        self.reward_fns = [
            functools.partial(self.captioner.satisfied, meaning) for meaning in self.meanings
        ]
        self.ids = {t: i for i, t in enumerate(self.tasks)}
        self.ids.update({m.text: i for i, m in enumerate(self.meanings)})
        shape = tuple(env.observation_space["observation"].shape)
        self.initial = bool(initial)
        self.obs_shapes = vector_shapes(shape, self.initial)
        self._setup_image_obs(env, image_obs)
        self.goal_space = TaskGoals(self.num_tasks, terminate_on_success=True)

    #: the observation and the episode's first one, as language goals store them
    storage_obs = LanguageTask.storage_obs

    def goal(self, obs: Mapping[str, Any], env: gym.Env) -> int:
        """The task id of the episode's instruction."""
        text = obs["instruction"]
        task = self.ids.get(text)
        if task is None:
            task = self.ids.get(self.captioner.parse(text).text)
        if task is None:
            raise LcrlError(
                f"instruction {text!r} is not one of the {self.num_tasks} tasks of this task-id "
                "policy (env.tasks): reset the env with options={'instruction': TASK}"
            )
        return task

    def step_record(self, obs: Mapping[str, Any], env: gym.Env) -> Any:
        """The privileged scene after each step."""
        return find_language_wrapper(env).env.unwrapped.scene()

    def episode_fields(self, records: list[Any], goal: Any, env: gym.Env) -> dict[str, Any]:
        """The task id and, per step, whether the episode achieved its own task."""
        reward = self.reward_fns[int(goal)]
        s0 = records[0]
        return {"goal_id": int(goal), "success": [reward(s0, s) for s in records[1:]]}

    def embed_goals(self, goals: np.ndarray) -> np.ndarray:
        """Task ids as one-hot vectors."""
        return np.eye(self.num_tasks, dtype=np.float32)[np.asarray(goals, np.int64)]
