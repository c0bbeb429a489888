"""The messages of a rosbag2 whose recorder was killed (no metadata.yaml, an MCAP file without
its summary and footer), for `render --run` and `view`: rosbags' readers need both, so this
walks the MCAP records from the start and keeps every complete chunk (`mapf-fleet record`
writes one per tick: `ros.bag`). A chunk torn by the kill ends the walk. Messages are decoded
with the definitions the bag's own schemas carry (as rosbags' AnyReader does), so no ROS is
needed. MCAP's record layout: https://mcap.dev/spec.
"""

from __future__ import annotations

import struct
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"
SCHEMA, CHANNEL, MESSAGE, CHUNK, DATA_END, FOOTER = 0x03, 0x04, 0x05, 0x06, 0x0F, 0x02


class SalvageError(ValueError):
    """Nothing can be read from the file (the message names it and why)."""


def mcap_file(bag_dir: Path) -> Path | None:
    """The bag's .mcap file (`record` names it after the directory), or None."""
    found = sorted(Path(bag_dir).glob("*.mcap"))
    return found[0] if found else None


def _records(data: bytes, pos: int, end: int):
    """(opcode, body) of each complete record of data[pos:end]; a torn last record is left out."""
    while pos + 9 <= end:
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        stop = pos + 9 + length
        if stop > end:
            return
        yield op, memoryview(data)[pos + 9:stop]
        pos = stop


def _string(body, pos: int) -> tuple[str, int]:
    (length,) = struct.unpack_from("<I", body, pos)
    return bytes(body[pos + 4:pos + 4 + length]).decode(), pos + 4 + length


def _walk(path: Path):
    data = path.read_bytes()
    if not data:
        raise SalvageError(f"{path}: the file is empty (the recorder was stopped before it wrote "
                           f"its first tick)")
    if not data.startswith(MAGIC):
        raise SalvageError(f"{path}: not an MCAP file (no MCAP magic at its start)")
    schemas: dict[int, tuple[str, str, str]] = {}  # id -> (type name, encoding, definition)
    channels: dict[int, tuple[str, int]] = {}  # id -> (topic, schema id)
    messages = []

    def take(op, body):
        if op == SCHEMA:
            (sid,) = struct.unpack_from("<H", body, 0)
            name, pos = _string(body, 2)
            encoding, pos = _string(body, pos)
            (length,) = struct.unpack_from("<I", body, pos)
            schemas[sid] = (name, encoding, bytes(body[pos + 4:pos + 4 + length]).decode())
        elif op == CHANNEL:
            cid, sid = struct.unpack_from("<HH", body, 0)
            topic, _ = _string(body, 4)
            channels[cid] = (topic, sid)
        elif op == MESSAGE:
            cid, _, log_time = struct.unpack_from("<HIQ", body, 0)
            if cid in channels:
                topic, sid = channels[cid]
                messages.append((topic, schemas[sid][0] if sid in schemas else "", log_time,
                                 bytes(body[22:])))

    for op, body in _records(data, len(MAGIC), len(data)):
        if op in (DATA_END, FOOTER):
            break
        if op == CHUNK:
            (size,) = struct.unpack_from("<Q", body, 16)
            compression, pos = _string(body, 28)
            if compression:
                raise SalvageError(f"{path}: chunks compressed with {compression!r} (a bag "
                                   f"`mapf-fleet record` did not write)")
            (length,) = struct.unpack_from("<Q", body, pos)
            chunk = bytes(body[pos + 8:pos + 8 + length])
            for inner_op, inner in _records(chunk, 0, len(chunk)):
                take(inner_op, inner)
        else:
            take(op, body)
    return messages, schemas


def decoded_messages(path):
    """(topic, stamp ns, message) of every complete message of the unfinished MCAP file `path`,
    decoded with its schemas' definitions (rosbags' typestore, pure Python)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    messages, schemas = _walk(Path(path))
    typestore = get_typestore(Stores.EMPTY)
    types = {}
    for name, encoding, text in schemas.values():
        if encoding == "ros2msg":
            types.update(get_types_from_msg(text, name))
    typestore.register(types)
    for topic, msgtype, stamp, raw in messages:
        if msgtype in types:
            yield topic, stamp, typestore.deserialize_cdr(raw, msgtype)
