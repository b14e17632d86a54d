"""An MCAP file cut short (a recorder killed mid-write: no summary, no footer, often half a record at the end),
read up to its last complete record.

rosbags reads MCAP files without a summary section by scanning them, but refuses a file whose end magic is
missing. `TolerantMcapReader` finds the last complete record itself (each record is an opcode byte and a u64
length) and hands rosbags' scan that end; `tolerant_reader(path)` plugs it into an AnyReader for a bare .mcap.
"""

from __future__ import annotations

import struct
from pathlib import Path

from rosbags.rosbag2.reader import Reader as Reader2
from rosbags.rosbag2.storage_mcap import McapReader

MAGIC = b"\x89MCAP0\r\n"


def last_complete_record(path: Path, data_start: int) -> int:
    """The offset just past the last record that lies wholly inside the file, scanning from `data_start`."""
    size = path.stat().st_size
    end = data_start
    with path.open("rb") as f:
        f.seek(data_start)
        while True:
            head = f.read(9)
            if len(head) < 9:
                return end
            (length,) = struct.unpack("<Q", head[1:])
            if end + 9 + length > size:
                return end
            end += 9 + length
            f.seek(end)


class TolerantMcapReader(McapReader):
    """rosbags' McapReader, which on a file without its end magic reads the complete records before the cut."""

    truncated_at: int | None = None

    def _open(self) -> None:
        from rosbags.rosbag2.errors import ReaderError

        try:
            super()._open()
            return
        except ReaderError as e:
            if "end magic" not in str(e):
                raise
        assert self.bio is not None
        self.data_end = last_complete_record(self.path, self.data_start)
        self.truncated_at = self.data_end
        self.meta_scan()
        stats = self.statistics
        assert stats is not None
        self.connections = [c._replace(msgcount=stats.channel_message_counts.get(c.id, 0)) for c in self.connections]
        n = stats.message_count
        self.metadata = self.metadata._replace(duration=stats.end_time - stats.start_time + 1 if n else 0,
                                               start_time=stats.start_time if n else 2**63 - 1,
                                               end_time=stats.end_time + 1 if n else 0, message_count=n)


class _TolerantReader2(Reader2):
    STORAGE_PLUGINS = {**Reader2.STORAGE_PLUGINS, ".mcap": TolerantMcapReader}


def tolerant_reader(path: Path, default_typestore):
    """An unopened AnyReader on a bare .mcap whose storage reader tolerates a missing end."""
    from rosbags.highlevel import AnyReader

    reader = AnyReader([path], default_typestore=default_typestore)
    reader.readers = [_TolerantReader2(path)]
    return reader


def truncation_of(reader) -> int | None:
    """Where the bag behind an opened AnyReader was cut (bytes read), or None when it ends properly."""
    for r in getattr(reader, "readers", []):
        at = getattr(getattr(r, "storage", None), "truncated_at", None)
        if at is not None:
            return at
    return None
