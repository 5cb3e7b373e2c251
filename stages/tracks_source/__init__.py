"""Tracks source stage (dataset player): plays recorded tracks onto the bus, frame by frame.

Consumes nothing. Produces ``scene`` (``SceneInfo``, latched: with the first
frame, and again whenever the scene changes between sequences) and
``track_frame`` (``TrackFrame``: every object of one recorded frame) and,
when the recording has signal phases (``signal_phases_NNN.csv``) and
``signals`` is on, ``signal_state`` (``SignalState``: every group's phase at
the frame's stamp, read at the sequence's own time).

Parameters (``TracksSourceConfig``):

- ``data``: a data folder laid out like ``stages/data/taf-bw`` (INTERACTION- or
  inD-format, see ``stages.lib.datasets``); empty: the embedded default scenario.
- ``recording``: empty: ``k729_2022-03-16`` for the default folder, else the
  first recording found.
- ``sequences``: ids to play back to back; empty: ``("013",)`` for the
  default scenario, else all sequences of the recording.
- ``speed``: playback rate relative to recording time (> 0), or ``"max"``
  (as fast as every live node keeps up); the runtime paces by it.
- ``loop``: start over after the last sequence.
- ``signals`` True: publish ``signal_state`` when the recording has phases;
  False plays the same recording without them (for comparisons).
- ``projection``: the projection named in ``SceneInfo``; ``"auto"`` (the
  default) names the measured one of the recording's location
  (``stages.lib.projections``: K729 ``utm``, K733 ``scaled_mercator``, other
  locations ``local_cartesian``), so that a reader of the bus need not know
  that table (docs/wire.md, "Frames"). The scene id hashes the configured
  value, as before.
- ``clock``: ``"recording"`` (default) or ``"wall"``: every stamp moved by
  one offset so that the first frame carries the wall clock (Unix ns) at
  which playback starts, as a live tracker stamps its frames (README,
  "Predicting from a live tracker"); the intervals, and so the pacing, are
  the recording's.

Time: ``stamp_ns`` is recording time. The first sequence keeps its own stamps
(``timestamp_ms`` of the file; with ``clock = "wall"`` moved as above); each
following one (and each loop) is shifted to start one frame period after the
previous one ended, so stamps strictly increase over a run. ``header.frame_index`` counts the frames of the run
0, 1, 2, ...

Whatever the loader skipped, flagged or repaired becomes one ``Issue`` per
reason on the first result (kind ``bad_row_<reason>``, ``unknown_agent_type``
or ``repaired_<reason>``, detail with count and first example), so the
runtime logs and counts it. No docs/method.md section: this is infrastructure.
"""

from __future__ import annotations

from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, file_sha256, resolve_selection, scene_id_of

__all__ = ['TrackPlayer', 'TracksSourceConfig', 'file_sha256', 'resolve_selection', 'scene_id_of', "SPEC", "INPUTS", "OUTPUTS", "main"]

_BINDING = ("SPEC", "INPUTS", "OUTPUTS", "main", "make_core")


def __getattr__(name: str):
    """The binding lives in ``__main__.py``; importing it pulls in the runtime (zenoh) only when asked."""
    if name in _BINDING:
        from stages.tracks_source import __main__ as binding

        return getattr(binding, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
