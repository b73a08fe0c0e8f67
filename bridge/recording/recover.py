"""Rewrite a recording cut short (SIGKILL, a full disk) into a complete, indexed MCAP file.

A recorder killed with SIGKILL leaves chunks but no summary, chunk index or footer: the MCAP
library's seeking reader (``mcap.reader.make_reader`` on a file, Foxglove, the ``mcap`` CLI's
indexed commands) cannot open it, although every complete chunk is intact. :func:`recover`
reads what :func:`~koala_bridge.recording.mcap_file.open_recording` can (each chunk's CRC
checked) and writes it again with the MCAP library's writer: the header's profile, every
metadata record, schema and channel, and every message with its times and sequence number, in
file order, then the summary and footer. Attachments are not carried over (recordings have none).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from koala_bridge.recording.mcap_file import (
    Recording,
    RecordingError,
    open_recording,
)
from mcap.writer import CompressionType, Writer

log = logging.getLogger(__name__)


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> Recording:
    """Write the readable part of the recording ``src`` to ``dst`` as a complete MCAP file.

    ``salvage`` reading (:func:`open_recording`): a damaged chunk is skipped with a warning
    (which chunk, which time span is lost) and the records after it are read on -- its record
    length, when intact, leads to the next record; when the length itself is damaged, reading
    goes on at the next chunk record whose CRC holds. Damage with no intact chunk after it ends
    the readable part as a cut does. ``dst`` is written under a temporary name and renamed when
    complete; it must not exist. Returns what was read. Raises :class:`RecordingError` when
    ``src`` has nothing readable, ``dst`` exists or is ``src``, or ``dst`` cannot be written.
    """
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise RecordingError(f"{dst} exists: recover writes a new file, give another name")
    rec = open_recording(src, salvage=True)
    tmp = dst.with_name(f".{dst.name}.partial")
    try:
        with tmp.open("wb") as f:
            writer = Writer(f, compression=CompressionType.ZSTD, enable_data_crcs=True)
            writer.start(profile=rec.profile, library="koala-bridge recover")
            for name, values in rec.metadata.items():
                writer.add_metadata(name, values)
            schema_ids: dict[int, int] = {}
            for sid, s in sorted(rec.schema_records.items()):
                schema_ids[sid] = writer.register_schema(s.name, s.encoding, s.data)
            channel_ids: dict[int, int] = {}
            for cid, ch in sorted(rec.channel_records.items()):
                channel_ids[cid] = writer.register_channel(
                    ch.topic, ch.message_encoding, schema_ids.get(ch.schema_id, 0), ch.metadata
                )
            for m in rec.messages:
                writer.add_message(
                    channel_ids[m.channel_id],
                    m.log_time_ns,
                    m.data,
                    m.log_time_ns if m.publish_time_ns is None else m.publish_time_ns,
                    m.sequence,
                )
            writer.finish()
        os.replace(tmp, dst)
    except OSError as e:
        raise RecordingError(f"cannot write {dst}: {e.strerror or e}") from e
    finally:
        tmp.unlink(missing_ok=True)
    log.info(
        "%s: %d messages in %d channels written to %s%s",
        src, len(rec.messages), len(rec.channel_records), dst,
        "" if not rec.lost else " (parts of the source were lost: see the warnings above)",
    )
    return rec
