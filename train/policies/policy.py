"""A trained policy as a Python object: observations and free-text instructions in, actions out.

::

    import lcrl

    policy = lcrl.load("runs/lang2d")          # a run folder or one checkpoint folder
    env = policy.make_env()
    obs, info = env.reset(seed=0)
    policy.reset()                              # a new episode starts
    while True:
        action = policy.act(obs, "push the red cube left")
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    policy.nearest("shove the crimson box leftwards", k=3)

Any text is a goal: the checkpoint's frozen text encoder embeds it, whether or not the
instruction grammar knows its words. :meth:`Policy.nearest` shows which training
instructions lie closest to a text in that embedding space, i.e. what the policy most
probably understood.

The first observation of an episode
    Language policies judge push and put relative to where the objects started, so besides
    the current observation they read the episode's first observation. Pass it as
    ``initial=``, or let the policy remember it: the first observation given to
    :meth:`Policy.act` after :meth:`Policy.reset` (or after loading) is kept as the
    episode's start until the next :meth:`Policy.reset`. Call :meth:`Policy.reset` whenever
    an environment is reset.

Batches
    ``observation`` may carry a leading batch dimension on every array (``B`` environments
    stepped together); the instruction is then one text for every row or a list of ``B``
    texts, and the actions come back with the same leading dimension.

Task ids
    A policy trained on a fixed task set with one-hot task ids (``env.goal_type="task"``,
    preset ``lang2d-tasks``) reads no text: :meth:`Policy.act` takes the id of one of its
    :attr:`Policy.tasks` (an int, or one per batch row), and the environment is reset with
    that task's instruction so that success is judged::

        policy = lcrl.load("runs/lang2d-tasks")
        env = policy.make_env()
        obs, info = env.reset(seed=0, options={"instruction": policy.tasks[3]})
        policy.reset()
        action = policy.act(obs, 3)
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np

from lcrl.algos import Agent
from lcrl.checkpoint import Checkpoint
from lcrl.errors import LcrlError
from train.configs.config import TrainConfig
from train.environments.simulators import describe
from train.environments.tasks import Task, goal_modality, make_env, task_texts


class Neighbour(NamedTuple):
    """A training instruction and its cosine similarity to a query text."""

    text: str
    similarity: float


def check_instruction(text: Any) -> str:
    """``text`` with runs of whitespace collapsed, or an error for a non-string, an empty
    text, control characters, or a text longer than the instruction limit
    (:data:`captioner.lang_env.MAX_INSTRUCTION_LENGTH` characters). Any other characters
    and words are fine: the text encoder embeds whatever it is given."""
    from captioner.lang_env import MAX_INSTRUCTION_LENGTH

    if isinstance(text, (bytes, bytearray)):
        raise LcrlError(
            f"an instruction must be text (str), not bytes: decode it first, e.g. "
            f"{bytes(text)[:40]!r}.decode()"
        )
    if not isinstance(text, str):
        raise LcrlError(f"an instruction must be a string, got {type(text).__name__}")
    norm = " ".join(text.split())
    if not norm:
        raise LcrlError("empty instruction: say what to do, e.g. 'push the red cube left'")
    if any("\udc80" <= c <= "\udcff" for c in norm):  # bytes Python could not decode
        raw = norm.encode("utf-8", "surrogateescape")
        raise LcrlError(
            f"instruction is not valid UTF-8: {raw!r} holds bytes that are no UTF-8 "
            "character (is the terminal or file in another encoding?); pass UTF-8 text"
        )
    if "\ufffd" in norm:
        raise LcrlError(
            f"instruction holds U+FFFD, the mark of bytes that were not valid UTF-8: {norm!r}; "
            "decode its source as UTF-8"
        )
    if not norm.isprintable():
        raise LcrlError(f"instruction contains control characters: {norm!r}")
    if len(norm) > MAX_INSTRUCTION_LENGTH:
        raise LcrlError(
            f"instruction is {len(norm)} characters long; the limit is {MAX_INSTRUCTION_LENGTH}"
        )
    return norm


def check_finite(arr: np.ndarray, name: str) -> None:
    """Refuse NaN and infinite values: a policy that drives a robot must not turn them
    into actions silently."""
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        flat = np.flatnonzero(~np.isfinite(arr))
        first = np.unravel_index(flat[0], arr.shape)
        value = arr[first]
        where = ", ".join(map(str, first)) if arr.ndim else ""
        raise LcrlError(
            f"{name} holds {value} at index [{where}] ({flat.size} non-finite value"
            f"{'s' if flat.size > 1 else ''}): a policy acts on finite observations only"
        )


def describe_env(cfg: TrainConfig) -> str:
    """A few words naming a config's environment (for error messages)."""
    env = cfg.env
    name = f"{describe(env)} ({env.goal_type} goals)"
    if goal_modality(env.goal_type).task_ids:
        name += f", {len(env.tasks)} task ids"
    return name + (", image observations" if env.image_obs else "")


class Policy:
    """A trained policy: call :meth:`act` with an environment observation and an instruction.

    Build one with :func:`load`. Attributes: ``cfg`` (the run's config), ``agent`` (the
    learner), ``task`` (observation layout and goals), ``checkpoint``, and ``env`` (the
    environment rebuilt from the config when loading, used to check shapes; make fresh
    ones with :meth:`make_env`).
    """

    def __init__(
        self, cfg: TrainConfig, agent: Agent, task: Task, env: gym.Env, checkpoint: Checkpoint
    ) -> None:
        self.cfg, self.agent, self.task, self.env = cfg, agent, task, env
        self.checkpoint = checkpoint
        space = env.observation_space
        self._spaces = dict(space.spaces) if isinstance(space, gym.spaces.Dict) else {}
        self._initial: dict[str, np.ndarray] | None = None
        self._initial_batch: int | None = None
        self._origin: np.ndarray | None = None  # perceived slots of the episode's first frame

    # --- what the policy is -------------------------------------------------------------
    @property
    def language(self) -> bool:
        """Whether the policy follows instructions (else it reaches the env's goals)."""
        return self.task.query == "text"

    @property
    def instructions(self) -> list[str]:
        """The instructions it was trained on (empty for state- and image-goal policies)."""
        if self.task.query != "text":
            return []
        return list(self.task.table[: self.task.num_train])

    @property
    def takes_task_ids(self) -> bool:
        """Whether the policy's goal is the one-hot id of one of its :attr:`tasks`
        (``env.goal_type="task"``): :meth:`act` takes a task id, not text."""
        return self.task.query == "task_id"

    @property
    def tasks(self) -> list[str]:
        """The fixed task set it was trained on (``env.tasks``; task ``i`` has id ``i``),
        as task ids or as language goals; empty without one."""
        return list(task_texts(self.cfg.env))

    def task_id(self, task: Any) -> int:
        """The id of one of :attr:`tasks`, given by its id (checked) or its text (any
        phrasing the instruction grammar reads as the same instruction).

        Raises:
            LcrlError: the policy has no task set, an id out of range, or a text that is
                none of its tasks (the message lists them).
        """
        tasks = self.tasks
        if not tasks:
            raise LcrlError(
                f"this policy was not trained on a fixed task set ({describe_env(self.cfg)}): "
                "it has no task ids"
            )
        if isinstance(task, str):
            from captioner.grammar import try_parse

            text = " ".join(task.split())
            if text in tasks:
                return tasks.index(text)
            meaning = try_parse(text)
            if meaning is not None:
                for k, t in enumerate(tasks):
                    other = try_parse(t)
                    if other is not None and other.text == meaning.text:
                        return k
            raise LcrlError(f"{task!r} is none of this policy's tasks: {self.describe_tasks()}")
        return self._check_task_id(task)

    def describe_tasks(self) -> str:
        """The tasks with their ids, for messages: ``0 'reach the red cube', 1 ...``."""
        return ", ".join(f"{k} {t!r}" for k, t in enumerate(self.tasks))

    def _check_task_id(self, task: Any) -> int:
        """``task`` as an int in ``[0, K)``, or an error naming the range and the tasks."""
        if isinstance(task, (bool, np.bool_)) or not isinstance(task, (int, np.integer)):
            raise LcrlError(
                f"a task id must be an integer, got {type(task).__name__}: one of "
                f"{self.describe_tasks()}"
            )
        k = len(self.tasks)
        if not 0 <= int(task) < k:
            raise LcrlError(
                f"task id {int(task)} is out of range: this policy has {k} tasks, ids 0 to "
                f"{k - 1}: {self.describe_tasks()}"
            )
        return int(task)

    @property
    def families(self) -> tuple[str, ...]:
        """Instruction families it was trained on (empty for state- and image-goal ones)."""
        return tuple(self.cfg.env.families) if self.language else ()

    def __repr__(self) -> str:
        step = self.checkpoint.meta.get("step", "?")
        return (
            f"Policy({self.checkpoint.path}, step {step}, {self.checkpoint.meta.get('algo')}, "
            f"{describe_env(self.cfg)})"
        )

    # --- environments -------------------------------------------------------------------
    def make_env(self, split_set: str = "train", render: bool = False) -> gym.Env:
        """A new environment like the one the policy was trained on.

        Args:
            split_set: language policies: the instruction set that ``reset()`` samples from
                when no ``options={"instruction": ...}`` is given (``train``, ``heldout``
                or ``paraphrase``).
            render: make it with ``render_mode="rgb_array"`` so ``env.render()`` returns
                camera frames.
        """
        env_cfg = copy.deepcopy(self.cfg.env)
        if render:
            env_cfg.extra = {**env_cfg.extra, "render_mode": "rgb_array"}
        return make_env(env_cfg, split_set)

    # --- language ----------------------------------------------------------------------
    def embed(self, texts: str | Sequence[str]) -> np.ndarray:
        """Text embeddings ``(N, d)`` from the policy's frozen encoder (unit length)."""
        encoder = self._encoder()
        texts = [texts] if isinstance(texts, (str, bytes, bytearray)) else list(texts)
        return np.asarray(encoder.encode([check_instruction(t) for t in texts]), np.float32)

    def nearest(self, text: str, k: int = 3) -> list[Neighbour]:
        """The ``k`` training instructions closest to ``text`` by cosine similarity of their
        embeddings, most similar first (a training instruction's nearest is itself, with
        similarity 1)."""
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k <= 0:
            raise LcrlError(f"k must be a positive integer, got {k!r}")
        query = self.embed(text)[0]
        table = self.task.embeddings[: self.task.num_train]
        norms = np.linalg.norm(table, axis=1) * max(float(np.linalg.norm(query)), 1e-12)
        sims = table @ query / np.maximum(norms, 1e-12)
        order = np.argsort(-sims, kind="stable")[: int(k)]
        return [Neighbour(self.task.table[i], float(sims[i])) for i in order]

    def _encoder(self) -> Any:
        if self.task.query != "text":
            raise LcrlError(
                f"this policy was not trained with language goals ({describe_env(self.cfg)}): "
                "it takes no instruction"
            )
        return self.task.encoder

    # --- acting -------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the remembered first observation: the next :meth:`act` starts an episode."""
        self._initial, self._initial_batch = None, None
        self._origin = None

    def act(
        self,
        observation: Mapping[str, Any],
        instruction: str | Sequence[str] | None = None,
        *,
        initial: Mapping[str, Any] | None = None,
        goal: np.ndarray | None = None,
        deterministic: bool = True,
    ) -> np.ndarray:
        """The action for an observation, in the environment's units (pass it to
        ``env.step``).

        Args:
            observation: the dict the environment returns (extra entries such as
                ``instruction`` are ignored), or the same with a leading batch dimension
                on every array.
            instruction: any text (language policies), or one text per batch row. ``None``
                takes the observation's own ``instruction`` entry. Task-id policies
                (:attr:`takes_task_ids`): the task id, an int in ``[0, K)``, or one per
                batch row; ``None`` takes the task whose instruction the observation
                carries (an env reset with ``options={"instruction": policy.tasks[i]}``).
            initial: the episode's first observation (same layout and batch size as
                ``observation``). Default: the first observation given since
                :meth:`reset`, remembered.
            goal: state-goal policies: the goal vector (default: the observation's
                ``desired_goal``); image-goal policies: the goal frame (required, e.g.
                ``env.unwrapped.goal_image()``).
            deterministic: the policy's mean (greedy) action; ``False`` samples one.

        Returns:
            ``(action_dim,)`` floats (or one integer for discrete moves); with a batch,
            ``(B, action_dim)`` (or ``(B,)``).

        Raises:
            LcrlError: missing observation entries or wrong shapes (e.g. an observation of
                another environment), an empty or overlong text, texts and observations of
                different batch sizes; for task-id policies, text or an id out of range.
        """
        if initial is not None:
            initial = self._from_frames(initial, "initial", starts=True)
        observation = self._from_frames(
            observation, "observation", starts=initial is None and self._initial is None
        )
        obs, batch = self._check_obs(observation, "observation")
        rows = 1 if batch is None else batch
        if self.task.query == "task_id":
            if goal is not None:
                raise LcrlError(
                    "goal= is for state- and image-goal policies; this task-id policy takes a "
                    "task id: policy.act(observation, 0)"
                )
            ids = self._task_ids(observation, instruction, batch)  # before remembering
            first = self._first(initial, obs, batch)
            net_obs = self._storage(obs, first, batch)
            a = self.agent.act(net_obs, ids, deterministic=deterministic)
        elif self.task.query == "text":
            texts = self._texts(observation, instruction, batch)
            vectors = self.embed(texts)  # before remembering anything: the texts may be bad
            first = self._first(initial, obs, batch)
            if len(vectors) == 1 and rows > 1:
                vectors = np.repeat(vectors, rows, axis=0)
            net_obs = self._storage(obs, first, batch)
            a = self.agent.act(net_obs, vectors, deterministic=deterministic, embedded=True)
        else:
            if instruction is not None:
                raise LcrlError(
                    f"this policy was not trained with language goals ({describe_env(self.cfg)})"
                    ": it takes no instruction; its goal is the observation's desired_goal "
                    "(or goal=)"
                )
            goals = self._goals(observation, goal, batch)
            net_obs = self._storage(obs, obs, batch)
            a = self.agent.act(net_obs, goals, deterministic=deterministic)
        actions = self.task.scale_action(a)
        return actions if batch is not None else actions[0]

    # --- camera frames -----------------------------------------------------------------
    @property
    def perceives(self) -> bool:
        """Whether the policy acts through a perception model (``--env.perception``): it
        reads object slots estimated from camera frames, never the simulator's state."""
        return self._frame_reader()[0] is not None

    def _frame_reader(self) -> tuple[Any, Any]:
        """The perception model and the slot-feature wrapper of the policy's env (None
        where there is none)."""
        from envs.features import SlotFeatures
        from train.environments.perception import find_perception

        wrapper = find_perception(self.env)
        features, e = None, self.env
        while isinstance(e, gym.Wrapper):
            if isinstance(e, SlotFeatures):
                features = e
                break
            e = e.env
        return (wrapper.model if wrapper is not None else None), features

    def _from_frames(self, observation: Any, name: str, starts: bool) -> Any:
        """An observation given as camera frames and proprioception (``image`` and
        ``proprio``, no ``observation``) turned into the env's observation: perception's
        estimate of the object slots, with the slot features the policy was trained on
        (displacements from the episode's first frame). Anything else is returned as
        given."""
        model, features = self._frame_reader()
        if model is None or not isinstance(observation, Mapping) or "observation" in observation:
            return observation
        if "image" not in observation or "proprio" not in observation:
            raise LcrlError(
                f"{name} has neither 'observation' nor both 'image' and 'proprio' (it has "
                f"{sorted(map(str, observation))}): this policy acts from camera frames, "
                f"{tuple(model.frame_shape)} uint8, and the robot's proprioception, "
                f"({model.layout.start},)"
            )
        image = np.asarray(observation["image"])
        proprio = np.asarray(observation["proprio"], np.float32)
        frame, start = tuple(model.frame_shape), model.layout.start
        if image.shape[-3:] != frame or image.ndim not in (3, 4):
            raise LcrlError(
                f"{name}['image'] has shape {image.shape}; this policy's perception reads "
                f"{frame} frames (or (batch, *{frame}))"
            )
        if image.dtype != np.uint8:
            raise LcrlError(f"{name}['image'] must be uint8 camera frames, got {image.dtype}")
        batch = image.shape[0] if image.ndim == 4 else None
        want = (start,) if batch is None else (batch, start)
        if proprio.shape != want:
            raise LcrlError(f"{name}['proprio'] has shape {proprio.shape}; expected {want}")
        check_finite(proprio, f"{name}['proprio']")
        rows = 1 if batch is None else batch
        origin = getattr(self, "_origin", None)
        new_episode = starts or origin is None or len(origin) != rows
        # presence is the episode's first frame's, as in training (PerceptionObservation)
        present = None if new_episode else model.presence(origin)
        estimate = model.observation(image.reshape(-1, *frame), proprio.reshape(-1, start), present)
        held = getattr(self, "_held", None)
        if held is None:
            # objects are held as the env holds them
            held = self._held = model.held_slots(self.cfg.env.perception_hold_radius)
        if new_episode:
            held.reset()
            self._origin = estimate
        # objects the gripper stays away from keep their positions, as in training
        estimate = held(estimate)
        x = estimate if features is None else features.features(estimate, self._origin)
        out = {k: v for k, v in observation.items() if k != "proprio"}
        out["observation"] = x.astype(np.float32) if batch is not None else x[0].astype(np.float32)
        return out

    # --- checks ---------------------------------------------------------------------------
    def _required_keys(self) -> tuple[str, ...]:
        task = self.task
        keys = ["observation"]
        if "image" in task.obs_shapes:
            keys.append("image")
        return tuple(keys)

    def _check_obs(self, observation: Any, name: str) -> tuple[dict[str, np.ndarray], int | None]:
        """The entries the network reads, checked against the env's shapes, and the batch
        size (None for one unbatched observation)."""
        if not isinstance(observation, Mapping):
            raise LcrlError(
                f"{name} must be the dict the environment returns (keys "
                f"{list(self._required_keys())}), got {type(observation).__name__}"
            )
        out: dict[str, np.ndarray] = {}
        batch: int | None = None
        for key in self._required_keys():
            if key not in observation:
                raise LcrlError(
                    f"{name} has no {key!r} entry (it has {sorted(map(str, observation))}); "
                    f"this policy ({describe_env(self.cfg)}) reads {list(self._required_keys())}"
                )
            arr = np.asarray(observation[key])
            if arr.dtype.kind not in "fiub":
                raise LcrlError(f"{name}[{key!r}] must be numbers, got dtype {arr.dtype}")
            check_finite(arr, f"{name}[{key!r}]")
            want = tuple(self._spaces[key].shape)
            if arr.shape == want:
                b = None
            elif arr.ndim == len(want) + 1 and arr.shape[1:] == want:
                b = int(arr.shape[0])
            else:
                raise LcrlError(
                    f"{name}[{key!r}] has shape {arr.shape}; this policy was trained on the "
                    f"{describe_env(self.cfg)}, whose {key!r} is {want} (or (batch, *{want})): "
                    "is the observation from another environment?"
                )
            if out and b != batch:
                raise LcrlError(
                    f"{name} entries disagree on the batch size: "
                    + ", ".join(f"{k} {v.shape}" for k, v in [*out.items(), (key, arr)])
                )
            out[key], batch = arr, b
        if batch == 0:
            raise LcrlError(f"{name} is an empty batch")
        return out, batch

    def _texts(self, observation: Mapping[str, Any], instruction: Any, batch: int | None) -> list:
        if instruction is None:
            if "instruction" not in observation:
                raise LcrlError(
                    "give an instruction: policy.act(observation, 'push the red cube left') "
                    "(the observation has no 'instruction' entry either)"
                )
            instruction = observation["instruction"]
            if isinstance(instruction, np.ndarray):
                instruction = instruction.tolist()
        if isinstance(instruction, str):
            return [instruction]
        if isinstance(instruction, (bytes, bytearray)) or (
            isinstance(instruction, Sequence)
            and any(isinstance(t, (bytes, bytearray)) for t in instruction)
        ):
            raise LcrlError(
                "instructions must be text (str), not bytes: decode them first, e.g. "
                "b'reach the red cube'.decode()"
            )
        if not isinstance(instruction, Sequence):
            raise LcrlError(
                f"an instruction must be a string or a list of strings, got "
                f"{type(instruction).__name__}"
            )
        texts = list(instruction)
        rows = 1 if batch is None else batch
        if len(texts) != rows:
            what = "one observation" if batch is None else f"a batch of {batch} observations"
            raise LcrlError(f"{len(texts)} instructions for {what}: give one text, or one per row")
        return texts

    def _task_ids(self, observation: Mapping[str, Any], task: Any, batch: int | None) -> np.ndarray:
        """Checked task ids, one per row: ``task`` (an id, or one per row), or the task
        of the observation's own ``instruction`` entry."""
        rows = 1 if batch is None else batch
        if task is None:
            if "instruction" not in observation:
                raise LcrlError(
                    f"give a task id: policy.act(observation, 0); tasks: {self.describe_tasks()}"
                )
            texts = observation["instruction"]
            texts = [texts] if isinstance(texts, str) else list(np.asarray(texts).tolist())
            ids = []
            for text in texts:
                try:
                    ids.append(self.task_id(str(text)))
                except LcrlError:
                    raise LcrlError(
                        f"the observation's instruction {text!r} is none of this policy's "
                        f"tasks: reset the env with options={{'instruction': policy.tasks[i]}} "
                        f"or pass the id; tasks: {self.describe_tasks()}"
                    ) from None
        elif isinstance(task, str) or (
            isinstance(task, (Sequence, np.ndarray))
            and any(isinstance(t, str) for t in np.asarray(task, object).reshape(-1))
        ):
            raise LcrlError(
                f"this policy was trained with task ids ({describe_env(self.cfg)}): it reads "
                f"no text; pass a task id (policy.task_id(TEXT) looks one up): "
                f"{self.describe_tasks()}"
            )
        elif isinstance(task, (Sequence, np.ndarray)):
            arr = np.asarray(task)
            if arr.ndim == 0:  # a 0-d array: one id
                arr = arr.reshape(1)
            if arr.ndim != 1:
                raise LcrlError(f"task ids must be one id or a list of ids, got shape {arr.shape}")
            ids = [self._check_task_id(t) for t in arr.tolist()]
        else:
            ids = [self._check_task_id(task)]
        if len(ids) == 1 and rows > 1:
            ids = ids * rows
        if len(ids) != rows:
            what = "one observation" if batch is None else f"a batch of {batch} observations"
            raise LcrlError(f"{len(ids)} task ids for {what}: give one id, or one per row")
        return np.asarray(ids, np.int64)

    def _first(
        self, initial: Mapping[str, Any] | None, obs: dict[str, np.ndarray], batch: int | None
    ) -> dict[str, np.ndarray]:
        if initial is not None:
            first, b = self._check_obs(initial, "initial")
            if b != batch:
                raise LcrlError(
                    f"initial has batch size {b} but observation has {batch}: give the "
                    "first observation of the same episodes"
                )
            return first
        if self._initial is None:
            self._initial = {k: np.array(v, copy=True) for k, v in obs.items()}
            self._initial_batch = batch
        elif self._initial_batch != batch:
            raise LcrlError(
                f"the remembered first observation has batch size {self._initial_batch} but "
                f"this observation has {batch}: call policy.reset() when new episodes start "
                "(or pass initial=)"
            )
        return self._initial

    def _goals(self, observation: Mapping[str, Any], goal: Any, batch: int | None) -> np.ndarray:
        key = self.task.goal_key
        if goal is None and key is None:
            raise LcrlError(
                "an image-goal policy needs goal=, the goal frame (env.unwrapped.goal_image())"
            )
        if goal is None:
            if key not in observation:
                raise LcrlError(f"the observation has no {key!r} entry: pass goal= (a goal vector)")
            goal = observation[key]
        want = tuple(self.task.problem().goal_shape)
        g = np.asarray(goal)
        if g.dtype.kind in "fiub":
            check_finite(g, "goal")
        if g.shape == want:
            g = g[None] if batch is None else np.repeat(g[None], batch, axis=0)
        elif batch is None or g.shape != (batch, *want):
            rows = "" if batch is None else f" or ({batch}, *{want})"
            raise LcrlError(f"the goal has shape {g.shape}; this policy expects {want}{rows}")
        return g if g.dtype == np.uint8 else g.astype(np.float32)

    def _storage(
        self, obs: dict[str, np.ndarray], first: dict[str, np.ndarray], batch: int | None
    ) -> dict[str, np.ndarray]:
        """The network's observation arrays, built row by row exactly as in training."""
        if batch is None:
            return {k: v[None] for k, v in self.task.storage_obs(obs, first).items()}
        parts = [
            self.task.storage_obs(
                {k: v[i] for k, v in obs.items()}, {k: v[i] for k, v in first.items()}
            )
            for i in range(batch)
        ]
        return {k: np.stack([p[k] for p in parts]) for k in parts[0]}


def load(
    path: str | Path,
    device: str | None = None,
    env_overrides: Mapping[str, Any] | None = None,
) -> Policy:
    """Load a trained policy.

    Args:
        path: a checkpoint folder, or a run folder (its latest checkpoint).
        device: run the networks here (``"cpu"``, ``"cuda"``) instead of the checkpoint's
            device.
        env_overrides: env config fields to change (e.g. ``{"families": ("reach",)}``);
            the resulting environment must give the checkpoint's observation and action
            shapes.

    Raises:
        LcrlError: no checkpoint at ``path``, or it does not match its environment.
    """
    from train.policies.loading import load_policy

    loaded = load_policy(path, dict(env_overrides or {}), device)
    return Policy(loaded.cfg, loaded.agent, loaded.task, loaded.env, loaded.checkpoint)
