"""Teacher -> student distillation with DAgger: ``lcrl distill TEACHER_RUN``.

A policy trained on the simulator's privileged state (the teacher) is distilled into a
student that acts from what the cameras show: the object slots a perception model
estimates from each frame (``--perception MODEL``), or the camera frames and the robot's
proprioception themselves (``--image-obs``, a CNN: the GPU path). Both see the same
instruction embedding, so the student inherits the teacher's instruction table.

A student may also read the same privileged state as its teachers (``--state``): then
DAgger merges policies trained apart, one per instruction family (``--teacher-for
put=RUN``), into one policy that follows every family, and with ``--chain`` it learns
to go on from where the previous instruction left the scene.

DAgger (Ross et al., 2011), one round at a time:

1. collect ``distill.episodes_per_round`` episodes. At every step the teacher names its
   action for the true state; the action executed is the teacher's with probability
   ``beta_r = beta * beta_decay ** r`` and the student's own otherwise, so control is
   handed over round by round and the student visits the states its own mistakes lead to;
   The teacher of a state is the one of its instruction's family. With ``distill.chain``
   an achieved instruction is followed, in the same scene, by the next one (as
   ``lcrl eval --chain`` does), up to ``distill.chain_length`` in a row; with
   ``distill.roll_in`` the teacher acts some episodes' whole first instruction, so the
   student meets more of the scenes that chains go on from;
2. add every visited state, with the teacher's action, to the dataset (it only grows);
3. run ``distill.updates_per_round`` behavioural-cloning updates of the student on the
   whole dataset (:class:`lcrl.bc.BC`, squared error of the mean action).

With ``distill.init_from_teacher`` (``--init-from-teacher``) the student starts as a copy
of the teacher's actor, so the first rounds fine-tune a policy that already acts, instead of
one that learns from nothing; a student given more or wider hidden layers starts from the
teacher's grown to them (Net2Net), still acting as the teacher.

``total_steps``, ``eval_every``, ``checkpoint_every`` and ``log_every`` count rounds. The
student's checkpoints are ``bc`` policies in the format of every run (with the perception
model they act through), so ``lcrl eval``, ``lcrl act``, ``lcrl.load`` and ``lcrl report``
work unchanged. Checkpoints keep the dataset, so ``--resume`` continues exactly; a stop
inside a round goes back to the round's start.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch

from envs.features import slot_layout
from lcrl.buffer import Batch
from lcrl.errors import LcrlError
from train.configs.config import (
    BCConfig,
    ExploreConfig,
    FinetuneConfig,
    TrainConfig,
    family_teachers,
)
from train.configs.sections import SCRIPTED
from train.environments.tasks import ScriptedActor, find_language_wrapper, make_env, switch_in_place
from train.evaluation.evaluate import LoadedPolicy, build_agent, build_task, resolve_checkpoint
from train.policies.loading import load_policy
from train.training.augment import Augmentation, augmentation
from train.training.loop import attach_grounding, checkpoint_meta
from train.training.trainer import BaseTrainer, open_run

#: Seeds of the collection episodes: round r, episode e of a run with seed s.
EPISODE_SEED = 1_000_003


def labelled_batch(
    obs: dict[str, np.ndarray], action: np.ndarray, goal: np.ndarray, index: np.ndarray
) -> Batch:
    """Labelled states as a batch a behavioural-cloning student updates on (no rewards)."""
    n = len(index)
    return Batch(
        obs=obs,
        action=action,
        reward=np.zeros(n, np.float32),
        next_obs=obs,
        terminated=np.zeros(n, np.float32),
        goal=goal,
        relabelled=np.zeros(n, bool),
        index=index,
    )


def student_config(
    teacher_cfg: TrainConfig,
    *,
    perception: str = "",
    image_obs: bool = False,
    state: bool = False,
    out: str = "runs/distill",
    **overrides: Any,
) -> TrainConfig:
    """The student's run config: the teacher's environment and networks, acting through
    ``perception`` (or from ``image_obs``, or from the teacher's own privileged ``state``),
    cloned with ``algo="bc"``; ``overrides`` set
    any other :class:`TrainConfig` field (``distill``, ``total_steps`` ...). How the
    teacher's own episodes were shaped (``explore``: chains, hand-overs, a curriculum) and
    the demonstrations it started from (``finetune``) are not the student's: DAgger
    collects its episodes itself.

    Raises:
        LcrlError: not exactly one of a perception model, image observations or state.
    """
    if bool(perception) + bool(image_obs) + bool(state) != 1:
        raise LcrlError(
            "say what the student reads, one of: --perception MODEL (object slots estimated "
            "from each camera frame), --image-obs (a CNN over the frames) or --state (the "
            "teachers' privileged state: merging teachers)"
        )
    cfg = copy.deepcopy(teacher_cfg)
    env = dataclasses.replace(cfg.env, perception=perception, image_obs=image_obs)
    agent = dataclasses.replace(cfg.agent, privileged_critic=False)
    return dataclasses.replace(
        cfg,
        out=out,
        env=env,
        agent=agent,
        algo="bc",
        bc=BCConfig(loss="mse", hindsight=False),
        demos="",
        explore=ExploreConfig(),
        finetune=FinetuneConfig(),
        resume=False,
        overwrite=False,
        **overrides,
    )


def grown_layers(
    layers: list[tuple[torch.Tensor, torch.Tensor]], hidden: tuple[int, ...], seed: int = 0
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """A ReLU MLP's ``(weight, bias)`` layers (the last one the output layer) grown to the
    hidden widths ``hidden`` so that it computes the same function (Net2Net, Chen et al.
    2016). Deeper: identity layers are inserted after the last hidden layer (its outputs
    are >= 0, so ``relu(I h) = h``). Wider: a hidden layer's new units copy randomly
    chosen units' incoming weights, and each copied unit's outgoing weights are split
    among it and its copies in random positive shares that sum to one, so copies start
    equal but learn apart.

    Raises:
        LcrlError: fewer layers than the MLP has, or a layer narrower than the one it grows
            from.
    """
    layers = [(w.detach().clone(), b.detach().clone()) for w, b in layers]
    widths = tuple(w.shape[0] for w, _ in layers[:-1])
    # an added layer starts as the identity of the teacher's last hidden layer
    floor = [*widths, *[widths[-1]] * (len(hidden) - len(widths))]
    if len(hidden) < len(widths) or any(h < f for h, f in zip(hidden, floor, strict=True)):
        raise LcrlError(
            f"the student's hidden layers {tuple(hidden)} cannot grow from the teacher's "
            f"{widths}: give at least as many layers, each at least as wide"
        )
    while len(layers) - 1 < len(hidden):
        width = layers[-2][0].shape[0]
        layers.insert(-1, (torch.eye(width), torch.zeros(width)))
    gen = torch.Generator().manual_seed(seed)
    for i, target in enumerate(hidden):
        (w, b), (w_next, b_next) = layers[i], layers[i + 1]
        n = w.shape[0]
        if target == n:
            continue
        pick = torch.cat([torch.arange(n), torch.randint(n, (target - n,), generator=gen)])
        share = torch.rand(target, generator=gen) + 0.5
        share = share / torch.zeros(n).index_add_(0, pick, share)[pick]
        layers[i] = (w[pick], b[pick])
        layers[i + 1] = (w_next[:, pick] * share[None, :], b_next)
    return layers


def start_from_teacher(student: Any, teacher: Any) -> None:
    """Make ``student`` (a :class:`lcrl.algos.bc.BC` agent) act as ``teacher``'s actor:
    copy its policy network and its observation and goal normalisers. A stochastic
    actor's output layer gives its mean half (the first ``action_dim`` outputs) to a
    deterministic student. A student with more or wider hidden layers (``--hidden``)
    gets the teacher's head grown to them (:func:`grown_layers`), still acting as the
    teacher; any other difference of shape is refused.

    Raises:
        LcrlError: the teacher has no actor, or networks of other inputs, of a fusion
            other than ``concat`` when the sizes differ, or a student narrower or
            shallower than the teacher.
    """
    actor = getattr(teacher, "actor", None)
    if actor is None:
        raise LcrlError(
            f"--init-from-teacher: the teacher ({teacher.name}) has no actor network to start from"
        )
    sizes = [tuple(a.options.net.hidden) for a in (student, teacher)]
    mine, theirs = student.actor.state_dict(), actor.state_dict()
    if sizes[0] != sizes[1]:
        theirs = grown_head(theirs, sizes[0], sizes[1], student.options.net)
    if mine.keys() != theirs.keys():
        only_one = sorted(set(mine) ^ set(theirs))
        raise LcrlError(
            f"--init-from-teacher: the student's policy network has other layers than the "
            f"teacher's ({only_one[0]} is in one only): keep the teacher's networks"
        )
    weights = {}
    for key, w in mine.items():
        t = theirs[key]
        if t.shape != w.shape and t.shape[1:] == w.shape[1:] and t.shape[0] == 2 * w.shape[0]:
            t = t[: w.shape[0]]  # the mean half of a Gaussian actor's output
        if t.shape != w.shape:
            raise LcrlError(
                f"--init-from-teacher: the student's {key} is {tuple(w.shape)}, the teacher's "
                f"{tuple(theirs[key].shape)}: keep the teacher's networks"
            )
        weights[key] = t
    norms = teacher.norms.state_dict()
    if student.norms.state_dict().keys() != norms.keys():
        raise LcrlError(
            f"--init-from-teacher: the student normalises {sorted(student.norms)}, the "
            f"teacher {sorted(teacher.norms)}"
        )
    student.actor.load_state_dict(weights)
    student.norms.load_state_dict(norms)
    student.reset_average()


def grown_head(
    theirs: dict[str, torch.Tensor], hidden: tuple[int, ...], had: tuple[int, ...], net: Any
) -> dict[str, torch.Tensor]:
    """The teacher actor's weights ``theirs`` with its head's MLP (hidden layers ``had``)
    grown to the student's ``hidden`` layers (:func:`grown_layers`).

    Raises:
        LcrlError: a head other than one ``concat`` MLP, or sizes it cannot grow to.
    """
    if net.fusion != "concat" or net.task_heads:
        raise LcrlError(
            f"--init-from-teacher: the student's hidden layers are {hidden}, the teacher's "
            f"{had}; only a concat head without task heads can grow: keep the teacher's "
            "networks (no --hidden)"
        )
    prefix = "head.net."
    count = len(had) + 1
    keys = [(f"{prefix}{2 * i}.weight", f"{prefix}{2 * i}.bias") for i in range(count)]
    if any(k not in theirs for pair in keys for k in pair):
        raise LcrlError(
            f"--init-from-teacher: the teacher's head is not an MLP of {had}: keep the "
            "teacher's networks (no --hidden)"
        )
    try:
        grown = grown_layers([(theirs[w], theirs[b]) for w, b in keys], hidden)
    except LcrlError as e:
        raise LcrlError(f"--init-from-teacher: {e} (--hidden)") from None
    out = {k: v for k, v in theirs.items() if not k.startswith(prefix)}
    for i, (w, b) in enumerate(grown):
        out[f"{prefix}{2 * i}.weight"], out[f"{prefix}{2 * i}.bias"] = w, b
    return out


class DistillTrainer(BaseTrainer):
    """DAgger from a privileged-state teacher (``cfg.distill.teacher``, with
    ``cfg.distill.teachers`` for some families) into a ``bc`` student that acts from
    camera frames, or from the same state.

    Args:
        cfg: the student's run config (:func:`student_config`). With ``cfg.resume`` the
            latest checkpoint in ``cfg.out`` is loaded, with its config (and
            ``cfg.total_steps``).
        new_perception: with ``cfg.resume``, a perception model the student acts through
            from the next round on (one fine-tuned on the student's own frames): the
            rounds gathered before keep their estimates, new rounds read the new model's.

    Raises:
        LcrlError: no teacher, a teacher without language goals or of another environment
            than the student's, a family's teacher without that family's instructions, or
            a student with a privileged critic.
    """

    unit = "round"

    def __init__(self, cfg: TrainConfig, new_perception: str = "") -> None:
        cfg.validate()
        if not cfg.distill.teacher:
            raise LcrlError("distillation needs a teacher: lcrl distill TEACHER_RUN")
        if cfg.algo != "bc":
            raise LcrlError(f"the student is a bc policy, not {cfg.algo!r}")
        teacher = load_policy(resolve_checkpoint(cfg.distill.teacher))
        self.teacher = teacher
        self.family_teachers: dict[str, LoadedPolicy] = {}
        self.scripted_families: list[str] = []
        self.chain_teacher: LoadedPolicy | None = None
        self.env: Any = None
        try:
            given = cfg.distill
            self._load_teachers(given)
            self.out = Path(cfg.out)
            if new_perception and not cfg.resume:
                raise LcrlError(
                    "--new-perception changes the model a student resumes with: add --resume"
                )
            cfg, ckpt = open_run(cfg, perception=new_perception)
            saved = cfg.distill  # a resumed run keeps the teachers it started with
            #: The round from which the updates' rows are augmented (0: from the start).
            self.augment_from = 0
            if ckpt is not None and given.augment and given.augment != saved.augment:
                cfg.distill = saved = dataclasses.replace(saved, augment=given.augment)
                self.augment_from = -1  # from the checkpoint's round: set by restore
            if (saved.teachers, saved.chain_teacher) != (given.teachers, given.chain_teacher):
                self._close_envs(teachers_only=True)
                self._load_teachers(saved)
            self.cfg = cfg
            self.algo = "bc"
            self.env = make_env(cfg.env, "train", training=True)
            self._build(ckpt)
        except BaseException:
            self._close_envs()
            raise

    def _load_teachers(self, distill: Any) -> None:
        """The family teachers and the chain's teacher of ``distill``."""
        self.family_teachers, self.scripted_families, self.chain_teacher = {}, [], None
        if distill.chain_teacher not in ("", SCRIPTED):
            self.chain_teacher = load_policy(resolve_checkpoint(distill.chain_teacher))
        for family, run in family_teachers(distill.teachers).items():
            if run == SCRIPTED:
                self.scripted_families.append(family)
            else:
                self.family_teachers[family] = load_policy(resolve_checkpoint(run))

    def _check_teacher(self, teacher: LoadedPolicy) -> None:
        """Refuse a teacher that cannot label the student's states."""
        cfg = self.cfg
        if teacher.task.query != "text":
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} was not trained with language goals "
                f"({teacher.cfg.env.goal_type} goals): DAgger here distils instruction-"
                "following policies"
            )
        if teacher.cfg.env.image_obs or teacher.cfg.env.perception:
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} acts from camera frames itself: a "
                "teacher reads the privileged state"
            )
        theirs = tuple(teacher.task.problem().obs_shapes["observation"])
        ours = tuple(self.env.observation_space[self._source].shape)
        if theirs != ours or teacher.cfg.env.kind != cfg.env.kind:
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} reads the {teacher.cfg.env.kind} env's "
                f"state of shape {theirs}; the student's {cfg.env.kind} env gives {ours}: "
                "distil a teacher of the same environment and observation features"
            )

    def _check_family_teachers(self) -> None:
        """Each family's teacher knows every training instruction of its family."""
        wrapper = find_language_wrapper(self.env)
        texts = wrapper.split.texts(wrapper.split_set)
        meanings = wrapper.split.instructions(wrapper.split_set)
        for family in [*self.family_teachers, *self.scripted_families]:
            if family not in wrapper.families:
                raise LcrlError(
                    f"--teacher-for {family}=...: the student's env has the families "
                    f"{', '.join(wrapper.families)}"
                )
        teachers = list(self.family_teachers.items())
        if self.chain_teacher is not None:
            teachers += [(family, self.chain_teacher) for family in wrapper.families]
        for family, teacher in teachers:
            self._check_teacher(teacher)
            mine = [t for t, m in zip(texts, meanings, strict=True) if m.family == family]
            missing = [t for t in mine if t not in teacher.task.ids]
            if missing:
                raise LcrlError(
                    f"the {family} teacher {teacher.checkpoint.path} was not trained on "
                    f"{len(missing)} of the student's {len(mine)} {family} instructions "
                    f"(e.g. {missing[0]!r}): a family's teacher needs the same split"
                )

    def _build(self, ckpt: Any) -> None:
        cfg, teacher = self.cfg, self.teacher
        space = self.env.observation_space
        self._source = "privileged" if "privileged" in space.spaces else "observation"
        self._check_teacher(teacher)
        self._check_family_teachers()
        # the teacher's ids, unless the student follows other families (--families): a
        # student of several family teachers has the table of its own families
        same = tuple(cfg.env.families) == tuple(teacher.cfg.env.families)
        table = (list(teacher.task.table), teacher.task.num_train) if same else None
        self.task = build_task(cfg, self.env, ckpt, table=None if ckpt else table)
        if same and list(self.task.table) != list(teacher.task.table):
            raise LcrlError(
                "the student's instruction table differs from the teacher's: resume with the "
                "run's own config"
            )
        self._teacher_ids = list(self.task.table) == list(teacher.task.table)
        self.problem = self.task.problem()
        if self.problem.privileged:
            raise LcrlError("the student is a policy: it reads no privileged state")
        self.agent = build_agent("bc", self.problem, cfg, self.task.goal_space.embed)
        self.keys = list(self.problem.obs_shapes)
        self.data: dict[str, list[np.ndarray]] = {k: [] for k in [*self.keys, "action", "goal"]}
        self.rng = np.random.default_rng([cfg.seed, 3])
        self.step = 0
        self.episodes = 0
        self.rows = 0
        self._round: dict[str, float] = {}
        self._start: dict[str, Any] | None = None
        self.lang = find_language_wrapper(self.env)
        self.augment = self._augmentation()
        self.scripted = None
        if self.scripted_families or cfg.distill.chain_teacher == SCRIPTED:
            # the controller that reads everything off the scene
            self.scripted = ScriptedActor(
                cfg.env, self.task, 0.0, teacher=True, funnel=cfg.distill.scripted_funnel
            )
        if ckpt is not None:
            self.restore(ckpt)
        elif cfg.distill.init_from_teacher:
            start_from_teacher(self.agent, teacher.agent)
        else:
            self.agent.observe({}, self.task.embeddings[: self.task.num_train])
        attach_grounding(self.agent, self.task, cfg)

    def _augmentation(self) -> Augmentation | None:
        """The augmentations of ``distill.augment`` for the student's rows (None: off)."""
        if not self.cfg.distill.augment:
            return None
        return augmentation(
            self.cfg.distill.augment,
            self.task.table,
            self.task.num_train,
            slot_layout(self.env),
            int(self.problem.obs_shapes["observation"][0]),
            self.problem.discrete,
        )

    # --- the loop --------------------------------------------------------------------
    def begin(self) -> None:
        """Say who teaches whom."""
        cfg = self.cfg
        if cfg.env.perception:
            how = f"acting through perception {cfg.env.perception}"
        elif cfg.env.image_obs:
            how = "acting through camera frames"
        else:
            how = "acting from the same state"
        others = "".join(
            f", {family}: {t.checkpoint.path} (step {t.checkpoint.meta.get('step')})"
            for family, t in self.family_teachers.items()
        ) + "".join(f", {family}: the scripted controller" for family in self.scripted_families)
        if cfg.distill.chain_teacher:
            who = (
                self.chain_teacher.checkpoint.path
                if self.chain_teacher
                else "the scripted controller"
            )
            others += f", after the first instruction of a chain: {who}"
        chain = f"; chains of up to {cfg.distill.chain_length}" if cfg.distill.chain else ""
        if self.augment is not None:
            since = f" from round {self.augment_from + 1} on" if self.augment_from else ""
            chain += f"; every update's rows augmented{since}: {self.augment.describe()}"
        if cfg.distill.roll_in:
            chain += f", the teacher acting the first instruction of {cfg.distill.roll_in:.0%}"
        if self.scripted is not None and cfg.distill.scripted_funnel:
            width = cfg.distill.scripted_funnel * 100
            chain += f"; the scripted put and stack lower along a {width:g} cm funnel"
        print(
            f"DAgger: teacher {self.teacher.checkpoint.path} (step "
            f"{self.teacher.checkpoint.meta.get('step')}){others} -> student {how}; "
            f"{cfg.distill.episodes_per_round} episodes and {cfg.distill.updates_per_round} "
            f"updates per round{chain}"
        )

    def beta(self, round_index: int) -> float:
        """The teacher's share of the executed actions in a round."""
        d = self.cfg.distill
        return float(d.beta * d.beta_decay**round_index) if round_index else float(d.beta)

    def advance(self) -> None:
        """One DAgger round: collect with the mixed policy, label with the teacher,
        aggregate, fit the student."""
        self._start = self.snapshot()
        cfg = self.cfg
        beta = self.beta(self.step)
        teacher_steps, steps, successes, chained, chained_ok = 0, 0, 0, 0, 0
        for e in range(cfg.distill.episodes_per_round):
            seed = int(cfg.seed * EPISODE_SEED * 7 + self.step * 1000 + e)
            rows, executed, achieved = self._episode(seed, beta)
            teacher_steps += executed
            steps += rows
            successes += int(achieved[0])
            chained += len(achieved) - 1
            chained_ok += sum(achieved[1:])
        losses = []
        for _ in range(cfg.distill.updates_per_round):
            losses.append(self.agent.update(self._batch())["loss"])
        with self.holding_signals():  # a round is counted whole, or not at all
            self.step += 1
            self.episodes += cfg.distill.episodes_per_round
            self._round = {
                "beta": beta,
                "teacher_share": teacher_steps / max(steps, 1),
                "success": successes / cfg.distill.episodes_per_round,
                "rows": float(self.rows),
                **(
                    {"chained": float(chained), "chained_success": chained_ok / max(chained, 1)}
                    if cfg.distill.chain
                    else {}
                ),
                "loss": float(np.mean(losses)) if losses else float("nan"),
                "loss_first": float(losses[0]) if losses else float("nan"),
            }
            self._start = None

    def _teacher(self, goal: int, link: int = 0) -> tuple[LoadedPolicy | None, np.ndarray]:
        """The teacher of the running instruction (by its family, or the chain's teacher
        from the second instruction of a chain, ``link`` > 0; None: the scripted
        controller) and the instruction's id in that teacher's table, as a batch of one."""
        family = self.lang.meaning.family
        if link > 0 and self.cfg.distill.chain_teacher:
            teacher = self.chain_teacher
        elif family in self.scripted_families:
            teacher = None
        else:
            teacher = self.family_teachers.get(family, self.teacher)
        if teacher is None or (teacher is self.teacher and self._teacher_ids):
            return teacher, np.asarray([goal])  # the student's own ids
        text = self.task.table[goal]
        if text not in teacher.task.ids:
            raise LcrlError(
                f"the teacher {teacher.checkpoint.path} has no instruction {text!r}: give "
                f"{family} a teacher of its own (--teacher-for {family}=RUN or =scripted)"
            )
        return teacher, np.asarray([teacher.task.ids[text]])

    def _label(
        self,
        teacher: LoadedPolicy | None,
        goal: np.ndarray,
        obs: dict[str, Any],
        first: dict[str, Any],
    ) -> np.ndarray:
        """The teacher's action (policy units) for the env's current state."""
        if teacher is None:
            return self.scripted.act(self.env, self.rng)
        view = {"observation": obs[self._source]}
        theirs = teacher.task.storage_obs(view, {"observation": first[self._source]})
        return teacher.agent.act({k: v[None] for k, v in theirs.items()}, goal, deterministic=True)[
            0
        ]

    def _episode(self, seed: int, beta: float) -> tuple[int, int, list[bool]]:
        """One episode under the mixed policy (a chain of instructions with
        ``distill.chain``); every visited state is kept with its teacher's action. Returns
        the rows added, the teachers' executed steps and, per instruction, whether it was
        achieved."""
        env, task, chain = self.env, self.task, self.cfg.distill
        obs, _ = env.reset(seed=seed)
        if self.scripted is not None:
            self.scripted.reset()
        first = obs
        goal = task.goal(obs, env)
        goal_batch = np.asarray([goal])
        teacher, theirs_goal = self._teacher(goal)
        rows: dict[str, list[np.ndarray]] = {k: [] for k in self.data}
        executed, success, achieved = 0, False, []
        # roll-in: the teacher acts the whole first instruction, the student the next ones
        rolled = bool(chain.roll_in) and self.rng.random() < chain.roll_in
        while True:
            mine = task.storage_obs(obs, first)
            label = self._label(teacher, theirs_goal, obs, first)
            for k in self.keys:
                rows[k].append(mine[k])
            rows["action"].append(np.asarray(label, np.float32))
            rows["goal"].append(np.asarray(goal, np.int64))
            if (rolled and not achieved) or self.rng.random() < beta:
                action = label
                executed += 1
            else:
                batch = {k: v[None] for k, v in mine.items()}
                action = self.agent.act(batch, goal_batch, deterministic=True)[0]
            obs, _, terminated, truncated, info = env.step(task.scale_action(action))
            success = success or bool(info.get("is_success", False))
            if not (terminated or truncated):
                continue
            achieved.append(success)
            go_on = success and chain.chain and len(achieved) < chain.chain_length
            if not (go_on and self.rng.random() < chain.chain):
                break
            following = switch_in_place(env, obs)
            if following is None:  # no instruction feasible in this scene
                break
            obs = first = following
            goal = task.goal(obs, env)
            goal_batch = np.asarray([goal])
            teacher, theirs_goal = self._teacher(goal, len(achieved))
            success = False
        for k, v in rows.items():
            self.data[k].append(np.stack(v))
        n = len(rows["action"])
        self.rows += n
        self.agent.observe({k: np.stack(rows[k]) for k in self.keys})
        return n, executed, achieved

    def _batch(self) -> Batch:
        """Rows drawn uniformly from everything gathered so far."""
        arrays = self._arrays()
        idx = self.rng.integers(self.rows, size=self.cfg.batch_size)
        obs = {k: arrays[k][idx] for k in self.keys}
        goal, action = arrays["goal"][idx], arrays["action"][idx]
        if self.augment is not None:
            obs, goal, action = self.augment.apply(obs, goal, action, self.rng)
        return labelled_batch(obs, action, goal, idx)

    def _arrays(self) -> dict[str, np.ndarray]:
        """The dataset as one array per key (consolidated on first use after a round)."""
        for k, parts in self.data.items():
            if len(parts) > 1:
                self.data[k] = [np.concatenate(parts)]
        return {k: parts[0] for k, parts in self.data.items()}

    # --- stopping inside a round --------------------------------------------------------
    def snapshot(self) -> dict[str, Any]:
        """What a round changes before it is counted, copied."""
        return {
            "modules": {
                name: copy.deepcopy(m.state_dict()) for name, m in self.agent.modules().items()
            },
            "states": copy.deepcopy(self.agent.states()),
            "rng": self.rng.bit_generator.state,
            "data": {k: list(v) for k, v in self.data.items()},
            "rows": self.rows,
        }

    def rollback(self) -> None:
        """Undo the round in hand (nothing between rounds)."""
        start = self._start
        if start is None:
            return
        for name, module in self.agent.modules().items():
            module.load_state_dict(start["modules"][name])
        self.agent.load_states(start["states"])
        self.rng.bit_generator.state = start["rng"]
        self.data, self.rows = start["data"], start["rows"]
        self._start = None

    # --- logging ---------------------------------------------------------------------
    def postfix(self) -> str:
        """The last round's teacher share and loss, and the last evaluation."""
        r = self._round
        text = f"beta {r['beta']:.2f} loss {r['loss']:.4g} " if r else ""
        return text + super().postfix()

    def log(self) -> None:
        """A progress.csv row per round: the teacher's share, the students' loss, the
        mixed policy's success, the dataset's size."""
        row: dict[str, Any] = {
            "step": self.step,
            "episodes": self.episodes,
            "updates": self.agent.updates,
            "steps_per_s": self.rate(),
            **self._round,
        }
        self.progress_log.write(row)
        self.last_logged = self.step
        if self.tb is not None:
            for k, v in row.items():
                if k != "step":
                    self.tb.add_scalar(f"train/{k}", v, self.step)

    # --- checkpoints -----------------------------------------------------------------
    def save(self) -> Path:
        """Checkpoint the student (with the perception model it acts through), the
        dataset and the random state."""
        cfg = self.cfg
        meta, json_files = checkpoint_meta(
            cfg,
            self.algo,
            self.problem,
            self.env,
            self.task,
            self.step,
            self.episodes,
            self.eval_pending,
        )
        meta["distill"] = {
            "teacher": str(self.teacher.checkpoint.path),
            "teacher_step": self.teacher.checkpoint.meta.get("step"),
            "rows": self.rows,
            "init_from_teacher": bool(cfg.distill.init_from_teacher),
        }
        if cfg.distill.augment:
            meta["distill"]["augment"] = {
                "kind": cfg.distill.augment,
                "from_round": self.augment_from,
            }
        if self.family_teachers or self.scripted_families:
            meta["distill"]["teachers"] = {
                **{
                    family: {"path": str(t.checkpoint.path), "step": t.checkpoint.meta.get("step")}
                    for family, t in self.family_teachers.items()
                },
                **{family: {"path": SCRIPTED} for family in self.scripted_families},
            }
        if self.cfg.distill.chain_teacher:
            t = self.chain_teacher
            meta["distill"]["chain_teacher"] = (
                {"path": SCRIPTED}
                if t is None
                else {"path": str(t.checkpoint.path), "step": t.checkpoint.meta.get("step")}
            )
        states = {
            **self.agent.states(),
            "trainer": {
                "step": self.step,
                "episodes": self.episodes,
                "round": self._round,
                "train_s": self.train_seconds(),
                "augment_from": self.augment_from,
            },
            "rng": self.rng.bit_generator.state,
        }
        arrays = {f"data_{k}": v for k, v in self._arrays().items()} if self.rows else None
        return self.write_checkpoint(meta, json_files, states, arrays)

    def restore(self, ckpt: Any) -> None:
        """The student, the dataset and the random state of a checkpoint."""
        self.resume_schedule(ckpt)
        for name, module in self.agent.modules().items():
            ckpt.load_module(name, module)
        self.agent.load_states({name: ckpt.state(name) for name in self.agent.states()})
        trainer = ckpt.state("trainer")
        self.step = int(trainer["step"])
        self.episodes = int(trainer["episodes"])
        self._round = dict(trainer.get("round") or {})
        # seconds before this resume, so a run's train_s counts every session of it
        self.train_s_before = float(trainer.get("train_s", 0.0))
        if self.augment_from < 0:  # switched on by this resumption
            self.augment_from = self.step
        else:
            self.augment_from = int(trainer.get("augment_from", 0))
        self.rng.bit_generator.state = ckpt.state("rng")
        if ckpt.has_arrays():
            arrays = ckpt.arrays()
            self.data = {k: [np.asarray(arrays[f"data_{k}"])] for k in self.data}
            self.rows = len(self.data["action"][0])
        print(f"resumed {self.out} at round {self.step} ({self.rows} labelled states)")

    def _close_envs(self, teachers_only: bool = False) -> None:
        if self.env is not None and not teachers_only:
            self.env.close()
        extra = [self.chain_teacher] if self.chain_teacher is not None else []
        main = [] if teachers_only else [self.teacher]
        for teacher in [*main, *self.family_teachers.values(), *extra]:
            teacher.env.close()

    def close(self) -> None:
        """Close the environments and TensorBoard."""
        self._close_envs()
        super().close()
