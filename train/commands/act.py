"""``lcrl act``: run a policy on free-text instructions, one at a time or interactively.

For each instruction the command prints how the rule captioner reads it (or that it cannot,
in which case the episodes still run but success is not checked), the training
instructions nearest to it in the text encoder's embedding space, one line per episode
and the success rate. Episodes of an instruction the captioner can check start from
layouts where it is feasible (its objects are on the table, it does not already hold).

Policies trained on a fixed task set (``env.tasks``) also run one of their tasks by id or
text (``--task``); task-id policies (``env.goal_type="task"``) take nothing else. Their
episodes start, like checked instructions, from layouts where the task is feasible.

Videos (``.mp4`` or ``.gif``) show the instruction (or task) on every frame and hold each
episode's last frame for a moment with its outcome written on it. Small renders are
enlarged by an integer factor (nearest neighbour) so the text stays readable.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import gymnasium as gym
import numpy as np

from lcrl.errors import LcrlError
from train.policies.policy import Neighbour, Policy, check_instruction

#: Video formats ``--video`` can write.
VIDEO_SUFFIXES = (".mp4", ".gif")
#: Frames narrower than this are enlarged by an integer factor before text is drawn.
MIN_VIDEO_WIDTH = 384
#: Layouts tried per episode to find one where a checkable instruction is feasible.
LAYOUT_TRIES = 50
#: Lines that end an interactive session (besides an empty line and end of input).
QUIT_WORDS = ("quit", "exit")

_OUTCOME_COLOURS = {
    "success": (70, 210, 70),
    "failure": (235, 70, 60),
    "not checked": (230, 230, 230),
}


# --- frames and videos ---------------------------------------------------------------------
def check_video_path(path: str | Path) -> Path:
    """``path`` as a Path, or an error when it does not end in ``.mp4`` or ``.gif``."""
    p = Path(path)
    if p.suffix.lower() not in VIDEO_SUFFIXES:
        raise LcrlError(f"--video must name an .mp4 or .gif file, got {str(path)!r}")
    return p


def numbered_path(path: Path, number: int) -> Path:
    """``clip.gif`` -> ``clip_003.gif`` (one video per instruction)."""
    return path.with_name(f"{path.stem}_{number:03d}{path.suffix}")


def upscale(frame: np.ndarray, min_width: int = MIN_VIDEO_WIDTH) -> np.ndarray:
    """``frame`` enlarged by the smallest integer factor that makes it at least
    ``min_width`` pixels wide (each pixel repeated; unchanged when already as wide)."""
    frame = np.ascontiguousarray(frame, np.uint8)
    factor = max(1, math.ceil(min_width / frame.shape[1]))
    if factor == 1:
        return frame.copy()
    return np.repeat(np.repeat(frame, factor, axis=0), factor, axis=1)


def _wrap(text: str, width: int, font: int, scale: float, thickness: int) -> list[str]:
    import cv2

    def fits(s: str) -> bool:
        return cv2.getTextSize(s, font, scale, thickness)[0][0] <= width

    lines: list[str] = []
    line = ""
    for word in text.split():
        while not fits(word) and len(word) > 1:  # a word wider than the frame: cut it
            cut = len(word) - 1
            while cut > 1 and not fits(word[:cut]):
                cut -= 1
            if line:
                lines.append(line)
                line = ""
            lines.append(word[:cut])
            word = word[cut:]
        candidate = f"{line} {word}" if line else word
        if fits(candidate):
            line = candidate
        else:
            lines.append(line)
            line = word
    if line:
        lines.append(line)
    return lines


def draw_text(
    frame: np.ndarray,
    text: str,
    top: bool = True,
    colour: tuple[int, int, int] = (255, 255, 255),
) -> np.ndarray:
    """A copy of the RGB ``frame`` with ``text`` written across a darkened band at its top
    (or bottom), wrapped over as many lines as it needs."""
    import cv2

    out = np.ascontiguousarray(frame, np.uint8).copy()
    h, w = out.shape[:2]
    text = "".join(c if 32 <= ord(c) < 127 else "?" for c in text)  # the font is ASCII only
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = max(0.35, w / 700)
    thickness = 1 if scale < 0.8 else 2
    pad = max(3, w // 80)
    lines = _wrap(text, w - 2 * pad, font, scale, thickness) or [""]
    (_, text_h), baseline = cv2.getTextSize("Ag", font, scale, thickness)
    line_h = text_h + baseline + pad // 2
    band = min(h, len(lines) * line_h + 2 * pad)
    y0 = 0 if top else h - band
    out[y0 : y0 + band] = (out[y0 : y0 + band].astype(np.float32) * 0.3).astype(np.uint8)
    for n, line in enumerate(lines):
        y = y0 + pad + n * line_h + text_h
        if y > y0 + band:
            break
        cv2.putText(out, line, (pad, y), font, scale, colour, thickness, cv2.LINE_AA)
    return out


def annotate_episode(
    frames: Sequence[np.ndarray],
    text: str | None,
    outcome: str,
    hold: int,
    detail: str = "",
) -> list[np.ndarray]:
    """An episode's frames for a video: enlarged, ``text`` on each, and the last frame
    repeated ``hold`` more times, all of those with the ``outcome`` (``success``,
    ``failure`` or ``not checked``) written at the bottom."""
    frames = [f for f in frames if f is not None]
    if not frames:
        return []
    out = [upscale(f) for f in frames]
    if text:
        out = [draw_text(f, text) for f in out]
    label = outcome + (f" - {detail}" if detail else "")
    last = draw_text(out[-1], label, top=False, colour=_OUTCOME_COLOURS.get(outcome, (255,) * 3))
    return [*out[:-1], *([last] * (hold + 1))]


def save_video(path: str | Path, frames: Sequence[np.ndarray], fps: int = 10) -> Path:
    """Write RGB uint8 frames ``(H, W, 3)`` to an ``.mp4`` (OpenCV's mp4v codec) or an
    animated ``.gif`` (Pillow; it stores runs of identical frames as one longer frame)."""
    path = check_video_path(path)
    frames = [np.ascontiguousarray(f, np.uint8) for f in frames if f is not None]
    if not frames:
        raise LcrlError("no frames to save: the environment did not render")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        duration = max(20, round(1000 / fps))  # most viewers play faster GIFs at 10 fps
        images[0].save(path, save_all=True, append_images=images[1:], duration=duration, loop=0)
        return path
    import cv2

    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        raise LcrlError(f"cannot write a video to {path} (OpenCV has no mp4v encoder here)")
    try:
        for frame in frames:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return path


# --- running instructions ----------------------------------------------------------------
@dataclass
class InstructionResult:
    """What happened when a policy ran on one instruction."""

    text: str
    """The instruction, whitespace collapsed."""
    canonical: str | None
    """The captioner's reading of it (None: it cannot check this text)."""
    nearest: list[Neighbour]
    """The nearest training instructions by embedding cosine similarity."""
    steps: list[int] = field(default_factory=list)
    """Length of each episode."""
    successes: list[bool] = field(default_factory=list)
    """Whether each episode succeeded (empty when success is not checked)."""
    video: Path | None = None
    """The video written, if any."""

    @property
    def success_rate(self) -> float | None:
        """Fraction of successful episodes (None when success is not checked)."""
        return float(np.mean(self.successes)) if self.successes else None


class ActSession:
    """Runs a policy's episodes on instructions and prints what happened.

    Args:
        policy: the loaded policy.
        env: the environment to run in (rendering, when videos are wanted).
        episodes: episodes per instruction.
        seed: seed of the first layout; episode ``i`` starts from layout ``seed + i`` (or,
            when the instruction is not feasible there, from ``seed + i + k * episodes``
            for the first ``k`` where it is).
        deterministic: take the policy's mean action.
        fps: video frame rate.
        hold: seconds each episode's last frame is shown with its outcome.
        out: where the lines go (``print``'s ``file``).
    """

    def __init__(
        self,
        policy: Policy,
        env: gym.Env,
        episodes: int,
        seed: int = 0,
        deterministic: bool = True,
        fps: int = 10,
        hold: float = 1.0,
        out: TextIO | None = None,
    ) -> None:
        if episodes <= 0:
            raise LcrlError("--episodes must be positive")
        if fps <= 0:
            raise LcrlError("--fps must be positive")
        if hold < 0:
            raise LcrlError("--hold must not be negative")
        self.policy, self.env = policy, env
        self.episodes, self.seed, self.deterministic = episodes, seed, deterministic
        self.fps, self.hold_frames = fps, round(hold * fps)
        self.out = out

    def _print(self, *args: Any) -> None:
        print(*args, file=self.out or sys.stdout, flush=True)

    def reading(self, text: str) -> tuple[Any, str]:
        """The captioner's :class:`~captioner.grammar.Instruction` for ``text`` when it can
        check it in this environment (else None), and a line saying how it reads it."""
        from captioner.grammar import try_parse
        from train.environments.tasks import find_language_wrapper

        meaning = try_parse(text)
        if meaning is None:
            return None, f"{text!r}: the captioner cannot parse it, so success is not checked"
        checkable = find_language_wrapper(self.env).split.families
        if meaning.family not in checkable:
            return None, (
                f"{text!r} -> {meaning.text!r}: this environment cannot check {meaning.family} "
                "instructions, so success is not checked"
            )
        trained = self.policy.families
        note = "" if meaning.family in trained else f" (not a family it was trained on: {trained})"
        return meaning, f"{text!r} -> {meaning.text!r}{note}"

    def run_text(self, text: str, video: Path | None = None) -> InstructionResult:
        """Run :attr:`episodes` episodes on one instruction; print and return the outcome."""
        if self.policy.takes_task_ids:
            raise LcrlError(
                "this policy was trained with task ids: it reads no text; give one of its "
                f"tasks by id or text: {self.policy.describe_tasks()}"
            )
        text = check_instruction(text)
        if video is not None:
            check_video_path(video)
        meaning, line = self.reading(text)
        vector = self.policy.embed(text)[0]
        result = InstructionResult(text, meaning.text if meaning else None, [])
        result.nearest = self.policy.nearest(text, 3)
        self._print(line)
        reader = self.policy.task.encoder
        if hasattr(reader, "canonical"):  # --canonical-reader: the sentence the policy reads
            self._print(f"the reader reads it as {reader.canonical([text])[0]!r}")
        self._print("nearest training instructions (cosine similarity):")
        for n in result.nearest:
            self._print(f"  {n.similarity:.3f}  {n.text}")
        route = getattr(self.policy.agent, "route", None)
        if route is not None:  # experts routed by family (lcrl route)
            family = route(self.policy.embed([text]))[0]
            owner = self.policy.agent.expert_of(family)
            who = "the base policy" if owner == "base" else f"the {owner} expert"
            self._print(f"routed as {family}: {who} acts")
        return self._run_episodes(result, meaning, vector, text, video)

    def run_chain(self, texts: Sequence[str], video: Path | None = None) -> list[list[bool]]:
        """Run :attr:`episodes` chains: each starts on ``texts[0]`` and, once an instruction
        is achieved, goes on with the next in the same scene (as ``lcrl eval --chain``: the
        scene then is the reference that success is judged against, and the displacement
        features restart). Each instruction has the env's step limit; a chain stops at its
        first failure. Returns, per chain, the success of each instruction attempted.

        Raises:
            LcrlError: an instruction the captioner cannot check here (a chain goes on only
                where success is known), or a policy that reads no text.
        """
        from train.environments.task_base import features_wrapper
        from train.environments.tasks import find_language_wrapper

        if self.policy.takes_task_ids:
            raise LcrlError("a chain of instructions needs a policy that reads text")
        texts = [check_instruction(t) for t in texts]
        if video is not None:
            check_video_path(video)
        meanings = []
        for text in texts:
            meaning, line = self.reading(text)
            if meaning is None:
                raise LcrlError(f"{line}; a chain (--then) goes on only where it is checked")
            meanings.append(meaning)
            self._print(line)
        vectors = [self.policy.embed(t)[0] for t in texts]
        env = self.env
        budget = self.policy.cfg.env.max_episode_steps  # per instruction, counted here
        inner = env.env if isinstance(env, gym.wrappers.TimeLimit) else env
        lang, features = find_language_wrapper(env), features_wrapper(env)
        task, agent = self.policy.task, self.policy.agent
        chains: list[list[bool]] = []
        frames: list[np.ndarray] = []
        for i in range(self.episodes):
            seed = self._feasible_layout(meanings[0], i)
            obs, _ = inner.reset(seed=seed, options={"instruction": meanings[0].text})
            done: list[bool] = []
            said = []
            for k, (text, vector) in enumerate(zip(texts, vectors, strict=True)):
                if k:
                    if lang.switch_instruction(meanings[k].text) is None:
                        break
                    obs = dict(obs) if features is None else features.restarted(obs)
                    obs["instruction"] = meanings[k].text
                raw = [env.render()] if video is not None else None
                first, steps, success = obs, 0, False
                while steps < budget:
                    o = {key: v[None] for key, v in task.storage_obs(obs, first).items()}
                    a = agent.act(o, vector[None], deterministic=self.deterministic, embedded=True)
                    obs, _, terminated, _, info = inner.step(task.scale_action(a[0]))
                    steps += 1
                    if raw is not None:
                        raw.append(env.render())
                    success = bool(info.get("is_success", False))
                    if success or terminated:
                        break
                done.append(success)
                status = "success" if success else "failure"
                said.append(f"{text!r} {status} in {steps} steps")
                if raw is not None:
                    hold = self.hold_frames if not success or k == len(texts) - 1 else 2
                    frames += annotate_episode(raw, text, status, hold, f"{steps} steps")
                if not success:
                    break
            chains.append(done)
            self._print(f"chain {i}: " + ", then ".join(said))
        for k in range(1, len(texts) + 1):
            rate = np.mean([len(c) >= k and all(c[:k]) for c in chains])
            self._print(f"{k} in a row: {rate:.2f} over {len(chains)} chains")
        if video is not None:
            self._save(video, frames)
        return chains

    def run_task(self, task: int | str, video: Path | None = None) -> InstructionResult:
        """Run :attr:`episodes` episodes of one task of the policy's fixed task set, given
        by its id (``3`` or ``"3"``) or its text; print and return the outcome.

        Raises:
            LcrlError: the policy has no task set, or ``task`` is none of its tasks (the
                message lists them).
        """
        from captioner.grammar import parse

        if isinstance(task, str) and task.strip().lstrip("+-").isdigit():
            task = int(task.strip())
        k = self.policy.task_id(task)
        text = self.policy.tasks[k]
        if video is not None:
            check_video_path(video)
        if not self.policy.takes_task_ids:  # a language policy trained on the task set
            self._print(f"task {k} of {len(self.policy.tasks)}:")
            return self.run_text(text, video)
        meaning = parse(text)
        self._print(f"task {k}: {text!r} (task id {k} of {len(self.policy.tasks)})")
        result = InstructionResult(text, meaning.text, [])
        return self._run_episodes(result, meaning, None, f"task {k}: {text}", video)

    def _run_episodes(
        self,
        result: InstructionResult,
        meaning: Any,
        vector: np.ndarray | None,
        label: str,
        video: Path | None,
    ) -> InstructionResult:
        """The episodes of one instruction or task (``vector``: its goal embedding, None
        for task ids), filling ``result``; ``label`` is drawn on the video frames."""
        from train.evaluation.evaluate import run_episode

        frames: list[np.ndarray] = []
        options = {"instruction": meaning.text} if meaning is not None else None
        for i in range(self.episodes):
            seed = self.seed + i
            if meaning is not None:
                seed = self._feasible_layout(meaning, i)
            raw: list[np.ndarray] | None = [] if video is not None else None
            try:
                r = run_episode(
                    self.policy.agent,
                    self.policy.task,
                    self.env,
                    seed=seed,
                    options=options,
                    goal_vector=vector,
                    deterministic=self.deterministic,
                    frames=raw,
                )
            except LcrlError as e:
                self._print(f"episode {i}: {e}")
                continue
            result.steps.append(r["steps"])
            if meaning is not None:
                result.successes.append(r["success"])
                status = "success" if r["success"] else "failure"
            else:
                status = "not checked"
            self._print(f"episode {i}: {r['steps']} steps, {status}")
            if raw is not None:
                frames += annotate_episode(
                    raw, label, status, self.hold_frames, f"{r['steps']} steps"
                )
        if result.successes:
            self._print(f"success {result.success_rate:.2f} over {len(result.successes)} episodes")
        if video is not None:
            result.video = self._save(video, frames)
        return result

    def _feasible_layout(self, meaning: Any, i: int) -> int:
        """The first layout seed of episode ``i`` in which ``meaning`` is feasible."""
        from train.environments.tasks import find_language_wrapper

        wrapper = find_language_wrapper(self.env)
        for k in range(LAYOUT_TRIES):
            seed = self.seed + i + k * self.episodes
            self.env.reset(seed=seed, options={"instruction": meaning.text})
            if wrapper.captioner.feasible(meaning, wrapper.s0):
                return seed
        self._print(
            f"episode {i}: {meaning.text!r} is not feasible in {LAYOUT_TRIES} layouts "
            "(are its objects on this table?); running it anyway"
        )
        return self.seed + i

    def run_goals(self, video: Path | None = None) -> list[bool]:
        """Episodes on the environment's own goals (state- and image-goal policies)."""
        from train.evaluation.evaluate import run_episode

        successes: list[bool] = []
        frames: list[np.ndarray] = []
        for i in range(self.episodes):
            raw: list[np.ndarray] | None = [] if video is not None else None
            r = run_episode(
                self.policy.agent,
                self.policy.task,
                self.env,
                seed=self.seed + i,
                deterministic=self.deterministic,
                frames=raw,
            )
            successes.append(r["success"])
            status = "success" if r["success"] else "failure"
            self._print(f"episode {i}: {r['steps']} steps, {status}")
            if raw is not None:
                frames += annotate_episode(
                    raw, None, status, self.hold_frames, f"{r['steps']} steps"
                )
        self._print(f"success {np.mean(successes):.2f} over {self.episodes} episodes")
        if video is not None:
            self._save(video, frames)
        return successes

    def _save(self, video: Path, frames: list[np.ndarray]) -> Path:
        path = save_video(video, frames, self.fps)
        self._print(f"video: {path} ({len(frames)} frames at {self.fps} fps)")
        return path

    def interactive(
        self, lines: Iterable[str], video: Path | None = None
    ) -> list[InstructionResult]:
        """Run every instruction of ``lines`` until an empty line, ``quit`` or the end
        (for task-id policies, every task, by id or text).

        A line that cannot be run prints ``error: ...`` and the session goes on. With
        ``video``, instruction ``n`` is saved as ``<stem>_<nnn><suffix>``.
        """
        run = self.run_task if self.policy.takes_task_ids else self.run_text
        results: list[InstructionResult] = []
        for line in lines:
            text = line.strip()
            if not text or text.lower() in QUIT_WORDS:
                break
            path = numbered_path(video, len(results) + 1) if video is not None else None
            try:
                results.append(run(text, path))
            except LcrlError as e:
                self._print(f"error: {e}")
            self._print("")
        self._print(f"{len(results)} instructions run")
        return results


def read_lines(stream: TextIO, prompt: str = "instruction> ") -> Iterator[str]:
    """Lines of ``stream``; the prompt is shown only when it is a terminal."""
    show = stream.isatty()
    while True:
        if show:
            print(prompt, end="", flush=True)
        line = stream.readline()
        if not line:
            if show:
                print()
            return
        yield line
