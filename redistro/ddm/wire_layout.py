"""The DDM kernels' buffers with fields (``ddm_admit``, ``ddm_emit``,
``ddm_send``, the compiled answer's state, a record's codec; their references are
ddm/record.py and ddm/worker.py's Python path), declared once."""

from __future__ import annotations

import numpy as np

from redistro.kernel_layouts import Table

I8 = "<i8"
KEY_MAX = 192  # a link's or run's key, at most [bytes]

# what seals and checks records of one key: the key, the layout of the
# records (the tag covers [0, body); the crc32, a u4, at crc_at)
CODEC = np.dtype(
    [("key", "u1", KEY_MAX), ("key_len", "<u4"), ("pad", "<u4"), ("body", I8), ("crc_at", I8)]
)
# where the admitting kernel finds what it checks (byte offsets in the
# record and the exchange record; in Local Data: the starving blocks, -1: none)
ADMIT_PARAMS = np.dtype(
    [
        (name, I8)
        for name in (
            "magic",
            "version",
            "kind",
            "payload_at",
            "size",
            "h_magic",
            "h_version",
            "h_kind",
            "h_robot",
            "h_source",
            "h_seq",
            "h_stamp",
            "h_estop",
            "ex_size",
            "ex_updates",
            "ex_last",
            "ex_fresh",
            "sent_seq",
            "sent_pay",
            "deliv_seq",
            "deliv_pay",
        )
    ]
)
# one row per local robot: its group id, its in block, and the admission
# state of the source that claimed it (shared with the Python path)
ADMIT_ROW = np.dtype(
    [
        ("gid", I8),
        ("seq_off", I8),
        ("pay_off", I8),
        ("claimed", I8),
        ("last_seq", I8),  # (a u8 seq, stored signed)
        ("last_stamp", I8),
        ("pad", I8, 2),
    ]
)
ADMIT_STATE = np.dtype([("latency_count", I8), ("taken", I8), ("mask", I8)])
EMIT_PARAMS = np.dtype(
    [
        (name, I8)
        for name in (
            "payload_at",
            "size",
            "seqsrc_at",
            "h_seq",
            "h_stamp",
            "h_estop",
            "ex_size",
            "ex_sent",
        )
    ]
)
EMIT_ROW = np.dtype(
    [("seq_off", I8), ("pay_off", I8), ("last_out", I8), ("seq", I8), ("pad", I8, 4)]
)
# ddm_reply's outcome, after ddm_send's per-robot status: the emit's mask
# (-2: not run; -1: a torn read) and the send's trouble bits
REPLY = np.dtype([("emitted", I8), ("trouble", I8)])
# the compiled answer's state: whether the ddm answers; records taken; a reply owed
ANSWER_STATE = np.dtype([("answering", I8), ("answered", I8), ("reply_owed", I8)])

LAYOUTS = {
    "wire": {"codec": CODEC},
    "ddm_admit": {
        "codec": CODEC,
        "params": ADMIT_PARAMS,
        "rows": Table(ADMIT_ROW),
        "state": ADMIT_STATE,
    },
    "ddm_emit": {"codec": CODEC, "params": EMIT_PARAMS, "rows": Table(EMIT_ROW)},
    "ddm_send": {"reply": REPLY},
    "answer": {"state": ANSWER_STATE},
}
