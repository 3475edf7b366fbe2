"""Make a cut-off MCAP log readable by standard readers.

A log cut off by a full disk or a kill -9 has no summary and no footer: readers that seek to
the summary (the `mcap` CLI, `mcap.reader.make_reader` on a file) find no messages. This
module streams it up to its last complete record, as McapLogReader does, and writes every
schema, channel, metadata record, attachment and message it read into a new, finished file. A
``ros2``-profile file that lost its ``rosbag2`` metadata record (written at a file's end) gets one
counting what was kept (runtime/aefabmap_runtime/adapters/rosbag2_mcap.py), as rosbag2 would have written it.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass
from pathlib import Path

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.durable_files import open_regular
from aefabmap_runtime.adapters.mcap_log import complete_records
from aefabmap_runtime.adapters.rosbag2_mcap import ROSBAG2_METADATA, Rosbag2Summary


@dataclass
class RepairReport:
    """What a repair kept: messages, channels, metadata records; truncated: the source had no
    clean end (reason: why reading stopped)."""

    source: str
    out: str
    messages: int = 0
    channels: int = 0
    metadata: int = 0
    truncated: bool = False
    reason: str = ""

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def repair_log(source: str | Path, out: str | Path) -> RepairReport:
    """Copy every complete record of MCAP `source` into a new finished MCAP `out` (never
    overwritten). LogError when `source` is not a regular MCAP file or `out` cannot be written
    (a full disk included): `out` is then removed, `source` is never changed."""
    source, out = Path(source), Path(out)
    report = RepairReport(str(source), str(out))
    try:  # a FIFO or a device is refused before anything reads it: open() on a FIFO blocks
        fh = os.fdopen(open_regular(source, follow_symlinks=True, error=LogError), "rb")
    except OSError as exc:
        raise LogError(f"{source}: cannot read: {exc.strerror or exc}") from exc
    with fh:
        try:
            fd = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except OSError as exc:
            raise LogError(f"{out}: cannot create (it must not exist yet): {exc.strerror or exc}") from exc
        try:
            with os.fdopen(fd, "wb") as sink:
                started = _copy(fh, sink, report, out.name)
        except BaseException as exc:
            _remove(out)  # a partial file is no repaired log
            if isinstance(exc, OSError):
                raise LogError(_write_error(out, source, exc)) from exc
            raise
    if not started:
        _remove(out)
        raise LogError(f"{source}: not an MCAP file (no complete record): {report.reason}")
    return report


def _copy(fh, sink, report: RepairReport, out_name: str) -> bool:
    """Write the complete records of `fh` into a finished MCAP on `sink` (file name `out_name`);
    False when there was none."""
    writer = Writer(sink, compression=CompressionType.ZSTD)
    schemas: dict[int, tuple[int, str]] = {}  # source schema id -> (our id, type name)
    channel_ids: dict[int, int] = {}
    bag: Rosbag2Summary | None = None  # a ros2 file's topics and counts, for its rosbag2 record
    started = False
    for record in complete_records(fh, report):
        if not started:
            profile = record.profile if isinstance(record, Header) else ""
            writer.start(profile=profile, library="aefabmap log repair")
            bag = Rosbag2Summary() if profile == "ros2" else None
            started = True
        if isinstance(record, Schema):
            schemas[record.id] = (writer.register_schema(record.name, record.encoding, record.data), record.name)
        elif isinstance(record, Channel):
            schema_id, type_name = schemas.get(record.schema_id, (0, ""))
            channel_ids[record.id] = writer.register_channel(
                record.topic, record.message_encoding, schema_id, dict(record.metadata))
            if bag is not None and record.message_encoding == "cdr" and type_name:
                bag.add_channel(channel_ids[record.id], record.topic, type_name, dict(record.metadata))
            report.channels += 1
        elif isinstance(record, Message) and record.channel_id in channel_ids:
            writer.add_message(channel_ids[record.channel_id], record.log_time, record.data, record.publish_time,
                               record.sequence)
            if bag is not None:
                bag.count(channel_ids[record.channel_id], record.log_time)
            report.messages += 1
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, dict(record.metadata))
            report.metadata += 1
            if record.name == ROSBAG2_METADATA:
                bag = None  # the file was finished: its own record is kept
        elif isinstance(record, Attachment):
            writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                  record.data)
    if started:
        if bag is not None:
            writer.add_metadata(ROSBAG2_METADATA, bag.record(out_name))
            report.metadata += 1
        writer.finish()
    return started


def _write_error(out: Path, source: Path, exc: OSError) -> str:
    why = "the disk is full" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else (exc.strerror or str(exc))
    return f"{out}: cannot write the repaired log: {why}; the partial file was removed, {source} is unchanged"


def _remove(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass
