"""Scripted controllers of the robosuite tabletop (captioner/scripted3d.py), and agreement of
the rule captioner's ``caption`` and ``satisfied`` on simulated episodes.

One environment is built per module (building takes a second or two); every episode resets
it with its own seed.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import envs.robosuite_tabletop as rt  # imports neither robosuite nor mujoco

with rt._quiet_robosuite():  # robosuite logs warnings about optional extras on import
    pytest.importorskip("robosuite")

import numpy as np

from captioner.grammar import FAMILIES, Instruction, all_instructions
from captioner.lang_env import LanguageGoalWrapper
from captioner.rule import RuleCaptioner
from captioner.scripted3d import MarkovController3D, ScriptedController3D
from envs.robosuite_tabletop import RobosuiteTabletopEnv
from envs.scene import OBJECT_KINDS, SceneState

SEEDS = range(8)
MIN_SUCCESSES = 7  # of len(SEEDS)
MAX_STEPS = 100
ALL = all_instructions(FAMILIES)
CAPTIONER = RuleCaptioner(FAMILIES)


@pytest.fixture(scope="module")
def env() -> Iterator[RobosuiteTabletopEnv]:
    e = RobosuiteTabletopEnv()
    yield e
    e.close()


def run_scripted(
    wrapped: LanguageGoalWrapper,
    seed: int | None,
    steps: int = MAX_STEPS,
    controller: ScriptedController3D | None = None,
) -> tuple[bool, int]:
    """One scripted episode (``seed`` None: go on in the scene, with the instruction the
    wrapper has); (success, steps taken)."""
    controller = controller or ScriptedController3D()
    if seed is not None:
        wrapped.reset(seed=seed)
    scene = wrapped.unwrapped.scene
    for t in range(steps):
        action = controller.act(wrapped.meaning, wrapped.s0, scene())
        assert action.shape == (4,) and action.dtype == np.float32
        assert np.all(np.abs(action) <= 1.0)
        _, _, _, truncated, info = wrapped.step(action)
        if info["is_success"]:
            return True, t + 1
        assert not truncated, info.get("sim_error")
    return False, steps


@pytest.mark.parametrize("family", FAMILIES)
def test_scripted_controller_succeeds(env: RobosuiteTabletopEnv, family: str) -> None:
    wrapped = LanguageGoalWrapper(env, families=(family,))
    results = {seed: run_scripted(wrapped, seed) for seed in SEEDS}
    successes = sum(ok for ok, _ in results.values())
    assert successes >= MIN_SUCCESSES, f"{family}: {results}"


@pytest.mark.parametrize("family", FAMILIES)
def test_the_memoryless_controller_succeeds_and_goes_on_in_the_same_scene(
    env: RobosuiteTabletopEnv, family: str
) -> None:
    """The DAgger teacher: each family from a reset, then a second instruction of another
    family from where the first left the scene (after lift, the object is still held)."""
    wrapped = LanguageGoalWrapper(env, families=(family,))
    markov = MarkovController3D()
    firsts, seconds = 0, 0
    for seed in range(4):
        ok, _ = run_scripted(wrapped, seed, controller=markov)
        firsts += ok
        following = "push" if family != "push" else "lift"
        pool = [str(i) for i in ALL if i.family == following]
        if ok and wrapped.switch_instruction(candidates=pool) is not None:
            seconds += run_scripted(wrapped, None, controller=markov)[0]
    assert firsts >= 3 and seconds >= 3, (family, firsts, seconds)


@pytest.mark.parametrize("family", ["put", "stack"])
def test_the_funnel_teacher_lowers_while_it_closes_in_and_still_succeeds(
    env: RobosuiteTabletopEnv, family: str
) -> None:
    """``MarkovController3D(funnel=...)``: put and stack lower the carried object as it
    closes the last centimetres to the drop point (the controller without a funnel holds
    it at carry height there), from a reset and after a lift."""
    wrapped = LanguageGoalWrapper(env, families=(family,))
    funnel, sharp = MarkovController3D(funnel=0.05), MarkovController3D()
    lowered, held_near, successes = 0, 0, 0
    for seed in range(3):
        wrapped.reset(seed=seed)
        for _ in range(MAX_STEPS):
            s = env.scene()
            ins = wrapped.meaning
            i = s.index(*ins.obj)
            a = funnel.act(ins, wrapped.s0, s)
            dest = funnel._drop_point(ins, wrapped.s0, s, i, s.index(*ins.target))
            err = float(np.linalg.norm(dest[:2] - s.positions[i, :2]))
            if s.grasped is not None and s.grasped[i] and 0.02 < err < 0.04:
                held_near += 1
                lowered += a[2] < -0.05 and sharp.act(ins, wrapped.s0, s)[2] > -0.05
            _, _, _, truncated, info = wrapped.step(a)
            if info["is_success"] or truncated:
                break
        successes += info["is_success"]
    assert successes == 3 and held_near > 0 and lowered > 0, (successes, held_near, lowered)
    lift = LanguageGoalWrapper(env, families=("lift",))
    pool = [str(i) for i in ALL if i.family == family]
    seconds = 0
    for seed in range(6):
        ok, _ = run_scripted(lift, seed, controller=funnel)
        if ok and lift.switch_instruction(candidates=pool) is not None:
            seconds += run_scripted(lift, None, controller=funnel)[0]
    assert seconds >= 4, seconds  # as many as without a funnel: put 8 and stack 10 of 10


def test_the_memoryless_controller_reads_everything_off_the_scene(
    env: RobosuiteTabletopEnv,
) -> None:
    wrapped = LanguageGoalWrapper(env, families=("put",))
    markov = MarkovController3D()
    wrapped.reset(seed=3)
    s0, scenes = wrapped.s0, []
    for _ in range(12):
        scenes.append(env.scene())
        wrapped.step(markov.act(wrapped.meaning, s0, scenes[-1]))
    first = [markov.act(wrapped.meaning, s0, s) for s in scenes]
    again = [markov.act(wrapped.meaning, s0, s) for s in reversed(scenes)][::-1]
    np.testing.assert_array_equal(np.stack(first), np.stack(again))
    assert len({a.tobytes() for a in first}) > 1  # it does move


def test_accepts_sentences_and_restarts_on_a_new_episode(env: RobosuiteTabletopEnv) -> None:
    wrapped = LanguageGoalWrapper(env, families=("lift",))
    controller = ScriptedController3D()
    env.reset(seed=0)
    first = env.scene()
    text = f"Pick up the {first.colours[0]} {'block' if first.shapes[0] == 'cube' else 'can'}"
    wrapped.reset(seed=0, options={"instruction": text})
    for _ in range(MAX_STEPS):
        _, _, terminated, _, info = wrapped.step(controller.act(text, wrapped.s0, env.scene()))
        if terminated:
            break
    assert info["is_success"] and controller.phase == "carry"
    wrapped.reset(seed=1)  # a new s0 restarts the phase machine without reset()
    controller.act(text, wrapped.s0, env.scene())
    assert controller.phase == "approach"
    for _ in range(15):
        wrapped.step(controller.act(wrapped.meaning, wrapped.s0, env.scene()))
    assert controller.phase != "approach"
    controller.reset()
    assert controller.phase == "approach"
    colour, shape = next(k for k in OBJECT_KINDS if wrapped.s0.index(*k) < 0)
    action = controller.act(Instruction("reach", colour, shape), wrapped.s0, env.scene())
    np.testing.assert_array_equal(action, [0.0, 0.0, 0.0, -1.0])


# --------------------------------------------------------------------------- caption agreement


def check_agreement(s0: SceneState, s: SceneState, instructions: list[Instruction]) -> set:
    """caption(s0, s) equals the set of the scene's instructions that satisfied() accepts."""
    caption = CAPTIONER.caption(s0, s)
    accepted = {i for i in instructions if CAPTIONER.satisfied(i, s0, s)}
    assert caption == accepted, (caption - accepted, accepted - caption)
    return caption


def scene_instructions(s: SceneState) -> list[Instruction]:
    """Every instruction of the 5 families over the objects in the scene."""
    present = set(zip(s.colours, s.shapes, strict=True))
    return [i for i in ALL if all(obj in present for obj in i.objects)]


def wander(rng: np.random.Generator, steps: int) -> Iterator[np.ndarray]:
    """Random actions held for a few steps each, biased down, so that the gripper meets
    the objects (and sometimes closes on one)."""
    while steps > 0:
        hold = int(rng.integers(2, 7))
        a = rng.uniform(-1.0, 1.0, 4)
        a[2] -= 0.3
        for _ in range(min(hold, steps)):
            yield np.clip(a, -1.0, 1.0)
        steps -= hold


def test_caption_agrees_with_satisfied_on_random_episodes(env: RobosuiteTabletopEnv) -> None:
    seen: set[Instruction] = set()
    for seed in range(3):
        env.reset(seed=100 + seed)
        s0 = env.scene()
        instructions = scene_instructions(s0)
        assert not check_agreement(s0, s0, instructions)
        for action in wander(np.random.default_rng(seed), 60):
            env.step(action)
            seen |= check_agreement(s0, env.scene(), instructions)
    assert seen, "the random episodes never satisfied anything: the check checked nothing"


@pytest.mark.parametrize("family", FAMILIES)
def test_caption_agrees_with_satisfied_on_scripted_episodes(
    env: RobosuiteTabletopEnv, family: str
) -> None:
    wrapped = LanguageGoalWrapper(env, families=(family,), terminate_on_success=False)
    controller = ScriptedController3D()
    wrapped.reset(seed=200)
    s0 = wrapped.s0
    instructions = scene_instructions(s0)
    seen: set[Instruction] = set()
    after = None  # steps run since the instruction was first satisfied
    for _ in range(MAX_STEPS):
        _, _, _, _, info = wrapped.step(controller.act(wrapped.meaning, s0, env.scene()))
        seen |= check_agreement(s0, env.scene(), instructions)
        if info["is_success"] and after is None:
            after = 0
        if after is not None:
            after += 1
            if after > 10:
                break
    assert wrapped.meaning in seen


def test_smoke_episodes_with_camera_images_and_captions() -> None:
    """A few scripted episodes on the camera env: every step renders a fresh uint8 frame,
    and the captioner's caption of the final scene holds the instruction that succeeded."""
    cam = RobosuiteTabletopEnv(image=True, image_size=64)
    try:
        for seed, family in enumerate(("reach", "push", "lift")):
            wrapped = LanguageGoalWrapper(cam, families=(family,))
            controller = ScriptedController3D()
            obs, _ = wrapped.reset(seed=100 + seed)
            frames = [obs["image"]]
            success = False
            for _ in range(MAX_STEPS):
                action = controller.act(wrapped.meaning, wrapped.s0, cam.scene())
                obs, _, _, truncated, info = wrapped.step(action)
                frames.append(obs["image"])
                if info["is_success"] or truncated:
                    success = bool(info["is_success"])
                    break
            assert success, f"{family} (seed {100 + seed}) did not succeed"
            assert all(f.shape == (64, 64, 3) and f.dtype == np.uint8 for f in frames)
            assert np.abs(frames[-1].astype(int) - frames[0].astype(int)).mean() > 0.5
            caption = CAPTIONER.caption(wrapped.s0, cam.scene())
            assert wrapped.meaning in caption
    finally:
        cam.close()
