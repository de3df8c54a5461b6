"""The run folder's ``session.mcap``: made from the nodes' parts, read back as numpy arrays."""

from __future__ import annotations

import heapq
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from redistro.log.frames import CDR_HEADER, MESSAGE_ENCODING, SCHEMA_ENCODING
from redistro.log.ros2 import EVENT, MESSAGE, event_json, message_doc
from redistro.log.schema import cdr_dtype, dtype_from_msg

log = logging.getLogger(__name__)

SESSION_LOG = "session.mcap"


def finish_run_log(run_dir: Path, node_cycles: dict[str, int] | None = None) -> dict[str, Any]:
    """Merge the nodes' ``<node>.mcap`` parts into ``session.mcap`` (time order)
    and gather their recording counters (the ``log`` entry of summary.json).
    node_cycles: each node's cycles from its result, for a part whose
    recorder died before it could send its own count. Returns {} when
    nothing was recorded."""
    parts = sorted(p for p in run_dir.glob("*.mcap") if p.name != SESSION_LOG)
    if not parts:
        return {}
    nodes: dict[str, Any] = {}
    for part in parts:
        side = part.with_name(part.name[: -len(".mcap")] + ".log.json")
        node = part.name[: -len(".mcap")]
        try:
            nodes[node] = json.loads(side.read_text())
        except (OSError, ValueError):
            nodes[node] = {"node": node, "complete": False}
        side.unlink(missing_ok=True)
        rec = nodes[node]
        cycles = (node_cycles or {}).get(node)
        if "recorded" not in rec and cycles is not None:
            # the recorder died: what reached the file is what was recorded
            rec["recorded"] = int(rec.get("frames_written", 0))
            rec["cycles"] = cycles
            rec["dropped"] = max(0, cycles - rec["recorded"])
    out = run_dir / SESSION_LOG
    t0 = time.monotonic()
    added = 0
    if len(parts) == 1:
        os.replace(parts[0], out)
    else:
        added = _merge(parts, out)
        for p in parts:
            p.unlink()
    merge_s = time.monotonic() - t0
    return {
        "file": SESSION_LOG,
        "bytes": out.stat().st_size,
        "messages": sum(int(n.get("messages", 0)) for n in nodes.values()) + added,
        "merge_s": round(merge_s, 3),  # the parts merged into one file (after the run)
        "dropped": sum(int(n.get("dropped", 0)) for n in nodes.values()),
        "digest": run_digest(nodes),
        "nodes": nodes,
    }


def run_digest(nodes: dict[str, Any]) -> str:
    """The whole log's digest: its parts' (each node's logged cycles but
    their wall-clock stamps), in node order."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    for node in sorted(nodes):
        h.update(f"{node}:{nodes[node].get('digest', '')}\n".encode())
    return h.hexdigest()


STATIC_SCENE = ("/robot_description", "/tf_static", "/workcell/markers")


def _merge(parts: list[Path], out: Path) -> int:
    """The parts into one rosbag2-profile MCAP file, in time order. Each
    part drew its own robots' static scene: those messages give way to one
    of the whole group (:func:`redistro.log.scene.static_messages`).
    Returns the messages added less those left out."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from redistro import files as safe

    files = [open(p, "rb") for p in parts]  # noqa: SIM115
    tmp = safe.temp_name(out)
    try:
        readers = [make_reader(f) for f in files]
        with safe.open_new(tmp, text=False) as sink:
            w = Writer(sink, chunk_size=1 << 20, compression=CompressionType.ZSTD)
            w.start(profile="ros2", library="redistro")
            schemas: dict[tuple[int, int], int] = {}
            channels: dict[tuple[int, int], int] = {}
            robots: dict[str, Any] = {}
            meta: dict[str, Any] = {}
            left_out = 0
            for k, r in enumerate(readers):
                summary = r.get_summary()
                assert summary is not None
                for sid, s in summary.schemas.items():
                    schemas[(k, sid)] = w.register_schema(s.name, s.encoding, s.data)
                for cid, c in summary.channels.items():
                    if c.topic in STATIC_SCENE:
                        stats = summary.statistics
                        left_out += stats.channel_message_counts.get(cid, 0) if stats else 0
                        continue
                    channels[(k, cid)] = w.register_channel(
                        c.topic, c.message_encoding, schemas.get((k, c.schema_id), 0), c.metadata
                    )
                for m in r.iter_metadata():
                    w.add_metadata(m.name, m.metadata)
                    if m.name == "redistro.meta":
                        meta.update({key: _loads(v) for key, v in m.metadata.items()})
                        part_robots = meta.get("robots")
                        robots.update(part_robots if isinstance(part_robots, dict) else {})

            def stream(k: int, r: Any) -> Any:
                for _, ch, msg in r.iter_messages(log_time_order=True):
                    if (k, ch.id) in channels:
                        yield msg.log_time, k, channels[(k, ch.id)], msg.data, msg.sequence

            merged = heapq.merge(
                *(stream(k, r) for k, r in enumerate(readers)), key=lambda e: (e[0], e[1])
            )
            first = 0
            for t, _, cid, data, seq in merged:
                first = first or t
                w.add_message(cid, t, data, t, seq)
            added = _static_scene(w, {**meta, "robots": robots}, first) if robots else 0
            w.finish()  # type: ignore[no-untyped-call]
        os.replace(tmp, out)
        return added - left_out
    finally:
        for f in files:
            f.close()
        tmp.unlink(missing_ok=True)


def _static_scene(w: Any, meta: dict[str, Any], stamp_ns: int) -> int:
    """The whole group's static scene into ``w``; how many messages."""
    from redistro.log import scene

    if not stamp_ns:
        return 0
    arms = {r: scene.Arm(r, v.get("peg")) for r, v in sorted(meta["robots"].items())}
    made = scene.static_messages(meta, arms, stamp_ns)
    for t, topic, msgtype, data in made:
        text = scene.definition(msgtype)
        sid = w.register_schema(msgtype, SCHEMA_ENCODING, text.encode())
        w.add_message(w.register_channel(topic, MESSAGE_ENCODING, sid, {}), t, data, t)
    return len(made)


@dataclass
class SessionLog:
    """A session log read whole: per topic a numpy array (binary channels) or a
    list of dicts (JSON channels, each with ``log_time_ns``); metadata by name."""

    path: Path
    arrays: dict[str, np.ndarray[Any, Any]] = field(default_factory=dict)
    log_times: dict[str, np.ndarray[Any, Any]] = field(default_factory=dict)
    events: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    metadata: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def meta(self, name: str) -> dict[str, Any]:
        """The metadata records of that name merged (later ones win)."""
        out: dict[str, Any] = {}
        for m in self.metadata.get(name, []):
            out.update(m)
        return out

    def nodes(self) -> dict[str, dict[str, Any]]:
        return {str(m.get("node")): m for m in self.metadata.get("redistro.node", [])}

    def robots(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for m in self.metadata.get("redistro.meta", []):
            out.update(m.get("robots", {}))
        return out


def read_log(path: Path) -> SessionLog:
    """Read a session log; raises ValueError naming the file if it is not one."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from zstandard import ZstdError  # a chunk that does not decompress

    from redistro.config.inputs import load_json
    from redistro.log.shapes import META, check

    out = SessionLog(path)
    chunks: dict[str, list[bytes]] = {}
    times: dict[str, list[int]] = {}
    dtypes: dict[str, np.dtype[Any]] = {}
    try:
        with open(path, "rb") as f:
            # every chunk's CRC checked: a flipped byte is a refusal, not changed data
            reader = make_reader(f, validate_crcs=True)
            for schema, channel, msg in reader.iter_messages(log_time_order=True):
                topic = channel.topic
                out.counts[topic] = out.counts.get(topic, 0) + 1
                if channel.message_encoding not in (MESSAGE_ENCODING, "json"):
                    raise ValueError(
                        f"{topic}: {channel.message_encoding!r} messages, not a log of this "
                        f"redistro (its channels are ROS 2 CDR)"
                    )
                name = schema.name if schema is not None else ""
                event = channel.message_encoding == "json" or name in (EVENT, MESSAGE)
                if not event and not name.startswith("redistro/msg/"):
                    continue  # a standard ROS 2 message (JointState ...): made from ours
                if not event:
                    assert schema is not None
                    if topic not in dtypes:
                        text = schema.data.decode()
                        out.schemas[topic] = text
                        dtypes[topic] = dtype_from_msg(text)
                    chunks.setdefault(topic, []).append(msg.data)
                    times.setdefault(topic, []).append(msg.log_time)
                else:
                    json_ = channel.message_encoding == "json"
                    if name == MESSAGE:
                        doc = message_doc(msg.data)
                    else:
                        text = msg.data.decode("utf-8") if json_ else event_json(msg.data)
                        doc = load_json(text)
                    if not isinstance(doc, dict):
                        raise ValueError(
                            f"{topic}: an event at {msg.log_time} ns is not a JSON object"
                        )
                    doc["log_time_ns"] = msg.log_time
                    out.events.setdefault(topic, []).append(doc)
            for meta in reader.iter_metadata():
                doc = {k: _loads(v) for k, v in meta.metadata.items()}
                if meta.name in META:
                    check(doc, META[meta.name], "metadata " + meta.name)
                out.metadata.setdefault(meta.name, []).append(doc)
    except (McapError, OSError, ValueError, KeyError, RecursionError, EOFError, ZstdError) as exc:
        text = str(exc) if len(str(exc)) <= 120 else str(exc)[:117] + "..."
        raise ValueError(f"{path}: not a readable session log ({text})") from exc
    for topic, parts in chunks.items():
        dt = dtypes[topic]
        wire = cdr_dtype(dt)
        blob = b"".join(parts)
        if len(blob) != wire.itemsize * len(parts) or any(
            p[:4] != CDR_HEADER for p in (parts[0], parts[-1])
        ):
            raise ValueError(f"{path}: {topic}: messages do not match their schema")
        got = np.frombuffer(blob, wire)
        packed = np.empty(len(parts), dt)
        for name in dt.names or ():
            packed[name] = got[name]
        out.arrays[topic] = packed
        out.log_times[topic] = np.asarray(times[topic], dtype=np.int64)
    return out


def _loads(v: str) -> Any:
    from redistro.config.inputs import load_json

    try:
        return load_json(v)
    except ValueError:
        return v
