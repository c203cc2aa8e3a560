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

The second probe asks the same of the rest of the meaning: the family and the direction
("push ... left"), the part of a paraphrase that the policy's object selection does not
cover. Trained on the training instructions and their 16 phrasings, a classifier reads
either the mean-pooled sentence vector (``pooled``, what the policy reads today) or the
frozen encoder's token states through a learned attention over the words (``tokens``,
:meth:`lcrl.text_encoder.FrozenTextEncoder.encode_tokens`); scored on paraphrases. Splits
whose instructions have only one such meaning (reach alone) are skipped.
Writes ``benchmarks/results/grounding-probe.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import json
import sys

from benchmarks.common import machine, save_figure, save_json, save_markdown

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
    meaning = {}
    for family_set in args.family_sets:
        found = run_meaning_probe(family_set.split(","), args)
        if found is not None:
            meaning[family_set] = found
    for fs, by_reader in meaning.items():
        tag = fs.replace(",", "_")
        for reader, acc in by_reader.items():
            headline[f"{tag}_meaning_{reader}_paraphrase_accuracy"] = round(
                float(np.mean(acc["paraphrase"])), 3
            )
    name = "grounding-probe"
    save_json(
        name,
        {
            "headline": headline,
            "machine": info,
            "settings": vars(args),
            "set_sizes": sizes,
            "accuracy": summary,
            "per_run": results,
            "meaning_per_run": meaning,
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
    if meaning:
        rows = [
            "| families | reader | seen | held-out combinations | paraphrases |",
            "|---|---|---:|---:|---:|",
        ]
        for fs, by_reader in meaning.items():
            for reader, acc in by_reader.items():
                cells = " | ".join(f"{np.mean(acc[n]):.3f}" for n in SETS)
                rows.append(f"| {fs} | {reader} | {cells} |")
        body += (
            "\nThe rest of the meaning (family and direction), from the training instructions "
            "and their 16 phrasings: accuracy of a classifier reading the mean-pooled "
            "sentence vector (`pooled`) or the token states through a learned attention "
            "over the words (`tokens`).\n\n" + "\n".join(rows) + "\n"
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
    save_figure(name, fig, info, rect=(0, 0.1, 1, 1))
    print(json.dumps(headline, indent=1))
    return 0


def run_meaning_probe(families, args):
    """Accuracy of the family-and-direction classifiers per reader and set, over splits
    and seeds; None when the split's instructions have a single such meaning."""
    import torch
    import torch.nn.functional as F

    from captioner.phrasings import training_phrasings
    from captioner.splits import make_split
    from lcrl.text_encoder import FrozenTextEncoder

    enc = FrozenTextEncoder()

    def meaning(m) -> str:
        return f"{m.family}:{getattr(m, 'direction', None)}"

    class Reader(torch.nn.Module):
        def __init__(self, tokens: bool, classes: int) -> None:
            super().__init__()
            self.tokens = tokens
            self.query = torch.nn.Linear(enc.dim, 1) if tokens else None
            self.proj = torch.nn.Linear(enc.dim, 64)
            self.out = torch.nn.Linear(64, classes)

        def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            if self.tokens:
                w = self.query(x).squeeze(-1).masked_fill(~mask, -1e9).softmax(-1)
                x = (w.unsqueeze(-1) * x).sum(1)
            return self.out(self.proj(x))

    def inputs(texts: list[str], tokens: bool):
        if tokens:
            states, mask = enc.encode_tokens(texts)
            return torch.as_tensor(states), torch.as_tensor(mask)
        x = torch.as_tensor(enc.encode(texts))
        return x, torch.ones(len(texts), 1, dtype=torch.bool)

    results: dict[str, dict[str, list[float]]] = {}
    for split_seed in args.split_seeds:
        split = make_split(split_seed, families)
        train = split.instructions("train")
        classes = sorted({meaning(m) for m in train})
        if len(classes) < 2:
            return None
        texts, labels = list(split.texts("train")), [meaning(m) for m in train]
        for i, m in enumerate(train):
            found = training_phrasings(m, 16, seed=i)
            texts += found
            labels += [meaning(m)] * len(found)
        y = torch.as_tensor([classes.index(c) for c in labels])
        for reader in ("pooled", "tokens"):
            tokens = reader == "tokens"
            x, mask = inputs(texts, tokens)
            flat = x[mask] if tokens else x  # the statistics of real tokens only
            mean, std = flat.mean(0), flat.std(0) + 1e-6
            sets = {
                name: (
                    *inputs(list(split.texts(name)), tokens),
                    torch.as_tensor(
                        [classes.index(meaning(m)) if meaning(m) in classes else -1
                         for m in split.instructions(name)]
                    ),
                )
                for name in SETS
            }  # fmt: skip
            for seed in args.seeds:
                torch.manual_seed(seed)
                model = Reader(tokens, len(classes))
                opt = torch.optim.Adam(model.parameters(), 1e-3)
                for _ in range(args.steps // 2):
                    loss = F.cross_entropy(model((x - mean) / std, mask), y)
                    opt.zero_grad()
                    loss.backward()
                    opt.step()
                with torch.no_grad():
                    for name, (xs, ms, ys) in sets.items():
                        acc = (model((xs - mean) / std, ms).argmax(-1) == ys).float().mean()
                        results.setdefault(reader, {}).setdefault(name, []).append(acc.item())
    return results


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
