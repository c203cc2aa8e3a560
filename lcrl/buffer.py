"""Episode replay buffer with hindsight relabelling at sample time.

Storage is preallocated numpy, one row per *observation slot*. An episode of ``T``
transitions takes ``T + 1`` consecutive slots: slot ``s + t`` holds observation ``t`` and
the action, reward and termination of step ``t``; the next observation of a transition is
simply the following slot, so observations (images included) are stored once. Episodes are
written whole; one that does not fit before the end of the storage starts again at slot
0, and every episode it overlaps is dropped at once, so a partly overwritten episode can
never be sampled.

Sampling decides for each batch row, with probability ``relabel_ratio`` (``k / (k + 1)``:
0.8 for ``k = 4``), whether it is relabelled. Rows that are not relabelled are transitions
drawn uniformly with their original goals. Rows that are relabelled are transitions drawn
uniformly among those that *can* be relabelled under the strategy, and get a goal the same
episode achieved (``future``, ``final`` or ``episode``; see :mod:`lcrl.goals`). For state
goals every transition can be relabelled, so this is classic HER; for language goals only
transitions followed by a captioned achievement can, and drawing the relabelled rows among
them keeps the relabelled fraction at ``k / (k + 1)`` when achievements are rare (with a
random policy on the 2D tabletop about 1.6% of steps achieve anything). The reward of
every row is recomputed with the goal space's reward function, vectorised.

What fraction of relabelled transitions become successes? Not ``k / (k + 1)``: that is the
relabelled fraction. With sparse rewards and an episode whose achieved goals are all
distinct (far apart), a relabelled transition at step ``t`` of a ``T``-step episode is a
success only if the chosen goal is its own next achieved goal:

* ``future`` (uniform over steps ``t' >= t``): probability ``1 / (T - t)``, so on average
  ``H_T / T`` where ``H_T = 1 + 1/2 + ... + 1/T`` (0.090 for ``T = 50``);
* ``final``: only the last transition, ``1 / T`` (0.02 for ``T = 50``);
* ``episode``: ``1 / T`` (0.02 for ``T = 50``).

Real episodes revisit goals (an arm resting still, an object never touched), so real
positive fractions are higher; ``tests/test_buffer.py`` checks the exact figures above.

Storage on the learner's device (``device``): the observation arrays (camera frames are
most of a buffer's bytes) can live as torch tensors on the learner's device, so a sampled
batch of frames is gathered there and never crosses the host-device bus; the index
arithmetic, relabelling and rewards stay in numpy on the host, where they are cheap. A
key the goal space reads from the host (the frames of image goals) stays on the host.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np
import torch

from lcrl.errors import LcrlError
from lcrl.goals import STRATEGIES, TASK_RELABEL_ERROR, GoalSpace


class Batch(NamedTuple):
    """A sampled batch (numpy; learners move it to their device).

    Attributes:
        obs: observation arrays by key, ``(B, ...)`` (uint8 images stay uint8).
        action: ``(B, *action_shape)``.
        reward: ``(B,)`` float32, recomputed for the batch's goals.
        next_obs: next observation arrays by key.
        terminated: ``(B,)`` float32: 1.0 where the transition ended the episode for a
            reason other than a time limit (no bootstrap); truncations are 0.0.
        goal: ``(B, ...)`` goals in the goal space's representation.
        relabelled: ``(B,)`` bool, which goals were relabelled.
        index: ``(B,)`` slots of the sampled transitions.
        discount: ``(B,)`` float32 factor of the bootstrapped value, ``gamma ** m`` for a
            row summing ``m`` rewards (``n_step > 1``); ``None`` for one-step returns,
            where learners use their own ``gamma``.
        demo: ``(B,)`` bool, which transitions a demonstrator acted (the scripted
            controller, a demonstration file); ``None`` where the buffer does not say.
    """

    obs: dict[str, np.ndarray]
    action: np.ndarray
    reward: np.ndarray
    next_obs: dict[str, np.ndarray]
    terminated: np.ndarray
    goal: np.ndarray
    relabelled: np.ndarray
    index: np.ndarray
    discount: np.ndarray | None = None
    demo: np.ndarray | None = None


def batch_rows(batch: Batch, rows: Any) -> Batch:
    """The rows ``rows`` (indices or a mask) of every array of ``batch``."""

    def pick(x: Any) -> Any:
        if x is None:
            return None
        if isinstance(x, dict):
            return {k: v[rows] for k, v in x.items()}
        return x[rows]

    return Batch(*(pick(x) for x in batch))


class HindsightReplayBuffer:
    """Preallocated episode storage with vectorised hindsight relabelling.

    Args:
        capacity: observation slots (an episode of ``T`` steps takes ``T + 1``).
        obs_spec: ``{key: (shape, dtype)}`` of the stored observation arrays, e.g.
            ``{"state": ((26,), np.float32), "image": ((64, 64, 3), np.uint8)}``.
        action_shape: shape of one action (``()`` for discrete actions).
        action_dtype: ``np.float32`` for continuous, ``np.int64`` for discrete actions.
        goal_space: a :class:`lcrl.goals.GoalSpace`.
        strategy: ``future``, ``final`` or ``episode``.
        k: relabelled goals per original goal; the relabel ratio is ``k / (k + 1)``.
            ``k = 0`` turns hindsight relabelling off. A goal space that cannot be
            relabelled (``can_relabel = False``, one-hot task ids) needs ``k = 0`` and
            ``random_fraction = 0``.
        seed: seed of the sampling generator.
        only_relabelable: draw the transitions to relabel among those that have an
            achieved goal for the strategy (see the module docstring); ``False`` draws
            them among all transitions and leaves those without one unrelabelled.
        random_fraction: fraction of batch rows (taken from those not relabelled in
            hindsight) whose goal is replaced by a goal achieved anywhere in the buffer
            (HER's ``random`` strategy). Such goals are rarely reached, so they teach the
            critic what a goal is *not* worth; language goals need them (see
            :class:`lcrl.goals.LabelGoals`). At most ``1 / (k + 1)``.
        n_step: rewards summed per sampled row. With ``n_step = n > 1`` a row starting at
            ``t`` carries ``sum_j gamma**j r_{t+j}`` over ``j < m``, where ``m <= n`` stops
            at the episode's end or at the first terminal step (for the row's own goal,
            relabelled or not), ``next_obs`` is the observation at ``t + m`` and
            :attr:`Batch.discount` is ``gamma ** m``. Rewards are recomputed for the row's
            goal at every step. Multi-step returns carry value back along sparse-reward
            paths ``n`` times faster, at the cost of a bias from the behaviour policy's
            later actions (small for small ``n``).
        gamma: the learner's discount, needed when ``n_step > 1``.
        device: store the observation arrays as torch tensors on this device (``cuda``,
            ``cuda:N``, ``cpu``) instead of numpy arrays in host memory; sampled batches
            then hold tensors on it for those keys. ``None``: host numpy (the default).
    """

    def __init__(
        self,
        capacity: int,
        obs_spec: Mapping[str, tuple[tuple[int, ...], Any]],
        action_shape: tuple[int, ...],
        action_dtype: Any,
        goal_space: GoalSpace,
        strategy: str = "future",
        k: int = 4,
        seed: int = 0,
        only_relabelable: bool = True,
        random_fraction: float = 0.0,
        n_step: int = 1,
        gamma: float = 0.98,
        device: str | torch.device | None = None,
    ) -> None:
        if capacity < 2:
            raise LcrlError(f"buffer capacity must be at least 2 slots, got {capacity}")
        if strategy not in STRATEGIES:
            raise LcrlError(
                f"unknown relabelling strategy {strategy!r}; choose one of {STRATEGIES}"
            )
        if k < 0:
            raise LcrlError(f"k must be >= 0, got {k}")
        if not 0.0 <= random_fraction <= 1.0 / (k + 1) + 1e-9:
            raise LcrlError(
                f"random_fraction must be in [0, 1 / (k + 1)] = [0, {1 / (k + 1):.3f}], got "
                f"{random_fraction}"
            )
        if isinstance(n_step, bool) or int(n_step) != n_step or n_step < 1:
            raise LcrlError(f"n_step must be an integer >= 1, got {n_step!r}")
        if not getattr(goal_space, "can_relabel", True) and (k > 0 or random_fraction > 0):
            raise LcrlError(TASK_RELABEL_ERROR)
        if not 0.0 < gamma <= 1.0:
            raise LcrlError(f"gamma must be in (0, 1], got {gamma}")
        self.n_step = int(n_step)
        self.gamma = float(gamma)
        self.capacity = int(capacity)
        self.obs_spec = {key: (tuple(shape), np.dtype(dt)) for key, (shape, dt) in obs_spec.items()}
        self.action_shape = tuple(action_shape)
        self.action_dtype = np.dtype(action_dtype)
        self.goal_space = goal_space
        self.strategy = strategy
        self.k = int(k)
        self.relabel_ratio = self.k / (self.k + 1)
        self.random_fraction = float(random_fraction)
        self.rng = np.random.default_rng(seed)
        self.device = None if device is None else storage_device(device)
        host = set(getattr(goal_space, "host_obs_keys", ()))
        #: Observation keys stored as tensors on :attr:`device`.
        self.device_keys = tuple(
            k for k in self.obs_spec if self.device is not None and k not in host
        )
        self.obs: dict[str, Any] = {}
        for key, (shape, dt) in self.obs_spec.items():
            if key in self.device_keys:
                self.obs[key] = torch.zeros(
                    (self.capacity, *shape), dtype=torch_dtype(dt), device=self.device
                )
            else:
                self.obs[key] = np.zeros((self.capacity, *shape), dt)
        self.action = np.zeros((self.capacity, *self.action_shape), self.action_dtype)
        self.env_reward = np.zeros(self.capacity, np.float32)
        self.terminated = np.zeros(self.capacity, bool)
        #: Transitions a demonstrator acted (episode field ``demo``; absent: none).
        self.demo = np.zeros(self.capacity, bool)
        self.ep_start = np.zeros(self.capacity, np.int64)
        self.ep_end = np.zeros(self.capacity, np.int64)  # slot of the episode's last observation
        self.valid = np.zeros(self.capacity, bool)  # sampleable transition slots
        goal_space.allocate(self.capacity)
        attach = getattr(goal_space, "attach", None)
        if callable(attach):
            attach(self.obs)
        self.ptr = 0
        self.high = 0  # slots below this have been written at least once
        self.episodes_added = 0
        self.steps_added = 0
        self._valid_idx: np.ndarray | None = None
        self._relabel_idx: np.ndarray | None = None
        self.only_relabelable = only_relabelable

    @staticmethod
    def estimate_bytes(
        capacity: int,
        obs_spec: Mapping[str, tuple[tuple[int, ...], Any]],
        action_shape: tuple[int, ...],
        action_dtype: Any,
        goal_space: GoalSpace,
    ) -> int:
        """The bytes a buffer of these arguments allocates (observation arrays, camera
        frames included, actions, flags, episode bounds and the goal space's arrays),
        computed without allocating anything: what a trainer checks against the
        machine's memory first."""
        per_slot = sum(
            int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize
            for shape, dt in obs_spec.values()
        )
        per_slot += int(np.prod(action_shape, dtype=np.int64)) * np.dtype(action_dtype).itemsize
        per_slot += 4 + 1 + 1 + 8 + 8 + 1  # reward, terminated, demo, episode bounds, valid
        return int(capacity) * per_slot + int(goal_space.nbytes(int(capacity)))

    # --- writing ---------------------------------------------------------------------
    def add_episode(self, episode: Mapping[str, Any]) -> None:
        """Store one finished episode.

        Args:
            episode: ``obs`` (dict of ``(T + 1, ...)`` arrays, the first and every next
                observation), ``action`` ``(T, ...)``, ``reward`` ``(T,)`` (the env's
                reward, kept for reference), ``terminated`` ``(T,)`` bool (true only where
                the episode ended for a reason other than a time limit), optionally
                ``demo`` ``(T,)`` bool (the steps a demonstrator acted), plus the goal
                space's fields (see :mod:`lcrl.goals`).
        """
        action = np.asarray(episode["action"], self.action_dtype)
        t = action.shape[0]
        if t < 1:
            raise LcrlError("an episode needs at least one step")
        if action.shape[1:] != self.action_shape:
            raise LcrlError(
                f"actions have shape {action.shape[1:]}; the buffer was built for "
                f"{self.action_shape}"
            )
        n = t + 1
        if n > self.capacity:
            raise LcrlError(f"an episode of {t} steps does not fit in {self.capacity} slots")
        obs = episode["obs"]
        if set(obs) != set(self.obs_spec):
            raise LcrlError(
                f"episode observations have keys {sorted(obs)}; expected {sorted(self.obs_spec)}"
            )
        for key, (shape, _) in self.obs_spec.items():
            got = np.shape(obs[key])
            if got != (n, *shape):
                raise LcrlError(f"obs[{key!r}] has shape {got}; expected {(n, *shape)}")
        start = self.ptr if self.ptr + n <= self.capacity else 0
        end = start + n
        self._drop_overlapping(start, end)
        for key in self.obs_spec:
            self._write_obs(key, start, end, obs[key])
        self.action[start : end - 1] = action
        self.env_reward[start : end - 1] = np.asarray(episode["reward"], np.float32)
        term = np.asarray(episode["terminated"], bool)
        self.terminated[start : end - 1] = term
        self.terminated[end - 1] = False
        demo = episode.get("demo")
        self.demo[start : end - 1] = False if demo is None else np.asarray(demo, bool)
        self.demo[end - 1] = False
        self.ep_start[start:end] = start
        self.ep_end[start:end] = end - 1
        self.goal_space.write(start, episode)
        self.valid[start : end - 1] = True
        self.valid[end - 1] = False
        self.ptr = end % self.capacity
        self.high = max(self.high, end)
        self.episodes_added += 1
        self.steps_added += t
        self._valid_idx = None

    def _write_obs(self, key: str, start: int, end: int, values: Any) -> None:
        """Write observation rows ``[start, end)`` of ``key`` (host or device storage)."""
        arr = self.obs[key]
        if isinstance(arr, torch.Tensor):
            arr[start:end] = torch.as_tensor(np.asarray(values, self.obs_spec[key][1])).to(
                arr.device
            )
        else:
            arr[start:end] = values

    def _gather(self, idx: np.ndarray) -> dict[str, Any]:
        """The observations at slots ``idx``: numpy arrays, or tensors on :attr:`device`
        for :attr:`device_keys`."""
        ti = torch.from_numpy(idx).to(self.device) if self.device_keys else None
        return {
            key: arr.index_select(0, ti) if isinstance(arr, torch.Tensor) else arr[idx]
            for key, arr in self.obs.items()
        }

    def host_obs(self, key: str, rows: Any = slice(None)) -> np.ndarray:
        """Rows of one observation array as numpy, wherever it is stored."""
        arr = self.obs[key][rows]
        return arr.cpu().numpy() if isinstance(arr, torch.Tensor) else arr

    def _drop_overlapping(self, start: int, end: int) -> None:
        """Invalidate every stored episode with a slot in ``[start, end)``."""
        touched = self.valid[start:end] | (self.ep_end[start:end] > 0)
        if not touched.any():
            return
        for s in np.unique(self.ep_start[start:end][touched]):
            e = self.ep_end[s]
            if e >= s and (self.ep_start[s] == s):
                self.valid[s : e + 1] = False
                self.ep_end[s : e + 1] = 0
                self.ep_start[s : e + 1] = 0
        # Forget the cached indices now: if the episode being added is then rejected (a
        # goal-space check raises), the dropped episodes must not stay sampleable.
        self._valid_idx = None

    # --- reading ---------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Number of sampleable transitions."""
        return int(self._valid_indices().size)

    def __len__(self) -> int:
        return self.size

    def _valid_indices(self) -> np.ndarray:
        if self._valid_idx is None:
            self._valid_idx = np.flatnonzero(self.valid)
            self._relabel_idx = None
        return self._valid_idx

    def _relabelable_indices(self) -> np.ndarray:
        """Valid transitions for which the strategy has an achieved goal to relabel with."""
        valid = self._valid_indices()
        if self._relabel_idx is None:
            mask = self.goal_space.relabelable(
                valid, self.ep_start[valid], self.ep_end[valid], self.strategy
            )
            self._relabel_idx = valid[mask]
        return self._relabel_idx

    def sample(self, batch_size: int, relabel: bool = True) -> Batch:
        """Sample transitions and relabel a ``k / (k + 1)`` fraction of goals (see the module
        docstring).

        Args:
            batch_size: transitions to draw (with replacement).
            relabel: set ``False`` to keep every original goal (rewards are still
                recomputed, so they agree with the goal space).
        """
        valid = self._valid_indices()
        if valid.size == 0:
            raise LcrlError("the replay buffer is empty: add an episode before sampling")
        idx = valid[self.rng.integers(0, valid.size, batch_size)]
        relabelled = np.zeros(batch_size, bool)
        which = np.zeros(0, np.int64)
        other = np.zeros(0, np.int64)
        if relabel and (self.k > 0 or self.random_fraction > 0):
            u = self.rng.random(batch_size)
            which = np.flatnonzero(u < self.relabel_ratio)
            other = np.flatnonzero(
                (u >= self.relabel_ratio) & (u < self.relabel_ratio + self.random_fraction)
            )
            pool = self._relabelable_indices() if self.only_relabelable else valid
            if which.size and pool.size:
                idx[which] = pool[self.rng.integers(0, pool.size, which.size)]
        goals = self.goal_space.desired(idx)
        if other.size:
            slots = valid[self.rng.integers(0, valid.size, other.size)]
            goals[other] = self.goal_space.random_goals(slots, self.rng)
        if which.size:
            sub = idx[which]
            new, ok = self.goal_space.relabel(
                sub, self.ep_start[sub], self.ep_end[sub], self.strategy, self.rng
            )
            goals[which] = new
            relabelled[which] = ok
        reward, terminated = self._step_reward(idx, goals, relabelled)
        nxt = idx + 1
        discount = None
        if self.n_step > 1:
            reward, terminated, nxt, discount = self._n_step_return(
                idx, goals, relabelled, reward, terminated
            )
        return Batch(
            obs=self._gather(idx),
            action=self.action[idx],
            reward=reward,
            next_obs=self._gather(nxt),
            terminated=terminated,
            goal=goals,
            relabelled=relabelled,
            index=idx,
            discount=discount,
            demo=self.demo[idx],
        )

    def _step_reward(
        self, idx: np.ndarray, goals: np.ndarray, relabelled: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Reward and terminal flag (float32) of the transitions at ``idx`` for ``goals``."""
        reward = self.goal_space.reward(idx, goals)
        terminated = self.terminated[idx].astype(np.float32)
        if self.goal_space.terminate_on_success:
            # Reaching the goal ends the episode. A relabelled goal's termination replaces
            # the stored one (which belongs to the original goal); an original goal also
            # ends at its success when the episode went on after it.
            success = self.goal_space.success(reward)
            terminated = np.where(relabelled, success, success | (terminated > 0))
            terminated = terminated.astype(np.float32)
        return reward, terminated

    def _n_step_return(
        self,
        idx: np.ndarray,
        goals: np.ndarray,
        relabelled: np.ndarray,
        reward: np.ndarray,
        terminated: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Discounted reward sums over up to ``n_step`` steps (see the class docstring)."""
        last = self.ep_end[idx] - 1  # the episode's last transition slot
        ret = reward.astype(np.float64)
        steps = np.ones(idx.size, np.int64)
        done = terminated > 0
        for j in range(1, self.n_step):
            alive = ~done & (idx + j <= last)
            if not alive.any():
                break
            p = np.minimum(idx + j, last)
            r, term = self._step_reward(p, goals, relabelled)
            ret += np.where(alive, self.gamma**j * r, 0.0)
            steps += alive
            done |= alive & (term > 0)
        discount = (self.gamma**steps).astype(np.float32)
        return ret.astype(np.float32), done.astype(np.float32), idx + steps, discount

    # --- saving ----------------------------------------------------------------------
    def _full_arrays(self) -> dict[str, np.ndarray]:
        """Every storage array at full capacity, and the counters."""
        out = {f"obs.{key}": arr for key, arr in self.obs.items()}
        out.update(
            action=self.action,
            env_reward=self.env_reward,
            terminated=self.terminated,
            demo=self.demo,
            ep_start=self.ep_start,
            ep_end=self.ep_end,
            valid=self.valid,
            counters=np.array([self.ptr, self.episodes_added, self.steps_added], np.int64),
        )
        out.update({f"goal.{key}": arr for key, arr in self.goal_space.arrays().items()})
        return out

    def arrays(self) -> dict[str, np.ndarray]:
        """Storage and counters as plain arrays (for checkpoints; no pickling).

        Only the slots written so far are kept: every per-slot array (first dimension
        ``capacity``) is cut to its first ``high`` rows, and ``extent`` holds
        ``[high, capacity]``. Before the buffer first wraps around that is the part that
        holds data; after, it is all of it.
        """
        out = {}
        for key, arr in self._full_arrays().items():
            per_slot = key != "counters" and arr.ndim >= 1 and arr.shape[0] == self.capacity
            out[key] = arr[: self.high] if per_slot else arr
            if isinstance(out[key], torch.Tensor):
                out[key] = out[key].cpu().numpy()
        out["extent"] = np.array([self.high, self.capacity], np.int64)
        return out

    def load_arrays(self, arrays: Mapping[str, np.ndarray]) -> None:
        """Restore storage saved by :meth:`arrays` into this (fresh) buffer: its capacity
        and shapes must match. Also reads the layout of earlier versions, which saved
        every slot."""
        if "extent" in arrays:
            high, capacity = (int(x) for x in arrays["extent"])
            if capacity != self.capacity:
                raise LcrlError(
                    f"saved replay buffer has capacity {capacity}; this buffer has "
                    f"{self.capacity} (buffer.capacity differs)"
                )
        else:
            high = self.capacity
        # start from fresh storage: the slots past ``high`` were never written
        for value in (
            *self.obs.values(),
            self.action,
            self.env_reward,
            self.terminated,
            self.demo,
        ):
            value[...] = 0
        self.goal_space.allocate(self.capacity)
        attach = getattr(self.goal_space, "attach", None)
        if callable(attach):
            attach(self.obs)
        expected = self._full_arrays()
        if "demo" not in arrays:  # saved before demonstrations were flagged: none
            expected.pop("demo")
        missing = sorted(set(expected) - set(arrays))
        if missing:
            raise LcrlError(f"saved replay buffer lacks {missing}")
        full: dict[str, np.ndarray] = {}
        for key, arr in expected.items():
            saved = np.asarray(arrays[key])
            if key == "counters":
                continue
            per_slot = arr.ndim >= 1 and arr.shape[0] == self.capacity
            if per_slot and saved.shape == (high, *arr.shape[1:]):
                if key.startswith("obs."):  # written row by row below; the rest stays 0
                    full[key] = saved
                    continue
                saved = np.concatenate([saved, arr[high:]]) if high < self.capacity else saved
            elif not key.startswith("goal.") and saved.shape != arr.shape:
                raise LcrlError(
                    f"saved replay buffer array {key!r} has shape {saved.shape}; this "
                    f"buffer has {arr.shape} (capacity or observation shapes differ)"
                )
            full[key] = saved
        for key in self.obs:
            saved = full[f"obs.{key}"]
            self._write_obs(key, 0, len(saved), saved)
        self.action[...] = full["action"]
        self.env_reward[...] = full["env_reward"]
        self.terminated[...] = full["terminated"]
        if "demo" in full:
            self.demo[...] = full["demo"]
        self.ep_start[...] = full["ep_start"]
        self.ep_end[...] = full["ep_end"]
        self.valid[...] = full["valid"]
        self.ptr, self.episodes_added, self.steps_added = (int(x) for x in arrays["counters"])
        self.high = high
        self.goal_space.load_arrays(
            {key[5:]: arr for key, arr in full.items() if key.startswith("goal.")}
        )
        self._valid_idx = None


def torch_dtype(dtype: Any) -> torch.dtype:
    """The torch dtype of a numpy observation dtype (device storage)."""
    try:
        return torch.from_numpy(np.empty(0, dtype)).dtype
    except TypeError:
        raise LcrlError(
            f"observations of dtype {np.dtype(dtype)} cannot be stored on a device"
        ) from None


def storage_device(device: str | torch.device) -> torch.device:
    """A buffer's storage device, checked: a clear error for a name torch does not know
    or a CUDA device this machine does not have."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise LcrlError(
            f"unknown replay storage device {device!r}; use cpu, cuda or cuda:N"
        ) from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise LcrlError(
            f"replay storage on {device!r} needs CUDA, which this machine does not have "
            "(store on the host: buffer.storage host)"
        )
    if dev.type not in ("cpu", "cuda"):
        raise LcrlError(f"replay storage on {dev.type!r} is not supported; use cpu or cuda")
    return dev
