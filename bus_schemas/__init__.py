"""Bus messages of hybrid-iamp: dataclasses, msgpack codec, registry and keys.

Depends on numpy and msgpack only. ``decode(data)`` turns any registered
payload into its message; ``Cls.decode(data)`` insists on one schema. Every
decode problem raises a ``SchemaError`` subclass.
"""

from . import keys
from .acceleration import AccelerationProfile, AccelerationProfiles
from ._wire import MAX_PAYLOAD_BYTES, REGISTRY, Array, Message, decode_any, json_schema, peek_schema, register, restamp_source_wall
from .corridors import Corridor, CorridorSet, MatchStatus, VehicleCorridors
from .common import VEHICLE_TYPE_VALUES, AgentType, Header
from .errors import MalformedPayload, PayloadTooLarge, SchemaError, UnknownSchema, WrongSchema, WrongVersion
from .relations import ConflictKind, CorridorRelations, RelationSet
from .predictions import CorridorPrediction, CorridorPredictions, GridStep, MotionGrid, coverage
from .infra import NodeStats, Progress
from .intentions import CorridorBelief, IntentionBelief, Manoeuvre, VehicleBelief
from .tracks import SceneInfo, TrackFrame
from .signals import SignalPhase, SignalState

decode = decode_any

__all__ = [
    "MAX_PAYLOAD_BYTES",
    "AccelerationProfile",
    "AccelerationProfiles",
    "REGISTRY",
    "restamp_source_wall",
    "AgentType",
    "ConflictKind",
    "Corridor",
    "CorridorPrediction",
    "CorridorPredictions",
    "coverage",
    "CorridorRelations",
    "CorridorSet",
    "CorridorBelief",
    "IntentionBelief",
    "Manoeuvre",
    "VehicleBelief",
    "MatchStatus",
    "RelationSet",
    "VehicleCorridors",
    "Array",
    "GridStep",
    "Header",
    "MalformedPayload",
    "Message",
    "MotionGrid",
    "NodeStats",
    "PayloadTooLarge",
    "Progress",
    "SceneInfo",
    "SchemaError",
    "SignalPhase",
    "SignalState",
    "TrackFrame",
    "UnknownSchema",
    "VEHICLE_TYPE_VALUES",
    "WrongSchema",
    "WrongVersion",
    "decode",
    "decode_any",
    "json_schema",
    "keys",
    "peek_schema",
    "register",
]
