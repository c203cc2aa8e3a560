"""Demonstration datasets: instruction-labelled episodes in one HDF5 file.

A demonstration dataset holds whole episodes (every observation, every action in policy
units) and a table of *segments*: stretches ``[start, end]`` of an episode labelled with
the instruction they accomplish, judged against the observation at ``start``. An
episode's own instruction gives one segment; hindsight relabelling adds one for every
other instruction the episode happened to achieve (:func:`append_segments`), so a failed
attempt at "push the red cube left" still teaches "reach the red cube" (a failed episode
keeps the instruction it attempted in ``episode_instruction`` but has no given segment for
it: it did not demonstrate it). Behavioural
cloning samples ``(observation, action, instruction)`` rows from the segments with
:meth:`DemoDataset.batches`.

File layout (``format = "lcrl-demos"``, ``version = 1``)::

    attrs                 format, version, meta (JSON given to the writer), discrete (bool)
    instructions          (I,) str       the instruction table: an id is an index into it
    obs/<key>             (N, ...)       every observation of every episode, concatenated;
                                         episode e's T_e + 1 observations are the rows
                                         [episode_start[e], episode_start[e + 1]).
                                         float32 vectors; uint8 images chunked one frame per
                                         chunk and lzf-compressed (random reads stay cheap)
    action                (M, A) float32 actions in policy units [-1, 1], or (M,) int64
                                         discrete actions; M = sum of T_e; episode e's T_e
                                         actions are the rows
                                         [action_start[e], action_start[e + 1]) and action t
                                         leads from observation t to observation t + 1
    episode_start         (E + 1,) int64 observation rows where each episode starts
    action_start          (E + 1,) int64 action rows where each episode starts
                                         (episode_start[e] - e)
    episode_success       (E,) int8      1 succeeded, 0 failed, -1 unknown
    episode_instruction   (E,) int32     the instruction the episode followed (-1: none)
    episode_source        (E,) str       where it came from (scripted, robomimic, ...)
    segments              (S, 5) int64   episode, start, end, instruction id, origin
                                         (0 given, 1 hindsight); the segment's transitions
                                         are steps start .. end - 1, observation end is
                                         the first where the instruction holds (or T_e)
    scene/<name>          per-step arrays (N, ...) aligned with obs/, or per-episode arrays
                                         (E, ...) whose dataset attribute per_episode is
                                         true: the privileged scene, stored as given (dtype
                                         kept, strings allowed) and opaque to this module

``initial`` is never stored: :meth:`DemoDataset.batches` gives, under that key, the
``observation`` row at the start of each row's segment. Files are written under a
temporary name and moved into place, so a file at the destination is always complete.
"""

from __future__ import annotations

from lcrl.demos.dataset import (
    DemoBatch as DemoBatch,
    DemoDataset as DemoDataset,
    append_segments as append_segments,
)
from lcrl.demos.hdf5 import (
    ACTION_TOLERANCE as ACTION_TOLERANCE,
    FORMAT as FORMAT,
    GIVEN as GIVEN,
    HINDSIGHT as HINDSIGHT,
    INITIAL as INITIAL,
    VERSION as VERSION,
)
from lcrl.demos.robomimic import (
    import_robomimic as import_robomimic,
)
from lcrl.demos.writer import (
    DemoWriter as DemoWriter,
)

__all__ = [
    "FORMAT",
    "GIVEN",
    "HINDSIGHT",
    "INITIAL",
    "VERSION",
    "DemoBatch",
    "DemoDataset",
    "DemoWriter",
    "append_segments",
    "import_robomimic",
]
