"""Local Data: the node's shared-memory segment, declared once as numpy dtypes."""

from redistro.localdata.block import Block, MessageBox
from redistro.localdata.layout import (
    DOF,
    MAX_PROCS,
    MAX_ROBOTS,
    ProcState,
    segment_dtype,
)
from redistro.localdata.segment import LocalData

__all__ = [
    "DOF",
    "MAX_PROCS",
    "MAX_ROBOTS",
    "Block",
    "LocalData",
    "MessageBox",
    "ProcState",
    "segment_dtype",
]
