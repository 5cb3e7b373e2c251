"""The in-process chain of the offline tools: TrackPlayer → CorridorBuilder → RelationExtractor [→ IntentionFilter].

``iamp eval``, ``iamp train`` (the AR training set), the intentions
evaluation and the bench scripts play recordings through this one chain, so
that a model is trained on the frames it is scored on. Plain cores, no bus:

    chain = Chain(recording, sequence, scene_maps, intentions=IntentionsConfig())
    for item in chain:          # one ChainFrame per played frame
        item.frame, item.corridor_set, item.relation_set, item.belief

One ``Chain`` plays one sequence with fresh cores (their continuity state is
as on the bus: every core sees every frame in order); the maps
(``SceneMaps``) are shared, loaded once. A scene whose map matched nothing
raises ``DatasetError`` (an evaluation on an unusable map would report
nothing, silently).

Errors. By default a core that raises ends the chain (the exception
propagates). With ``on_error(stage, where, exc)`` given, the failure is
reported there and the frame goes on without that output: no corridors, then
no relations and beliefs either (``corridor_set`` None); no relations, the
intentions still run (``relation_set`` None); no beliefs (``belief`` None).

Signals: when the recording has signal phases the player's ``SignalState``
goes to the relations core (``signals=False``: played without them, as a
recording without phases) and rides along in ``ChainFrame.signal_state``.

``chain_frames`` plays a whole sequence into a list; ``with_beliefs`` runs a
fresh ``IntentionFilter`` over such a list (the intentions evaluation runs
it once per seed over the same frames).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

from bus_schemas import CorridorSet, IntentionBelief, RelationSet, SceneInfo, SignalState, TrackFrame
from stages.corridors import CorridorBuilder, CorridorsConfig, SceneMaps
from stages.intentions import IntentionFilter, IntentionsConfig
from stages.lib.datasets import DatasetError, Recording
from stages.relations import RelationExtractor, RelationsConfig
from stages.tracks_source.core import TrackPlayer, TracksSourceConfig, file_sha256

#: on_error(stage, where, exception): stage is "corridors", "relations" or "intentions"; where names recording, sequence and stamp.
OnError = Callable[[str, str, Exception], None]


@dataclass(frozen=True, slots=True, eq=False)
class ChainFrame:
    """One frame through the chain: the inputs of the intentions stage, its output, and where the frame is.

    ``corridor_set``/``relation_set``/``belief`` are None where that core
    failed (``on_error``) or, for ``belief``, did not run; ``intentions_ms``
    is the wall time of ``IntentionFilter.process`` (None where it did not run).
    """

    frame: TrackFrame
    corridor_set: CorridorSet | None
    relation_set: RelationSet | None
    scene: SceneInfo
    belief: IntentionBelief | None = None
    index: int = 0
    stamp_ns: int = 0
    intentions_ms: float | None = None
    signal_state: SignalState | None = None  # the source's SignalState of this frame (None: no phases, or signals off)


class Chain:
    """One sequence of a recording through the cores, fresh ones (module docstring). Iterate it once."""

    def __init__(
        self,
        recording: Recording,
        sequence,
        scene_maps: SceneMaps,
        *,
        intentions: IntentionsConfig | None = None,
        max_frames: int = 0,
        map_sha256: str | None = None,
        on_error: OnError | None = None,
        run_id: str = "offline",
        producer: str = "offline",
        corridors_config: CorridorsConfig | None = None,
        relations_config: RelationsConfig | None = None,
        signals: bool = True,
        frame_hook: Callable[[TrackFrame], TrackFrame] | None = None,
        on_issues: Callable[[str, list], None] | None = None,
    ) -> None:
        self.recording = recording
        self.on_issues = on_issues  # on_issues(stage, issues): what a core flagged in a frame (the bus's NodeStats counts)
        self.frame_hook = frame_hook  # applied to every TrackFrame before the cores see it (training-time augmentation)
        self.sequence = sequence
        self.scene_maps = scene_maps
        self.max_frames = max(int(max_frames), 0)
        self.on_error = on_error
        if map_sha256 is None:
            map_sha256 = file_sha256(recording.map_path) if recording.map_path is not None else ""
        one = dataclasses.replace(recording, sequences=(sequence,))
        self.player = TrackPlayer(TracksSourceConfig(recording=recording.name, signals=signals), one, map_sha256=map_sha256, run_id=run_id, producer="source")
        self.corridors = CorridorBuilder(corridors_config or CorridorsConfig(), scene_maps=scene_maps)
        self.relations = RelationExtractor(relations_config or RelationsConfig(), scene_maps=scene_maps)
        self.intentions = IntentionFilter(intentions, producer=producer, scene_maps=scene_maps) if intentions is not None else None

    @property
    def n_frames(self) -> int:
        """Frames this chain plays (``max_frames`` applied)."""
        n = int(self.sequence.n_frames)
        return min(n, self.max_frames) if self.max_frames else n

    def __iter__(self) -> Iterator[ChainFrame]:
        scene: SceneInfo | None = None
        for n, (stamp, result) in enumerate(self.player):
            if self.max_frames and n >= self.max_frames:
                return
            if "scene" in result.outputs:
                scene = result.outputs["scene"]
                self._check_map(scene)
            frame: TrackFrame = result.outputs["track_frame"]
            if self.frame_hook is not None:
                frame = self.frame_hook(frame)
            signal_state = result.outputs.get("signal_state")
            where = f"{self.recording.name} sequence {self.sequence.id} stamp_ns {stamp}"
            corridor_set = self._run("corridors", where, lambda: self.corridors.process(frame, scene))
            relation_set = belief = ms = None
            if corridor_set is not None:
                relation_set = self._run("relations", where, lambda: self.relations.process(frame, corridor_set, scene, signal_state=signal_state))
                if self.intentions is not None:
                    t0 = time.perf_counter()
                    belief = self._run("intentions", where, lambda: self.intentions.process(frame, corridor_set, relation_set, scene))
                    ms = (time.perf_counter() - t0) * 1e3
            yield ChainFrame(frame, corridor_set, relation_set, scene, belief, index=n, stamp_ns=int(stamp), intentions_ms=ms,
                             signal_state=signal_state)

    def _check_map(self, scene: SceneInfo) -> None:
        scene_map = self.scene_maps.get(scene, self.corridors.config.projection)
        if scene_map.road_map is None:  # nothing could be matched: an error, never an all-NaN table
            problems = " ".join("; ".join(scene_map.problems).split())
            raise DatasetError(f"recording {self.recording.name}: map {scene.map_name} is unusable: {problems or 'no car lanelets'}")

    def _run(self, stage: str, where: str, call):
        """The core's first output, or None when it raises and ``on_error`` takes the failure."""
        if self.on_error is None:
            out = call()
        else:
            try:
                out = call()
            except Exception as exc:  # noqa: BLE001 - a data condition never ends an evaluation
                self.on_error(stage, where, exc)
                return None
        if self.on_issues is not None and len(out) > 1 and out[1]:
            self.on_issues(stage, out[1])
        return out[0]


def chain_frames(recording: Recording, sequence, scene_maps: SceneMaps, *, map_sha256: str = "", **kwargs) -> list[ChainFrame]:
    """Every frame of one sequence through a fresh ``Chain`` (keyword arguments as ``Chain``'s; ``map_sha256`` "" unless
    given, None: the map file's hash)."""
    return list(Chain(recording, sequence, scene_maps, map_sha256=map_sha256, **kwargs))


def with_beliefs(frames: Sequence[ChainFrame], config: IntentionsConfig, scene_maps: SceneMaps, *, producer: str = "offline") -> tuple[list[ChainFrame], list[float]]:
    """The frames with the beliefs of a fresh ``IntentionFilter`` (run over them in order), and its wall time per frame (ms)."""
    intentions = IntentionFilter(config, producer=producer, scene_maps=scene_maps)
    out, times = [], []
    for item in frames:
        if item.corridor_set is None:  # the corridors failed on this frame: nothing to filter
            out.append(item)
            continue
        t0 = time.perf_counter()
        belief, _issues = intentions.process(item.frame, item.corridor_set, item.relation_set, item.scene)
        ms = (time.perf_counter() - t0) * 1e3
        times.append(ms)
        out.append(dataclasses.replace(item, belief=belief, intentions_ms=ms))
    return out, times


__all__ = ["Chain", "ChainFrame", "OnError", "chain_frames", "with_beliefs"]
