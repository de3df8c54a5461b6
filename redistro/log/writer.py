"""The log writer process: drains a node's recording pipe into an MCAP file.

It runs at the default (non-real-time) priority, started by the node's
logging worker (:mod:`redistro.log.recorder`) with the read end of the pipe.
The first frame names the channels; cycle frames are cut into one message
per channel; event frames are JSON messages; the end frame carries the
recorder's counters. At end of file (the worker closed the pipe, or died)
the file is finished: summary, indexes, the counters as metadata, and a
``<node>.log.json`` sidecar for the session summary.
"""

from __future__ import annotations

import json
import os
from typing import IO, Any

from redistro.log.frames import FRAME, KIND_CYCLE, KIND_END, KIND_EVENT, KIND_HEADER

CHUNK_BYTES = 256 * 1024


def _read_exact(f: IO[bytes], n: int) -> bytes | None:
    data = f.read(n)
    if data is None or len(data) < n:
        return None  # end of file (a frame cut short by a dying recorder is dropped)
    return data


def run_writer(fd: int, out: str) -> int:
    from mcap.writer import CompressionType, Writer

    from redistro.log.frames import JSON_SCHEMA, MESSAGE_ENCODING, SCHEMA_ENCODING

    src = os.fdopen(fd, "rb", buffering=1 << 16)
    tmp = out + ".tmp"
    sink = open(tmp, "wb", buffering=1 << 20)  # noqa: SIM115
    writer = Writer(sink, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
    writer.start(profile="", library="redistro")
    cuts: list[tuple[int, int, int]] = []  # channel id, offset, size
    json_schema = writer.register_schema("redistro/Event", "jsonschema", JSON_SCHEMA)
    json_channels: dict[str, int] = {}
    header: dict[str, Any] = {}
    stats: dict[str, Any] = {}
    frames = messages = 0
    import time

    cpu0, wall0 = time.process_time(), time.monotonic()
    while True:
        head = _read_exact(src, FRAME.size)
        if head is None:
            break
        size, kind, log_ns = FRAME.unpack(head)
        body = _read_exact(src, size)
        if body is None:
            break
        if kind == KIND_CYCLE and cuts:
            seq = int.from_bytes(body[cuts[0][1] : cuts[0][1] + 8], "little")
            for cid, off, n in cuts:
                writer.add_message(cid, log_ns, body[off : off + n], log_ns, seq & 0xFFFFFFFF)
                messages += 1
            frames += 1
        elif kind == KIND_EVENT:
            doc = json.loads(body)
            topic = str(doc.pop("topic", "/events"))
            if topic not in json_channels:
                json_channels[topic] = writer.register_channel(topic, "json", json_schema)
            writer.add_message(json_channels[topic], log_ns, json.dumps(doc).encode(), log_ns)
            messages += 1
        elif kind == KIND_HEADER:
            header = json.loads(body)
            for ch in header["channels"]:
                sid = writer.register_schema(
                    ch["schema"], SCHEMA_ENCODING, ch["definition"].encode()
                )
                cid = writer.register_channel(
                    ch["topic"], MESSAGE_ENCODING, sid, {"node": header["node"]}
                )
                cuts.append((cid, int(ch["offset"]), int(ch["size"])))
            node = {k: v for k, v in header.items() if k not in ("channels", "meta")}
            writer.add_metadata("redistro.node", {k: json.dumps(v) for k, v in node.items()})
            writer.add_metadata(
                "redistro.meta", {k: json.dumps(v) for k, v in header.get("meta", {}).items()}
            )
        elif kind == KIND_END:
            stats = json.loads(body)
    stats.setdefault("node", header.get("node", ""))
    stats["frames_written"] = frames
    stats["messages"] = messages
    stats["complete"] = "recorded" in stats
    wall = time.monotonic() - wall0
    stats["writer_cpu_s"] = round(time.process_time() - cpu0, 3)
    stats["writer_cpu_percent"] = round(100 * stats["writer_cpu_s"] / wall, 2) if wall else 0.0
    writer.add_metadata("redistro.recording", {k: json.dumps(v) for k, v in stats.items()})
    writer.finish()  # type: ignore[no-untyped-call]
    sink.close()
    src.close()
    os.replace(tmp, out)
    side = out[: -len(".mcap")] + ".log.json" if out.endswith(".mcap") else out + ".json"
    with open(side + ".tmp", "w", encoding="utf-8") as f:
        json.dump(stats, f, indent=1)
    os.replace(side + ".tmp", side)
    return 0
