"""Distributed core: knows nothing about RL. See docs/runtime.md for the reference."""

from infinirl.runtime.channel import Channel
from infinirl.runtime.cluster import Cluster, ClusterConfig
from infinirl.runtime.errors import (
    CallCancelled,
    ChannelClosed,
    ChannelError,
    ChannelPeerDied,
    ClusterError,
    InfiniRLError,
    WorkerError,
)
from infinirl.runtime.inventory import Accelerator, ClusterInventory, NodeInventory, Robot
from infinirl.runtime.memory import device_turn
from infinirl.runtime.placement import PlacementError, PlacementPlan, RankPlacement, place, resized_spec
from infinirl.runtime.scaling import BusyRatioPolicy, ScaleCommands, ScalingConfig
from infinirl.runtime.tracing import Tracer
from infinirl.runtime.weights import (
    PendingSync,
    WeightSink,
    WeightSource,
    WeightSyncGroup,
    start_weight_sync,
    sync_weights,
)
from infinirl.runtime.worker import GroupHandle, RankContext, RestartPolicy, Worker, WorkerGroup

__all__ = [
    "Accelerator", "BusyRatioPolicy", "CallCancelled", "Channel", "ChannelClosed", "ChannelError", "ChannelPeerDied",
    "Cluster", "ClusterConfig", "ClusterError", "ClusterInventory", "GroupHandle", "InfiniRLError", "NodeInventory",
    "PlacementError", "PlacementPlan", "RankContext", "RankPlacement", "RestartPolicy", "Robot",
    "ScaleCommands", "ScalingConfig", "Tracer", "WeightSink", "WeightSource", "WeightSyncGroup", "Worker",
    "WorkerError", "WorkerGroup", "device_turn", "place", "resized_spec", "sync_weights", "start_weight_sync",
    "PendingSync",
]
