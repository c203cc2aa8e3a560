"""Language-goal wrapper on the 2D tabletop, and the scripted controllers."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.wrappers import TimeLimit

import captioner  # noqa: F401  (registers the language ids)
from captioner.grammar import FAMILIES_2D, parse
from captioner.lang_env import LanguageGoalWrapper
from captioner.rule import RuleCaptioner
from captioner.scripted import ScriptedController2D, to_discrete
from captioner.splits import make_split
from envs.tabletop2d import Tabletop2DEnv
from lcrl.errors import LcrlError

SPLIT = make_split(0, FAMILIES_2D)


def make(split_set="train", **kw):
    base = Tabletop2DEnv(**kw)
    return base, LanguageGoalWrapper(base, split=SPLIT, split_set=split_set, families=FAMILIES_2D)


@pytest.mark.filterwarnings("ignore:.*different from the unwrapped")
def test_env_checker_passes():
    _, env = make()
    check_env(env, skip_render_check=True)
    env = gym.make("lcrl/LangTabletop2D-v0", image=True)
    check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.parametrize("split_set", ["train", "heldout", "paraphrase"])
def test_instructions_come_from_the_chosen_set_and_are_feasible(split_set):
    base, env = make(split_set)
    texts = set(SPLIT.texts(split_set))
    cap = RuleCaptioner(FAMILIES_2D)
    families = set()
    for seed in range(40):
        obs, info = env.reset(seed=seed)
        assert obs["instruction"] == info["instruction"] == env.instruction
        assert env.instruction in texts
        assert cap.feasible(env.instruction, base.scene()) and info["feasible"]
        assert env.observation_space.contains(obs)
        families.add(env.meaning.family)
    assert families == set(FAMILIES_2D)


def test_same_seed_same_instruction_and_layout():
    _, a = make()
    _, b = make()
    oa, _ = a.reset(seed=5)
    ob, _ = b.reset(seed=5)
    assert oa["instruction"] == ob["instruction"]
    np.testing.assert_array_equal(oa["observation"], ob["observation"])


def test_reward_is_the_captioners_check_and_success_terminates():
    base, env = make()
    ctl = ScriptedController2D()
    env.reset(seed=0)
    name = base.scene().names[0]
    env.reset(seed=0, options={"instruction": f"reach the {name}"})
    s0 = env.s0
    cap = RuleCaptioner(FAMILIES_2D)
    rewards = []
    for _ in range(50):
        _, r, term, _, info = env.step(ctl.act(env.meaning, s0, base.scene()))
        assert r == float(cap.satisfied(env.meaning, s0, base.scene())) == float(info["is_success"])
        rewards.append(r)
        if term:
            break
    assert rewards[-1] == 1.0 and term and sum(rewards) == 1.0


def test_given_instruction_any_phrasing_and_bad_text():
    base, env = make()
    env.reset(seed=1)
    name = base.scene().names[0]
    obs, _ = env.reset(seed=1, options={"instruction": f"Touch the {name}, please"})
    assert env.meaning == parse(f"reach the {name}")
    assert obs["instruction"] == f"Touch the {name}, please"
    with pytest.raises(LcrlError, match="empty"):
        env.reset(seed=1, options={"instruction": "   "})
    with pytest.raises(LcrlError, match="cannot parse"):
        env.reset(seed=1, options={"instruction": "fly to the moon"})
    with pytest.raises(LcrlError, match="characters"):
        env.reset(seed=1, options={"instruction": "x" * 500})


def test_reset_info_says_whether_a_given_instruction_is_feasible():
    base, env = make()
    seen = set()
    for seed in range(30):
        _, info = env.reset(seed=seed, options={"instruction": "reach the red cube"})
        on_table = "red cube" in base.scene().names
        assert info["feasible"] == on_table
        seen.add(on_table)
    assert seen == {True, False}  # both kinds of layout were drawn


def test_wrapper_refuses_envs_without_scene_and_bad_sets():
    with pytest.raises(LcrlError, match="scene"):
        LanguageGoalWrapper(gym.make("CartPole-v1"))
    with pytest.raises(LcrlError, match="split set"):
        make("validation")
    with pytest.raises(LcrlError, match="no instruction"):
        LanguageGoalWrapper(Tabletop2DEnv(), split=make_split(0, ("lift",)), families=FAMILIES_2D)


@pytest.mark.parametrize("family", FAMILIES_2D)
def test_scripted_controller_achieves_each_family(family):
    """Every 2D family is achievable and recognised by the captioner."""
    base = Tabletop2DEnv()
    split = make_split(0, (family,), heldout_per_family=0)
    env = TimeLimit(LanguageGoalWrapper(base, split=split, families=(family,)), 50)
    ctl = ScriptedController2D()
    successes = []
    for seed in range(30):
        env.reset(seed=seed)
        wrapper = env.env
        done, success = False, False
        while not done:
            action = ctl.act(wrapper.meaning, wrapper.s0, base.scene())
            _, _, term, trunc, info = env.step(action)
            success |= info["is_success"]
            done = term or trunc
        successes.append(success)
    assert np.mean(successes) >= 0.8, (family, np.mean(successes))


def test_scripted_controller_works_with_discrete_actions():
    base = Tabletop2DEnv(action_type="discrete", num_directions=8)
    env = TimeLimit(
        LanguageGoalWrapper(base, split=make_split(0, ("reach",)), families=("reach",)), 50
    )
    ctl = ScriptedController2D()
    wins = 0
    for seed in range(10):
        env.reset(seed=seed)
        done = False
        while not done:
            a = to_discrete(ctl.act(env.env.meaning, env.env.s0, base.scene()), 8)
            _, r, term, trunc, _ = env.step(a)
            done = term or trunc
        wins += r == 1.0
    assert wins >= 8


def test_to_discrete_directions():
    assert to_discrete(np.array([0.0, 0.0])) == 0
    assert to_discrete(np.array([1.0, 0.0]), 4) == 1
    assert to_discrete(np.array([0.0, 1.0]), 4) == 2
    assert to_discrete(np.array([-1.0, 0.0]), 4) == 3
    assert to_discrete(np.array([0.0, -1.0]), 4) == 4
    assert to_discrete(np.array([1.0, 1.0]), 8) == 2
