"""The recording pipe's framing, shared by the recorder and the writer process.

A frame: u32 payload length, u8 kind, i64 log time (CLOCK_REALTIME ns), then
the payload. A cycle frame's payload is the cycle's messages back to back;
an event's is JSON; the header (the first frame) names the channels; the end
frame carries the recorder's counters. No numpy here: the writer process
does not need it.
"""

from __future__ import annotations

import struct

FRAME = struct.Struct("<IBq")
KIND_CYCLE = 0
KIND_EVENT = 1
KIND_HEADER = 2
KIND_END = 3

# how the channels are encoded (redistro.log.schema makes the definitions)
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
CDR_HEADER = b"\x00\x01\x00\x00"  # CDR, little-endian: the encapsulation ROS 2 uses
# a numpy scalar (kind, size) -> its struct code (the writer has no numpy)
STRUCT_CODES = {("u", 1): "B", ("i", 1): "b", ("u", 2): "H", ("i", 2): "h", ("u", 4): "I"}
STRUCT_CODES.update({("i", 4): "i", ("u", 8): "Q", ("i", 8): "q", ("f", 4): "f", ("f", 8): "d"})
