"""gymnasium's own conventions reach the lcrl env ids from a fresh interpreter: the
``module:id`` form imports ``envs`` first, and ``gym.register_envs(envs)`` names the module
whose import registers them (a plain ``gym.make("lcrl/...")`` before any import of ``envs``
raises ``NamespaceNotFound``, as for every third-party env package)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(code: str) -> str:
    """Run ``code`` in a fresh interpreter from the repository root; its stdout."""
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_module_prefix_imports_envs():
    out = run(
        "import gymnasium as gym\n"
        "env = gym.make('envs:lcrl/Tabletop2D-v0')\n"
        "obs, _ = env.reset(seed=0)\n"
        "print(sorted(obs), env.spec.max_episode_steps)\n"
    )
    assert out == "['achieved_goal', 'desired_goal', 'observation'] 50"


def test_register_envs_then_plain_id():
    out = run(
        "import gymnasium as gym\n"
        "import envs\n"
        "gym.register_envs(envs)\n"
        "env = gym.make('lcrl/Tabletop2DDiscrete-v0')\n"
        "print(env.action_space)\n"
    )
    assert out == "Discrete(9)"  # 8 directions and staying put


def test_plain_id_without_the_import_names_the_namespace():
    out = run(
        "import gymnasium as gym\n"
        "try:\n"
        "    gym.make('lcrl/Tabletop2D-v0')\n"
        "except gym.error.NamespaceNotFound as e:\n"
        "    print('NamespaceNotFound', e)\n"
    )
    assert out.startswith("NamespaceNotFound") and "lcrl" in out
