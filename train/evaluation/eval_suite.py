"""Detailed evaluation of a checkpoint: instruction sets, families, slot values, chains.

:func:`run_evaluation` runs a policy on each instruction set of its task (seen
instructions ``train``, held-out word combinations ``heldout``, unseen phrasings
``paraphrase``, and optionally the instructions of a user file, set ``custom``) and
reports, for every set, every instruction family, every slot value of the parsed
instructions (colour, shape, direction, relation, object) and every instruction: the
success rate with a 95% Wilson confidence interval, the number of episodes and the mean
number of steps to success. State- and image-goal tasks have one set, ``all``.

Fixed task sets (``env.tasks``, ``K`` instructions): a task-id policy has one set,
``train``, its ``K`` tasks; so has a language policy trained on a task set, besides its
held-out and paraphrase sets. Episode ``i`` of that set runs task ``i mod K`` from the first
layout of its reset seed where the task is feasible
(:func:`train.environments.tasks.reset_feasible`,
the layouts of the training loop's evaluation), and its figures add success per task.

Episodes run in a gymnasium vector env (``num_envs`` copies of the task's env, stepped
together; the policy acts on the whole batch). Episode ``i`` of a set always starts from
reset seed ``EVAL_SEED_OFFSET + seed * 10_007 + i`` (the seeds of the training loop's
evaluation), each sub-env runs a fixed share of the episodes and reseeds itself for each
one, and the policy's forward pass always sees batches of :data:`POLICY_BATCH` rows
(padded), so the results do not depend on ``num_envs`` or on the vector env kind.

Chained evaluation (``chain=N``, after CALVIN): an episode is up to N instructions in a
row in one scene. Each instruction gets the env's step budget; after a success the next
instruction is drawn (with the env's seeded generator) among the set's instructions
feasible in the current scene, and its success is judged relative to the scene at the
switch (:meth:`captioner.lang_env.LanguageGoalWrapper.switch_instruction`; object
displacement features restart there too). A chain stops at the first failure. Reported:
the fraction of chains whose first k instructions all succeeded, for k = 1..N, and the
average number of instructions completed in a row.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from lcrl.errors import LcrlError
from lcrl.statistics import (
    Z95 as Z95,
    rate_stats as rate_stats,
    wilson_interval as wilson_interval,
)
from train.configs.config import TrainConfig
from train.environments.simulators import env_spec
from train.environments.tasks import (
    Task,
    make_env,
    task_texts,
)
from train.evaluation.eval_episodes import (
    EpisodeResult as EpisodeResult,
    EpisodeSpec as EpisodeSpec,
    EvalEpisodes as EvalEpisodes,
)
from train.evaluation.instruction_files import (
    FileInstruction as FileInstruction,
    read_instruction_file as read_instruction_file,
)

#: Reset seed of the first evaluation episode (seed 0): far from the training episodes' seeds.
EVAL_SEED_OFFSET = 7_777_777
#: Rows of every forward pass of the policy during evaluation (smaller batches are padded,
#: larger ones split). A row's result then never depends on how many envs run together:
#: matrix kernels pick their blocking by batch size, which changes the last bits.
POLICY_BATCH = 16
#: The set of instructions read from a user file.
CUSTOM_SET = "custom"
#: Slots broken down in the reports, in order.
SLOT_KEYS = ("colour", "shape", "direction", "relation", "object")
VECTOR_KINDS = ("auto", "sync", "async")


# --- statistics ---------------------------------------------------------------------------


# --- instruction files --------------------------------------------------------------------


# --- episodes in a vector env --------------------------------------------------------------


# --- running a set ---------------------------------------------------------------------------
def episode_seed(seed: int, i: int) -> int:
    """Reset seed of evaluation episode ``i`` (the training loop's evaluation uses the
    same seeds)."""
    return EVAL_SEED_OFFSET + seed * 10_007 + i


def default_num_envs() -> int:
    """The CPU cores this process may use, less those other busy processes keep
    (:func:`train.runtime.machine.default_threads`): on robosuite each environment is a
    process of its own, and one more busy process than cores slows every one of them."""
    from train.runtime.machine import default_threads

    return default_threads()


def _vector_kind(kind: str, cfg: TrainConfig, num_envs: int) -> str:
    if kind not in VECTOR_KINDS:
        raise LcrlError(f"unknown vector env kind {kind!r}; choose one of {VECTOR_KINDS}")
    if kind != "auto":
        return kind
    # the 2D tabletop and gymnasium-robotics envs step in microseconds: processes would
    # only add messaging; a robosuite step (physics and cameras) takes milliseconds
    slow = env_spec(cfg.env.kind).step_cost == "slow"
    return "async" if num_envs > 1 and slow else "sync"


class PolicyRunner:
    """Acts for a batch of sub-envs: goals per env, fixed-size forward passes.

    Args:
        agent: the learner (``act(obs, goal, deterministic, embedded)``).
        task: its task (observation layout, goals, action scaling).
        vectors: text -> goal embedding (language tasks).
    """

    def __init__(self, agent: Any, task: Task, vectors: dict[str, np.ndarray] | None) -> None:
        self.agent, self.task, self.vectors = agent, task, vectors or {}
        self.language = bool(task.text_goals)

    def goal(self, obs: dict[str, Any], info_goal: Any) -> Any:
        """The goal of one env's current instruction or episode."""
        if self.language:
            text = obs["instruction"]
            if text not in self.vectors:
                raise LcrlError(f"no goal embedding for instruction {text!r}")
            return self.vectors[text]
        return self.task.eval_goal(obs, info_goal)

    def act(self, obs: list[dict[str, np.ndarray]], goals: list[Any]) -> np.ndarray:
        """Deterministic actions (policy space) for the given rows."""
        keys = obs[0].keys()
        stacked = {k: np.stack([o[k] for o in obs]) for k in keys}
        goal = np.stack([np.asarray(g) for g in goals])
        out = []
        for s in range(0, len(obs), POLICY_BATCH):
            o = {k: _pad(v[s : s + POLICY_BATCH]) for k, v in stacked.items()}
            g = _pad(goal[s : s + POLICY_BATCH])
            a = self.agent.act(o, g, deterministic=True, embedded=self.language)
            out.append(np.asarray(a)[: min(POLICY_BATCH, len(obs) - s)])
        return np.concatenate(out)


def _pad(x: np.ndarray) -> np.ndarray:
    if len(x) == POLICY_BATCH:
        return x
    reps = np.repeat(x[:1], POLICY_BATCH - len(x), axis=0)
    return np.concatenate([x, reps])


def run_set(
    agent: Any,
    task: Task,
    cfg: TrainConfig,
    split_set: str,
    specs: Sequence[EpisodeSpec],
    vectors: dict[str, np.ndarray] | None = None,
    num_envs: int = 1,
    vector: str = "auto",
    chain: int = 1,
    pool: Sequence[str] | None = None,
    on_episode: Callable[[EpisodeResult], None] | None = None,
    aliases: dict[str, str] | None = None,
) -> list[EpisodeResult]:
    """Run ``specs`` on copies of the task's env for ``split_set``; results by index.

    Args:
        agent, task, cfg: the policy, its task and its config.
        split_set: which instruction set the envs draw from.
        specs: the episodes.
        vectors: goal embedding of every instruction the episodes may see.
        num_envs: sub-envs stepped together (at most one per episode).
        vector: ``sync`` (one process), ``async`` (a process per sub-env) or ``auto``.
        chain: instructions per episode at most.
        pool: sentences the next instruction of a chain is drawn from.
        on_episode: called with each finished episode (progress bars).
        aliases: canonical instruction -> the free text the policy reads for it.
    """
    if not specs:
        return []
    language = task.instructed  # instructions (or task ids of them)
    n = max(1, min(int(num_envs), len(specs)))
    shares = [list(specs[j::n]) for j in range(n)]
    start_info = type(task).start_info
    env_cfg = cfg.env

    def factory(share: list[EpisodeSpec]) -> Callable[[], gym.Env]:
        def make() -> gym.Env:
            return EvalEpisodes(
                make_env(env_cfg, split_set),
                share,
                language,
                env_cfg.max_episode_steps,
                chain=chain,
                pool=pool,
                start_info=start_info,
                aliases=aliases,
            )

        return make

    fns = [factory(share) for share in shares]
    if _vector_kind(vector, cfg, n) == "sync":
        envs: gym.vector.VectorEnv = gym.vector.SyncVectorEnv(fns, copy=False)
    else:
        # spawned, not forked: a parent that has rendered (an OpenGL / EGL context, a
        # perception model's threads) leaves locks a forked child can wait on forever
        envs = gym.vector.AsyncVectorEnv(fns, shared_memory=False, copy=False, context="spawn")
    runner = PolicyRunner(agent, task, vectors)
    results: dict[int, EpisodeResult] = {}
    try:
        obs, info = envs.reset()
        firsts: list[Any] = [None] * n
        goals: list[Any] = [None] * n
        idle = np.zeros(n, bool)
        _track(obs, info, firsts, goals, idle, runner, n)
        zero = task.scale_action(np.zeros(task.action_dim, np.float32))
        if task.discrete:
            zero = np.asarray(0)
        while len(results) < len(specs):
            active = np.flatnonzero(~idle)
            if len(active) == 0:
                raise LcrlError("evaluation envs went idle before every episode finished")
            rows = [task.storage_obs(_row(obs, i), _row(firsts[i], None)) for i in active]
            acts = runner.act(rows, [goals[i] for i in active])
            actions = np.stack([zero] * n)
            for a, i in zip(acts, active, strict=True):
                actions[i] = task.scale_action(a)
            obs, _, _, _, info = envs.step(actions)
            if "episode" in info:
                for i in np.flatnonzero(info["_episode"]):
                    res = info["episode"][i]
                    results[res.index] = res
                    if on_episode is not None:
                        on_episode(res)
            _track(obs, info, firsts, goals, idle, runner, n)
    finally:
        envs.close()
    return [results[s.index] for s in specs]


def _row(obs: Any, i: int | None) -> dict[str, Any]:
    """One env's observation dict out of a batched one (``i=None``: already one env's)."""
    if i is None:
        return obs
    return {k: v[i] for k, v in obs.items()}


def _track(
    obs: Any,
    info: dict[str, Any],
    firsts: list[Any],
    goals: list[Any],
    idle: np.ndarray,
    runner: PolicyRunner,
    n: int,
) -> None:
    """Record each env's first observation and goal when an instruction starts."""
    starts = info.get("_start", np.zeros(n, bool))
    for i in np.flatnonzero(starts):
        # the vector env reuses its observation buffers: keep a copy
        firsts[i] = {
            k: v.copy() if isinstance(v, np.ndarray) else v for k, v in _row(obs, i).items()
        }
        goal_info = info["goal"][i] if "goal" in info else None
        goals[i] = runner.goal(firsts[i], goal_info)
    if runner.language:  # the instruction may change at a start only, but keep it exact
        for i in np.flatnonzero(~idle):
            goals[i] = runner.goal(_row(obs, i), None)
    if "_idle" in info:
        idle |= info["_idle"]


# --- the whole evaluation ---------------------------------------------------------------------
def summarise(
    results: Sequence[EpisodeResult], chain: int = 1, tasks: Sequence[str] = ()
) -> dict[str, Any]:
    """Every figure of one set: overall, per family, per slot value, per instruction,
    per family and object, (``chain > 1``) the chain figures, and (``tasks``, a fixed
    task set) per task.

    In chain mode the overall, family, slot, instruction and task figures count every
    instruction attempted, first ones and later ones alike.

    Args:
        results: the set's episodes.
        chain: instructions per episode at most.
        tasks: the ``K`` task texts of a fixed task set: ``out["tasks"]`` lists, for task
            ``i``, ``id``, ``instruction``, ``family`` and :func:`rate_stats` of the
            attempts of that text (success None for a task without episodes).
    """
    checked: list[dict[str, Any]] = []
    unchecked: dict[str, int] = defaultdict(int)
    for r in results:
        for a in r.attempts:
            if a["checked"] and a["success"] is not None:
                checked.append(a)
            else:
                unchecked[a["instruction"] or ""] += 1

    def stats(attempts: list[dict[str, Any]]) -> dict[str, Any]:
        return rate_stats(
            [a["success"] for a in attempts],
            [a["steps_to_success"] for a in attempts if a["success"]],
        )

    def group(key: Callable[[dict[str, Any]], str | None]) -> dict[str, Any]:
        groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for a in checked:
            k = key(a)
            if k is not None:
                groups[k].append(a)
        return {k: stats(v) for k, v in sorted(groups.items())}

    out = stats(checked)
    out["episodes"] = len(results)
    out["attempts"] = len(checked)
    out["unchecked"] = int(sum(unchecked.values()))
    out["families"] = group(lambda a: a["slots"].get("family", "all"))
    out["slots"] = {}
    for key in SLOT_KEYS:
        g = group(lambda a, key=key: a["slots"].get(key))
        if g:
            out["slots"][key] = g
    out["family_object"] = {}
    for fam in out["families"]:

        def object_of(a: dict[str, Any], fam: str = fam) -> str | None:
            return a["slots"].get("object") if a["slots"].get("family") == fam else None

        g = group(object_of)
        if g:
            out["family_object"][fam] = g
    out["instructions"] = (
        group(lambda a: a["instruction"]) if any(a["instruction"] for a in checked) else {}
    )
    out["unchecked_instructions"] = {k: v for k, v in sorted(unchecked.items()) if k}
    if tasks:
        from captioner.grammar import try_parse

        out["tasks"] = []
        for k, text in enumerate(tasks):
            meaning = try_parse(text)
            row = {"id": k, "instruction": text, "family": meaning.family if meaning else None}
            row.update(stats([a for a in checked if a["instruction"] == text]))
            out["tasks"].append(row)
    if chain > 1:
        out["chain"] = chain_stats(results, chain)
    return out


def chain_stats(results: Sequence[EpisodeResult], chain: int) -> dict[str, Any]:
    """Chain figures: success of the first k instructions in a row (k = 1..chain) with
    Wilson intervals, the average number completed in a row, and how chains ended."""
    done = []
    stops: dict[str, int] = defaultdict(int)
    for r in results:
        if not r.attempts or not r.attempts[0]["checked"]:
            continue
        k = 0
        for a in r.attempts:
            if not a["success"]:
                break
            k += 1
        done.append(k)
        stops[r.stop] += 1
    n = len(done)
    per_length = []
    for k in range(1, chain + 1):
        s = sum(d >= k for d in done)
        low, high = wilson_interval(s, n)
        per_length.append(
            {"length": k, "success": s / n if n else None, "ci": [low, high], "chains": s}
        )
    return {
        "length": chain,
        "chains": n,
        "success": per_length,
        "average_length": float(np.mean(done)) if n else None,
        "stops": dict(sorted(stops.items())),
    }


def goal_vectors(task: Task, texts: Sequence[str]) -> dict[str, np.ndarray]:
    """Goal embeddings of ``texts``: the checkpoint's table row where the text is in it
    (what training saw), else the frozen encoder's embedding (one batch, in order)."""
    if not task.text_goals:
        return {}
    out = {t: task.embeddings[task.ids[t]] for t in texts if t in task.ids}
    missing = [t for t in dict.fromkeys(texts) if t not in out]
    if missing:
        encoded = np.asarray(task.embed_fn(missing), np.float32)
        out.update(zip(missing, encoded, strict=True))
    return out


def _set_texts(task: Task, name: str) -> list[str]:
    """Sentences of one set that the task's env can draw (its families)."""
    split = task.wrapper.split
    pairs = zip(split.texts(name), split.instructions(name), strict=True)
    return [t for t, m in pairs if m.family in task.families]


def run_evaluation(
    agent: Any,
    task: Task,
    cfg: TrainConfig,
    episodes: int,
    seed: int = 0,
    sets: Sequence[str] | None = None,
    instructions: Sequence[FileInstruction] | None = None,
    chain: int = 0,
    num_envs: int = 1,
    vector: str = "auto",
    progress: bool = False,
) -> dict[str, Any]:
    """Evaluate a policy on instruction sets; returns every figure per set.

    Args:
        agent, task, cfg: the policy, its task and its (run's) config.
        episodes: episodes (chains, with ``chain``) per set.
        seed: seed of the evaluation layouts (and instruction draws).
        sets: the task's sets to run (default all); :data:`CUSTOM_SET` is added when
            ``instructions`` are given.
        instructions: a user's instructions (:func:`read_instruction_file`); episode
            ``i`` of the ``custom`` set runs instruction ``i % len(instructions)``.
        chain: instructions per episode (CALVIN-style chains); 0 or 1: one.
        num_envs: sub-envs stepped together; does not change any result.
        vector: ``auto``, ``sync`` or ``async`` vector env.
        progress: show a progress bar over episodes.

    With a fixed task set (``cfg.env.tasks``, task ids or language goals), episode ``i``
    of the ``train`` set runs task ``i mod K`` and its figures include ``tasks``
    (:func:`summarise`); a task-id policy has that set only.

    Returns:
        ``{set name: summarise(...)}``; state- and image-goal tasks report their one set
        as ``all``.

    Raises:
        LcrlError: bad counts, unknown sets, chains or instruction files on a task
            without language goals (task ids included).
    """
    language = task.text_goals
    tasks = list(task_texts(cfg.env))
    if task.instructed and not language:
        check_task_id_options(len(tasks), sets, bool(instructions), chain)
    if episodes <= 0:
        raise LcrlError("the number of episodes must be positive")
    if num_envs <= 0:
        raise LcrlError("the number of envs must be positive")
    if chain < 0:
        raise LcrlError("the chain length must be 0 (no chains) or more")
    if chain > 1 and not language:
        raise LcrlError("chained evaluation needs a checkpoint trained with language goals")
    if instructions and not language:
        raise LcrlError(
            "an instruction file needs a checkpoint trained with language goals; this one "
            f"has {task.goal_kind} goals"
        )
    names = list(sets) if sets else list(task.sets)
    known = [*task.sets, *([CUSTOM_SET] if instructions else [])]
    bad = [s for s in names if s not in known]
    if bad:
        hint = " (custom needs --instructions FILE)" if CUSTOM_SET in bad else ""
        raise LcrlError(f"unknown sets {bad}; this task has {tuple(known)}{hint}")
    if instructions and CUSTOM_SET not in names:
        names.append(CUSTOM_SET)
    chain = max(1, chain)

    plans: list[tuple[str, str, list[EpisodeSpec], list[str] | None, list[str]]] = []
    for name in names:
        seeds = [episode_seed(seed, i) for i in range(episodes)]
        if tasks and name == "train":  # a fixed task set: round robin over the tasks
            k = len(tasks)
            specs = [EpisodeSpec(i, s, tasks[i % k], task=i % k) for i, s in enumerate(seeds)]
            plans.append((name, name, specs, list(tasks), list(tasks)))
        elif name == CUSTOM_SET:
            assert instructions is not None
            lines = list(instructions)
            specs = [_file_spec(i, s, lines[i % len(lines)]) for i, s in enumerate(seeds)]
            pool = list(dict.fromkeys(x.judged for x in lines if x.checked))
            plans.append((name, "train", specs, pool, [x.text for x in lines]))
        else:
            specs = [EpisodeSpec(i, s) for i, s in enumerate(seeds)]
            texts = _set_texts(task, name) if language else []
            plans.append((name, name, specs, None, texts))

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=episodes * len(plans), unit="episode", dynamic_ncols=True)
    out: dict[str, Any] = {}
    try:
        for name, split_set, specs, pool, texts in plans:
            if bar is not None:
                bar.set_description(name)
            results = run_set(
                agent,
                task,
                cfg,
                split_set,
                specs,
                vectors=goal_vectors(task, texts),
                num_envs=num_envs,
                vector=vector,
                chain=chain,
                pool=pool,
                on_episode=(lambda _r: bar.update(1)) if bar is not None else None,
                aliases=_aliases(instructions) if name == CUSTOM_SET else None,
            )
            key = name if task.instructed else "all"
            out[key] = summarise(results, chain, tasks if tasks and name == "train" else ())
            if name == CUSTOM_SET:
                out[key]["file_instructions"] = [asdict(x) for x in instructions or ()]
            out[key]["episode_results"] = [asdict(r) for r in results]
    finally:
        if bar is not None:
            bar.close()
    return out


def _file_spec(index: int, seed: int, line: FileInstruction) -> EpisodeSpec:
    """The episode of an instruction-file line: a line with a canonical part is judged by
    it while the policy reads the free text."""
    if line.checked and line.canonical:
        return EpisodeSpec(index, seed, line.canonical, True, reads=line.text)
    return EpisodeSpec(index, seed, line.text, line.checked)


def _aliases(lines: Sequence[FileInstruction] | None) -> dict[str, str]:
    """Canonical instruction -> the free text read for it (the first line that has it);
    instructions that are their own canonical form read themselves."""
    out: dict[str, str] = {}
    for x in lines or ():
        if x.checked and x.canonical:
            out.setdefault(x.canonical, x.text)
        elif x.checked:
            out.setdefault(x.text, x.text)
    return {k: v for k, v in out.items() if k != v}


def check_task_id_options(
    num_tasks: int, sets: Sequence[str] | None, instructions: bool, chain: int
) -> None:
    """Refuse evaluation options that a task-id policy cannot follow: instruction sets
    other than ``train`` (its ``num_tasks`` tasks), an instruction file, chains.

    Raises:
        LcrlError: one of those is asked for.
    """
    bad = [s for s in sets or () if s != "train"]
    lang = "a policy trained with language goals over the same tasks (preset lang2d-tasks-lang)"
    if bad:
        raise LcrlError(
            f"a task-id policy has one set, 'train' (its {num_tasks} tasks), not {bad}: "
            f"drop --sets; held-out and paraphrase instructions need {lang}"
        )
    if instructions:
        raise LcrlError(
            f"a task-id policy reads no text, only the ids of its {num_tasks} tasks: drop "
            f"--instructions; free-text instructions need {lang}"
        )
    if chain > 1:
        raise LcrlError(
            "chained evaluation switches instructions inside an episode, which a task-id "
            f"policy cannot follow: drop --chain; chains need {lang}"
        )


def format_summary(results: dict[str, Any]) -> str:
    """Lines for the terminal: per set the success (as ``lcrl eval`` always printed it),
    then its confidence interval, steps to success and chain figures."""
    lines = []
    for name, res in results.items():
        fams = " ".join(
            f"{f} {st['success']:.2f}"
            for f, st in res["families"].items()
            if st["success"] is not None
        )
        rate = f"{res['success']:.2f}" if res["success"] is not None else "n/a"
        count = f"{res['episodes']} episodes"
        if "chain" in res:
            count = f"{res['attempts']} instructions in {res['episodes']} chains"
        lines.append(f"{name}: success {rate} ({fams}; {count})")
        if res["success"] is not None:
            low, high = res["ci"]
            steps = res["mean_steps_to_success"]
            more = f", {steps:.1f} steps to success on average" if steps is not None else ""
            lines.append(f"  95% CI [{low:.2f}, {high:.2f}]{more}")
        if res["unchecked"]:
            lines.append(f"  {res['unchecked']} episodes not checked (free text)")
        for t in res.get("tasks", ()):
            rate = "n/a" if t["success"] is None else f"{t['success']:.2f}"
            low, high = t["ci"]
            lines.append(
                f"  task {t['id']} {t['instruction']!r}: {rate} [{low:.2f}, {high:.2f}], "
                f"{t['episodes']} episodes"
            )
        if "chain" in res:
            c = res["chain"]
            if c["chains"]:
                rates = " ".join(f"{x['length']}:{x['success']:.2f}" for x in c["success"])
                lines.append(
                    f"  chains: {rates}; average length {c['average_length']:.2f} "
                    f"of {c['length']} ({c['chains']} chains)"
                )
    return "\n".join(lines)


def evaluation_document(
    checkpoint: str | Path,
    step: int,
    cfg: TrainConfig,
    results: dict[str, Any],
    settings: dict[str, Any],
) -> dict[str, Any]:
    """Everything an evaluation report needs: where the policy comes from, the settings
    and the figures of :func:`run_evaluation`."""
    from train.configs.config import config_to_dict
    from train.evaluation.report import run_of_checkpoint, task_name
    from train.runtime.machine import machine

    run = run_of_checkpoint(checkpoint)
    task = task_name(config_to_dict(cfg)["env"])
    seed = int(settings.get("seed", 0))
    return {
        "checkpoint": str(Path(checkpoint)),
        "step": int(step),
        "run": str(run) if run is not None else None,
        "task": task,
        "settings": {"first_seed": episode_seed(seed, 0), **settings},
        "machine": machine(),
        "sets": results,
    }
