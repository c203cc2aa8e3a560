"""Query a trained language policy from Python (the README's example).

    lcrl train lang2d-quick                      # writes runs/lang2d-quick
    python examples/query_policy.py runs/lang2d-quick

Runs episodes on a free-text instruction (the environment checks success because the rule
captioner reads this phrasing), acts on a batch of observations with one text per row, and
shows which training instructions a made-up phrasing is closest to.
"""

import sys

import numpy as np

import lcrl

policy = lcrl.load(sys.argv[1] if len(sys.argv) > 1 else "runs/lang2d-quick")

# Episodes on any text. The environment takes the instruction only to judge success.
text = "go to the red cube"
env = policy.make_env()
successes = []
seed = 0
while len(successes) < 3:
    obs, info = env.reset(seed=seed, options={"instruction": text})
    seed += 1
    if not info["feasible"]:  # e.g. no red cube on the table in this layout
        continue
    policy.reset()  # a new episode: the next observation is remembered as its start
    done = False
    while not done:
        action = policy.act(obs, text)  # in the environment's units
        obs, _, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    successes.append(info["is_success"])
print(f"{text!r}: success {np.mean(successes):.2f} over {len(successes)} episodes")

# A batch: every array gets a leading dimension; one text for all rows or one per row.
starts = [policy.make_env().reset(seed=100 + i)[0] for i in range(2)]
batch = {"observation": np.stack([o["observation"] for o in starts])}
actions = policy.act(batch, ["reach the blue cube", "touch the green cylinder"], initial=batch)
print(f"batched actions: {actions.shape}")

# What the policy probably understands by a text outside its training instructions.
for neighbour in policy.nearest("shove the crimson box leftwards", k=3):
    print(f"{neighbour.similarity:.2f}  {neighbour.text}")
