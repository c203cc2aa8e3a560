"""Can a selector over the frozen encoder's sentence vectors find the object that a held-out
word combination names, when it is told which object each training instruction names?

    python benchmarks/grounding_probe.py

The split is the training loop's (``make_split(seed, families)``: every colour and shape
stays in training, two object kinds per family are held out). A selector reads the
standardised sentence vector through a learned 64-wide projection (as the policy's text
goal encoder does) and gives logits over the 8 object slots: ``flat`` (one logit per
slot, as ``--agent.net.slot-mode select``) or ``attributes`` (a colour logit plus a shape
logit per slot). It is trained by cross-entropy on the training instructions only
(what ``--agent.grounding`` adds to the RL losses) and scored on held-out combinations and
paraphrases; ``phrased`` is ``attributes`` trained also on 16 training-only phrasings of
each training instruction (``--env.phrasings 16``, :mod:`captioner.phrasings`), whose
words the paraphrases never use. All on a reach and push split and on a reach split
(whose held-out kinds no training instruction names).
Writes ``benchmarks/results/grounding-probe.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import command, machine, save_figure, save_json, save_markdown

SETS = ("train", "heldout", "paraphrase")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--family-sets",
        nargs="+",
        default=["reach,push", "reach"],
        help="comma-separated families of each split (reach alone: held-out kinds are "
        "never named in training)",
    )
    parser.add_argument("--split-seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="init seeds")
    parser.add_argument("--steps", type=int, default=2000)
    args = parser.parse_args(argv)

    import numpy as np
    import torch

    torch.set_num_threads(1)
    info = machine()
    kinds = ("flat", "attributes", "phrased")
    results: dict[str, dict[str, dict[str, list[float]]]] = {}
    sizes: dict[str, dict[int, dict[str, int]]] = {}
    for family_set in args.family_sets:
        families = family_set.split(",")
        results[family_set], sizes[family_set] = run_probe(families, args, kinds)
    summary = {
        fs: {k: {n: float(np.mean(v)) for n, v in sets.items()} for k, sets in r.items()}
        for fs, r in results.items()
    }
    headline = {}
    for fs, by_kind in summary.items():
        tag = fs.replace(",", "_")
        for kind, acc in by_kind.items():
            headline[f"{tag}_{kind}_heldout_accuracy"] = round(acc["heldout"], 3)
            headline[f"{tag}_{kind}_paraphrase_accuracy"] = round(acc["paraphrase"], 3)
    name = "grounding-probe"
    save_json(
        name,
        {
            "headline": headline,
            "command": command(),
            "machine": info,
            "settings": vars(args),
            "set_sizes": sizes,
            "accuracy": summary,
            "per_run": results,
        },
    )
    lines = [
        "| families | selector | seen | held-out combinations | paraphrases |",
        "|---|---|---:|---:|---:|",
    ]
    for fs, by_kind in summary.items():
        for kind, a in by_kind.items():
            lines.append(
                f"| {fs} | {kind} | {a['train']:.3f} | {a['heldout']:.3f} | {a['paraphrase']:.3f} |"
            )
    body = (
        f"Splits {args.split_seeds} x init seeds {args.seeds}; {args.steps} Adam steps on "
        f"the training instructions (set sizes per split: {sizes}). Accuracy of the slot "
        "picked (argmax) against the object the instruction names. With reach alone the "
        "two held-out kinds are named by no training instruction: only the attribute "
        "selector can pick them.\n\n" + "\n".join(lines) + "\n"
    )
    save_markdown(
        name, "Grounding probe: picking the named object from sentence vectors", body, info
    )

    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(5.5 * len(summary), 3.6), squeeze=False)
    width = 0.8 / len(kinds)
    for ax, (fs, by_kind) in zip(axes[0], summary.items(), strict=True):
        for j, (kind, a) in enumerate(by_kind.items()):
            xs = [i + (j - (len(by_kind) - 1) / 2) * width for i in range(len(SETS))]
            ax.bar(xs, [a[n] for n in SETS], width, label=kind)
        ax.set_xticks(range(len(SETS)), ["seen", "held-out", "paraphrases"])
        ax.set(ylim=(0, 1.05), ylabel="slot picked = object named", title=f"families: {fs}")
        ax.legend()
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    save_figure(name, fig, info)
    print(json.dumps(headline, indent=1))
    return 0


def run_probe(families, args, kinds):
    """Accuracy per selector and set over splits and seeds, and the set sizes."""
    import torch
    import torch.nn.functional as F

    from captioner.phrasings import training_phrasings
    from captioner.splits import make_split
    from envs.scene import COLOURS, OBJECT_KINDS, SHAPES
    from lcrl.text_encoder import FrozenTextEncoder

    enc = FrozenTextEncoder()
    colours = list(COLOURS)
    colour_of = torch.eye(len(colours))[[colours.index(c) for c, _ in OBJECT_KINDS]]
    shape_of = torch.eye(len(SHAPES))[[SHAPES.index(s) for _, s in OBJECT_KINDS]]

    class Selector(torch.nn.Module):
        def __init__(self, kind: str) -> None:
            super().__init__()
            self.kind = kind
            self.proj = torch.nn.Linear(enc.dim, 64)
            if kind == "flat":
                self.slots = torch.nn.Linear(64, len(OBJECT_KINDS))
            else:
                self.colour = torch.nn.Linear(64, len(colours))
                self.shape = torch.nn.Linear(64, len(SHAPES))

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            h = self.proj(x)
            if self.kind == "flat":
                return self.slots(h)
            return self.colour(h) @ colour_of.T + self.shape(h) @ shape_of.T

    def phrasings(split) -> tuple[torch.Tensor, torch.Tensor]:
        texts, y = [], []
        for i, m in enumerate(split.instructions("train")):
            found = training_phrasings(m, 16, seed=i)
            texts += found
            y += [OBJECT_KINDS.index((m.colour, m.shape))] * len(found)
        return torch.as_tensor(enc.encode(texts)), torch.as_tensor(y)

    results = {k: {s: [] for s in SETS} for k in kinds}
    sizes = {}
    for split_seed in args.split_seeds:
        split = make_split(split_seed, families)
        data = {}
        for name in SETS:
            texts = list(split.texts(name))
            y = [OBJECT_KINDS.index((m.colour, m.shape)) for m in split.instructions(name)]
            data[name] = (torch.as_tensor(enc.encode(texts)), torch.as_tensor(y))
        sizes[split_seed] = {name: len(data[name][1]) for name in SETS}
        extra = phrasings(split)
        for kind in results:
            xt, yt = data["train"]
            if kind == "phrased":  # the normaliser's statistics cover the phrasings too
                xt, yt = torch.cat([xt, extra[0]]), torch.cat([yt, extra[1]])
            mean, std = xt.mean(0), xt.std(0) + 1e-6
            for seed in args.seeds:
                torch.manual_seed(seed)
                model = Selector("flat" if kind == "flat" else "attributes")
                opt = torch.optim.Adam(model.parameters(), 1e-3)
                for _ in range(args.steps):
                    loss = F.cross_entropy(model((xt - mean) / std), yt)
                    opt.zero_grad()
                    loss.backward()
                    opt.step()
                with torch.no_grad():
                    for name in SETS:
                        x, y = data[name]
                        acc = (model((x - mean) / std).argmax(-1) == y).float().mean().item()
                        results[kind][name].append(acc)
    return results, sizes


if __name__ == "__main__":
    sys.exit(main())
