"""A bag cut short (a recorder killed mid-write), read up to its last complete record.

MCAP: rosbags reads files without a summary section by scanning them, but refuses one whose end magic is missing.
`TolerantMcapReader` finds the last complete record itself (each record is an opcode byte and a u64 length) and
hands rosbags' scan that end.

ROS 1: a bag is read through the index at its end, which a recording killed mid-write never wrote (`index_pos` 0,
or pointing past the end). `TolerantReader1` then rebuilds the index by one pass over the chunks — connection and
message records inside each complete chunk — which is what `rosbag reindex` does, without ROS.

`tolerant_reader(path, store)` plugs either into an AnyReader; `truncation_of(reader)` says where a bag was cut.
"""

from __future__ import annotations

import struct
from pathlib import Path

from collections import defaultdict
from io import BytesIO

from rosbags.rosbag1.reader import (Chunk, ChunkInfo, Header, IndexData, ReaderError, RecordType, decompressors,
                                    read_uint32)
from rosbags.rosbag1.reader import Reader as Reader1
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


class TolerantReader1(Reader1):
    """rosbags' ROS 1 reader, which rebuilds a missing or damaged index from the complete chunks."""

    truncated_at: int | None = None

    def open(self) -> None:
        try:
            super().open()
            return
        except ReaderError as e:
            if "not indexed" not in str(e) and "index looks damaged" not in str(e):
                raise
        self.bio = self.path.open("rb")
        try:
            self._scan()
        except BaseException:
            self.bio.close()
            self.bio = None
            raise

    def _scan(self) -> None:
        bio, size = self.bio, self.path.stat().st_size
        bio.readline()  # the magic line, checked by the indexed open
        Header.read(bio, RecordType.BAGHEADER)
        bio.seek(read_uint32(bio), 1)
        conns, indexes, end = {}, defaultdict(list), bio.tell()
        while True:
            pos = bio.tell()
            try:
                header = Header.read(bio)
                n = read_uint32(bio)
            except ReaderError:
                break
            if bio.tell() + n > size:
                break
            if header.get_uint8("op") != RecordType.CHUNK:
                bio.seek(n, 1)  # index data and connection records after the chunks: rebuilt below
                end = bio.tell()
                continue
            compression = header.get_string("compression")
            datapos = bio.tell()
            raw = _decompressed(self.path, pos, compression, bio.read(n))
            self.chunks[pos] = Chunk(n, datapos, decompressors[compression])
            counts, t_min, t_max = self._scan_chunk(BytesIO(raw), len(raw), pos, conns, indexes)
            self.chunk_infos.append(ChunkInfo(pos, t_min, t_max + 1, counts))
            end = bio.tell()
        self.truncated_at = end
        self.indexes = {cid: sorted(indexes[cid]) for cid in conns}
        self.connections = [c._replace(msgcount=len(self.indexes[c.id])) for c in conns.values()]

    def _scan_chunk(self, chunk: BytesIO, size: int, pos: int, conns: dict, indexes) -> tuple[dict, int, int]:
        counts: dict[int, int] = defaultdict(int)
        t_min, t_max = 2**63 - 1, 0
        while chunk.tell() < size:
            offset = chunk.tell()
            header = Header.read(chunk)
            op = header.get_uint8("op")
            if op == RecordType.CONNECTION:
                bio, self.bio = self.bio, chunk  # read_connection reads its record from self.bio
                try:
                    chunk.seek(offset)
                    conn = self.read_connection()
                finally:
                    self.bio = bio
                conns.setdefault(conn.id, conn)
                continue
            n = read_uint32(chunk)
            if op == RecordType.MSGDATA:
                cid, t = header.get_uint32("conn"), header.get_time("time")
                indexes[cid].append(IndexData(t, pos, offset))
                counts[cid] += 1
                t_min, t_max = min(t_min, t), max(t_max, t)
            chunk.seek(n, 1)
        return dict(counts), t_min, t_max


def _decompressed(path: Path, pos: int, compression: str, data: bytes) -> bytes:
    """A complete chunk's records, or InputError: a chunk that does not decompress is damage, not a cut."""
    from swarmsplat.kernels.errors import InputError

    if compression not in decompressors:
        raise InputError(f"{path}: the chunk at byte {pos} is compressed with {compression!r}; expected one of "
                         f"{', '.join(decompressors)} (a ROS 1 bag)")
    try:
        return decompressors[compression](data)
    except (OSError, ValueError, RuntimeError, EOFError) as e:  # bz2: OSError / EOFError; lz4: RuntimeError
        why = " ".join(str(e).split()) or type(e).__name__
        raise InputError(f"{path}: the chunk at byte {pos} does not decompress as {compression} ({why}); expected "
                         "a ROS 1 bag's complete chunk") from None


def tolerant_reader(path: Path, default_typestore):
    """An unopened AnyReader on a ROS 1 bag or a bare .mcap whose reader tolerates a missing end."""
    from rosbags.highlevel import AnyReader

    reader = AnyReader([path], default_typestore=default_typestore)
    reader.readers = [TolerantReader1(path) if path.suffix == ".bag" else _TolerantReader2(path)]
    return reader


def truncation_of(reader) -> int | None:
    """Where the bag behind an opened AnyReader was cut (bytes read), or None when it ends properly."""
    for r in getattr(reader, "readers", []):
        for part in (r, getattr(r, "storage", None)):  # ROS 1: the reader; ROS 2: its storage plugin
            at = getattr(part, "truncated_at", None)
            if at is not None:
                return at
    return None
