"""``lcrl demos``: record, relabel, inspect and import demonstration datasets.

* :func:`record` runs the scripted controller of a language-goal preset (``lang2d``,
  ``robosuite`` ...) on instructions of the split's training set and writes what the policy
  of that preset observes, the actions in policy units, the instruction as a segment
  ending at the success step, the privileged scene of every step (so the rule captioner
  can run later) and the recording settings (:mod:`lcrl.demos` describes the file).
* :func:`relabel` is instruction augmentation in hindsight (as in DIAL): every segment
  ``[start, t]`` of every episode is captioned, and each instruction an episode achieved
  becomes a segment ending at the first step it holds. Failed demonstrations, which teach
  nothing about their own instruction, teach what they did do.
* :func:`info` and :func:`import_robomimic` (robomimic / LIBERO files) round it off.

Scene arrays (``scene/<name>``) use one slot per object kind of
:data:`envs.scene.OBJECT_KINDS`: per step ``positions`` ``(K, 3)``, ``gripper`` ``(3,)``,
``grasped`` and ``touching`` ``(K,)`` (when the env reports them); per episode
``present`` ``(K,)``, ``colours`` and ``shapes`` ``(K,)`` (empty where absent),
``half_extents`` ``(K, 3)``, ``table_bounds`` ``(4,)`` and ``table_height``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from lcrl.demos import DemoDataset
from lcrl.errors import LcrlError
from train.training.demo_episodes import (
    EPISODE_SCENE as EPISODE_SCENE,
    NOT_DEMONSTRATIONS as NOT_DEMONSTRATIONS,
    buffer_episode as buffer_episode,
    check_dataset as check_dataset,
    family_of as family_of,
    info as info,
    scene_arrays as scene_arrays,
    scenes_from_arrays as scenes_from_arrays,
)
from train.training.demo_recording import (
    ACTORS as ACTORS,
    RandomActor as RandomActor,
    RecordConfig as RecordConfig,
    record as record,
)
from train.training.demo_relabelling import (
    format_relabel as format_relabel,
    relabel as relabel,
)

__all__ = [
    "EPISODE_SCENE",
    "ImportRobomimicCommand",
    "InfoCommand",
    "RecordConfig",
    "RelabelCommand",
    "family_of",
    "info",
    "record",
    "relabel",
    "scene_arrays",
    "scenes_from_arrays",
]


# --------------------------------------------------------------------------- scenes


# --------------------------------------------------------------------------- recording


# --------------------------------------------------------------------------- relabelling


# --------------------------------------------------------------------------- info


# --------------------------------------------------------------------------- commands


@dataclass
class RelabelCommand:
    """Add hindsight segments to a dataset: every instruction each episode achieved,
    ending at the first step it holds (``lcrl demos relabel SRC --out DST``)."""

    src: tyro.conf.Positional[str]
    """The dataset to relabel (recorded by ``lcrl demos record``)."""
    out: str = ""
    """Where to write the relabelled dataset (required; may be SRC itself, replaced
    atomically)."""
    captioner: str = "rule"
    """``rule`` (privileged scene) or the folder of a learned-captioner checkpoint
    (``lcrl caption train``; needs a dataset recorded with --images)."""
    starts_every: int = 0
    """Also caption segments starting every this many steps (0: only from step 0)."""
    train_only: bool = True
    """Only add instructions of the split's training set (held-out combinations never
    enter the training data); --no-train-only adds held-out ones too."""
    beam: int = 3
    """Beam width of a learned captioner."""
    min_logprob: float = -1.0
    """Learned captions less likely than this are skipped."""
    overwrite: bool = False
    """Replace an existing --out file."""
    json: str = ""
    """Also write the counts to this JSON file."""
    progress: bool = True
    """Show a progress bar."""

    def run(self) -> None:
        """``lcrl demos relabel``."""
        if not self.out:
            raise LcrlError("pass --out DST (the relabelled dataset; SRC itself to replace it)")
        if self.json:  # before the work: a --json that cannot be written fails now
            from train.runtime.run_lock import check_output_file

            check_output_file(self.json, "--json")
        counts = relabel(
            self.src,
            self.out,
            captioner=self.captioner,
            starts_every=self.starts_every,
            train_only=self.train_only,
            overwrite=self.overwrite,
            progress=self.progress,
            beam=self.beam,
            min_logprob=self.min_logprob,
        )
        print(format_relabel(counts))
        if self.json:
            _write_json(self.json, counts)


@dataclass
class InfoCommand:
    """Summarise a demonstration dataset: episodes, outcomes, observations, segments and
    instructions (given and hindsight) per family (``lcrl demos info FILE``)."""

    path: tyro.conf.Positional[str]
    """The dataset file."""
    instructions: bool = False
    """Also list the segments per instruction."""
    json: bool = False
    """Print the counts as JSON instead of text."""

    def run(self) -> None:
        """``lcrl demos info``."""
        c = info(self.path)
        if self.json:
            print(json.dumps({k: v for k, v in c.items() if k != "summary"}, indent=1))
            return
        print(c["summary"])
        print("  segments per family (given / hindsight):")
        for fam, row in c["per_family"].items():
            print(f"    {fam:<8} {row['given']:>6} / {row['hindsight']}")
        rec = c["meta"].get("recording")
        if isinstance(rec, dict):
            settings = ", ".join(f"{k} {v}" for k, v in rec.items())
            print(f"  recording: {settings}")
        rates = c["meta"].get("per_family")
        if isinstance(rates, dict) and rates:
            parts = [f"{f} {r['rate']:.2f}" for f, r in rates.items() if r.get("rate") is not None]
            print(f"  scripted success: {', '.join(parts)}")
        relabelled = c["meta"].get("relabel")
        if isinstance(relabelled, dict):
            n = relabelled.get("starts_every")
            which = "training instructions only"
            if not relabelled.get("train_only"):
                which = "held-out ones included"
            print(
                f"  relabelled by the {relabelled.get('captioner')} captioner (segments from "
                f"step 0{f' and every {n} steps' if n else ''}; {which})"
            )
        if self.instructions:
            print("  segments per instruction (given / hindsight):")
            for text, row in c["per_instruction"].items():
                print(f"    {row['given']:>6} / {row['hindsight']:<6} {text}")


@dataclass
class ImportRobomimicCommand:
    """Convert a robomimic-style HDF5 file (robomimic, LIBERO) into a demonstration
    dataset (``lcrl demos import-robomimic SRC --out DST``)."""

    src: tyro.conf.Positional[str]
    """The robomimic file (``data/demo_<i>/{obs, actions, ...}``)."""
    out: str = ""
    """The dataset file to write (required)."""
    instruction: str = ""
    """The instruction of every demo (default: LIBERO's ``problem_info``
    ``language_instruction``)."""
    obs_keys: tuple[str, ...] = ()
    """Low-dimensional observation keys concatenated into ``observation``, in this order
    (default: every non-image key, sorted)."""
    image_key: str = "auto"
    """Camera key stored as ``image`` (``auto``: ``agentview_image`` / ``agentview_rgb`` /
    the first image key; ``none``: no image)."""
    proprio_keys: tuple[str, ...] = ()
    """Keys concatenated into ``proprio`` (the robot's state for camera policies)."""
    overwrite: bool = False
    """Replace an existing --out file."""
    progress: bool = True
    """Show a progress bar."""

    def run(self) -> None:
        """``lcrl demos import-robomimic``."""
        import warnings

        from tqdm import tqdm

        from lcrl.demos import import_robomimic

        if not self.out:
            raise LcrlError("pass --out DST (the demonstration dataset to write)")
        image_key = None if self.image_key.lower() in ("", "none") else self.image_key

        def bar(items: Any) -> Any:
            return tqdm(items, disable=not self.progress, desc="import", unit="demo")

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the clipped count is printed below
            path = import_robomimic(
                self.src,
                self.out,
                instruction=self.instruction or None,
                obs_keys=tuple(self.obs_keys) or None,
                image_key=image_key,
                proprio_keys=self.proprio_keys,
                overwrite=self.overwrite,
                progress=bar,
            )
        with DemoDataset(path) as data:
            print(data.summary())
            settings = data.meta["import"]
        print(
            f"  imported keys: observation = {' + '.join(settings['obs_keys']) or '-'}, "
            f"image = {settings['image_key'] or '-'}"
        )
        if settings.get("clipped_values"):
            print(
                f"warning: {settings['clipped_values']} of {settings['action_values']} action "
                "values were outside [-1, 1] and were clipped"
            )


def _write_json(path: str, value: Any) -> None:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=1) + "\n")
    os.replace(tmp, p)
    print(f"saved {p}")


#: ``lcrl demos`` subcommands.
COMMANDS: dict[str, type] = {
    "record": RecordConfig,
    "relabel": RelabelCommand,
    "info": InfoCommand,
    "import-robomimic": ImportRobomimicCommand,
}
