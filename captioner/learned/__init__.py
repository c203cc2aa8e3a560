"""Learned captioner and learned reward model over camera frames.

Both read a pair of camera frames, the episode's first frame and the current one, and
optionally the robot's proprioception at both; they learn from a caption dataset
(:mod:`captioner.dataset`) labelled by the rule captioner, so that relabelling can later
run where no privileged state exists.

* :class:`FramePairEncoder`: by default (``spatial``) convolutions over the first frame,
  the current frame, their difference and two coordinate channels, pooled by each
  channel's maximum and its spatial-softmax keypoint. Pooling instead of a flattened map
  makes "the red cube moved left" read the same wherever on the table it happens; on the
  2D tabletop it halved the gap between training and held-out episodes (see the README).
* :class:`Captioner`: the encoder, then a GRU that writes the instruction word by word
  over the grammar's vocabulary (so it can produce word combinations it never saw as a
  whole). An observation that achieved
  nothing is captioned ``<none>``. Greedy and beam decoding; a caption's log-likelihood is
  returned with it, so unsure captions can be dropped by a threshold.
* :class:`RewardModel`: the probability that an instruction is satisfied by the change
  from the first frame to the current one. The instruction enters as the frozen text
  encoder's embedding (standardised over the training instructions), so any free text
  can be scored; it scales and shifts the channels of the late convolutions (FiLM), so it
  chooses what to look for before the map is pooled.

Training (:func:`train_models`) uses the dataset's training episodes; held-out
instructions (the split's held-out word combinations) are never used as targets, positives
or negatives. :func:`evaluate_models` reports, on held-out episodes and separately on
observations that achieved a held-out combination: exact match, per-slot accuracy (verb,
object, direction, relation, reference object), BLEU-4, and the reward model's precision,
recall and ROC AUC.
"""

from __future__ import annotations

from captioner.learned.data import (
    CaptionTrainConfig,
    delayed_labels,
    onset_delays,
)
from captioner.learned.evaluation import (
    evaluate_models,
    format_agreement,
    format_results,
    relabel_agreement,
    save_results,
)
from captioner.learned.labeller import LearnedLabeller
from captioner.learned.metrics import SLOT_GROUPS, bleu4, roc_auc, slot_matches
from captioner.learned.models import (
    ENCODERS,
    Captioner,
    CaptionModelConfig,
    FramePairEncoder,
    RewardModel,
    SlotPairEncoder,
    make_encoder,
)
from captioner.learned.saved import LearnedCaptioner
from captioner.learned.training import train_models
from captioner.learned.vocabulary import (
    BOS,
    CHECKPOINT_KIND,
    EOS,
    MODELS,
    NEAR_WINDOW,
    NONE,
    NONE_TEXT,
    PAD,
    SPECIALS,
    Vocabulary,
)

__all__ = [
    "BOS",
    "CHECKPOINT_KIND",
    "ENCODERS",
    "EOS",
    "MODELS",
    "NEAR_WINDOW",
    "NONE",
    "NONE_TEXT",
    "PAD",
    "SLOT_GROUPS",
    "SPECIALS",
    "CaptionModelConfig",
    "CaptionTrainConfig",
    "Captioner",
    "FramePairEncoder",
    "LearnedCaptioner",
    "LearnedLabeller",
    "RewardModel",
    "SlotPairEncoder",
    "Vocabulary",
    "bleu4",
    "delayed_labels",
    "evaluate_models",
    "format_agreement",
    "format_results",
    "make_encoder",
    "onset_delays",
    "relabel_agreement",
    "roc_auc",
    "save_results",
    "slot_matches",
    "train_models",
]
