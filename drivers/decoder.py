"""The incremental stream decoder (public as ``millsense.drivers.protocol.StreamDecoder``).

Clean path: a run of equal-length SAMPLES frames laid end to end is recognised
with one numpy comparison over a 2-D view of the buffer, their CRCs are computed
together and their payloads become one int16 array.  Anything else goes frame by
frame with the spec's rule: check the CRC before trusting a length, else drop one
byte and hunt for the next sync.  Between calls at most one incomplete frame is
kept, so garbage cannot grow memory.  Live, a read usually holds one frame shaped
like the last one: that read takes a shortcut (`_one_like_last`, issue 13).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from millsense.drivers.protocol import (
    _COMMAND_ARG_LEN,
    CONTEXT_LEN,
    HEADER_LEN,
    INDEX_MOD,
    MAX_EXTENSION,
    MAX_PAYLOAD,
    MAX_SAMPLES_PER_FRAME,
    OVERHEAD,
    SCALAR_BELOW,
    STATUS_LEN_V1,
    STATUS_LEN_V2,
    SYNC,
    TYPE_COMMAND,
    TYPE_CONTEXT,
    TYPE_DESCRIPTOR,
    TYPE_SAMPLES,
    TYPE_STATUS,
    Channel,
    ChannelKind,
    Command,
    Context,
    Descriptor,
    Samples,
    Status,
    crc16_modbus,
    crc16_modbus_rows,
)


@dataclass
class DecoderStats:
    """Counters of a StreamDecoder.

    ``descriptor_mismatch`` counts refused SAMPLES frames; ``samples_before_descriptor``
    counts the samples (not frames) dropped for want of a descriptor.
    ``consumed_bytes`` = bytes of good frames + ``dropped_bytes``.
    """

    frames: int = 0
    samples: int = 0
    bad_crc: int = 0
    dropped_bytes: int = 0
    unknown_type: int = 0
    bad_length: int = 0
    descriptor_mismatch: int = 0
    samples_before_descriptor: int = 0
    consumed_bytes: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


Frame = Samples | Descriptor | Status | Context | Command

_KNOWN_TYPES = (TYPE_SAMPLES, TYPE_DESCRIPTOR, TYPE_STATUS, TYPE_COMMAND, TYPE_CONTEXT)
_NEED_MORE = -1
_BAD = -2
_MAX_RUN_ROWS = 8192
_MIN_RUN = SCALAR_BELOW
# bytes needed before a frame's length can be checked against its type
_HEADER_NEED = {TYPE_SAMPLES: 11, TYPE_DESCRIPTOR: 9, TYPE_STATUS: 5, TYPE_COMMAND: 6, TYPE_CONTEXT: 5}


class StreamDecoder:
    """Incremental decoder: ``feed(bytes)`` returns the frames completed so far.

    Between calls it keeps at most one incomplete frame (< 4103 bytes), so a
    stream of garbage cannot grow memory.
    """

    def __init__(self) -> None:
        self._rest = b""
        self.descriptor: Descriptor | None = None
        self.stats = DecoderStats()
        # the last SAMPLES frame accepted: (its first 5 bytes, its channel and sample count bytes, its length)
        self._shape: tuple[bytes, bytes, int] | None = None
        # the last DESCRIPTOR frame decoded: (its bytes, sync to CRC; the Descriptor parsed from them)
        self._last_descriptor: tuple[bytes, Descriptor] | None = None

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._rest)

    def feed(self, data: bytes) -> list[Frame]:
        if not self._rest and self._shape is not None and len(data) >= self._shape[2]:
            first = self._one_like_last(data)
            if first is not None:
                flen = self._shape[2]
                if len(data) == flen:
                    return [first]
                rest = self._feed(data[flen:])  # a STATUS after it, say, or more frames: the general path
                return _merge([first, *rest]) if rest and isinstance(rest[0], Samples) else [first, *rest]
        return self._feed(data)

    def _feed(self, data: bytes) -> list[Frame]:
        buf = self._rest + bytes(data) if self._rest else bytes(data)
        out: list[Frame] = []
        p = 0
        n = len(buf)
        st = self.stats
        while True:
            q = buf.find(SYNC, p)
            if q < 0:
                # keep a trailing 0xA5: it may be the first half of a sync
                keep = 1 if n > p and buf[n - 1] == 0xA5 else 0
                st.dropped_bytes += n - keep - p
                p = n - keep
                break
            if q > p:
                st.dropped_bytes += q - p
                p = q
            if self.descriptor is not None:
                p2 = self._fast_run(buf, p, out)
                if p2 != p:
                    p = p2
                    continue
            r = self._one_frame(buf, p, out)
            if r == _NEED_MORE:
                break
            if r == _BAD:
                st.dropped_bytes += 1
                p += 1
            else:
                p = r
        st.consumed_bytes += p
        self._rest = buf[p:]
        return _merge(out)

    def _one_like_last(self, data: bytes) -> Samples | None:
        """The live common case: a read that begins with one whole SAMPLES frame shaped like the
        last one accepted (alone, or with a STATUS behind it). Few steps on purpose (issue 13): the
        reader thread runs this once per frame with its caches cold, where each step costs several
        times what it does in a loop. None: anything else (the general path decides, and counts)."""
        prefix, shape, flen = self._shape  # type: ignore[misc]
        if data[:5] != prefix or data[9:11] != shape:
            return None
        if crc16_modbus(data[2 : flen - 2]) != data[flen - 2] | (data[flen - 1] << 8):
            return None
        c, s = shape[0], shape[1]
        counts = np.frombuffer(data, dtype="<i2", count=c * s, offset=11).reshape(s, c).astype(np.int16)
        st = self.stats
        st.frames += 1
        st.samples += s
        st.consumed_bytes += flen
        return Samples(data[5] | (data[6] << 8) | (data[7] << 16) | (data[8] << 24), counts)

    # -- frame by frame -------------------------------------------------------

    def _one_frame(self, buf: bytes, p: int, out: list) -> int:
        """Decode the frame at ``p`` (a sync): new position, _NEED_MORE or _BAD."""
        st = self.stats
        n = len(buf)
        if n - p < HEADER_LEN:
            return _NEED_MORE
        ftype = buf[p + 2]
        length = buf[p + 3] | (buf[p + 4] << 8)
        if ftype not in _KNOWN_TYPES:
            st.unknown_type += 1
            return _BAD
        if length > MAX_PAYLOAD:
            st.bad_length += 1
            return _BAD
        if n - p < _HEADER_NEED[ftype]:
            return _NEED_MORE
        if not _plausible_length(ftype, length, buf, p, self.descriptor):
            st.bad_length += 1
            return _BAD
        end = p + HEADER_LEN + length + 2
        if end > n:
            return _NEED_MORE
        if ftype == TYPE_DESCRIPTOR and self._last_descriptor is not None:
            # the DAQ repeats its DESCRIPTOR once a second: the very bytes of one already checked and parsed
            # need neither again (replay: the repeats took about a fifth of the decoding time)
            frame_bytes, known = self._last_descriptor
            if buf[p:end] == frame_bytes:
                self.descriptor = known
                self._shape = None
                out.append(known)
                st.frames += 1
                return end
        body = buf[p + 2 : end - 2]
        if crc16_modbus(body) != (buf[end - 2] | (buf[end - 1] << 8)):
            st.bad_crc += 1
            return _BAD
        payload = body[3:]
        if ftype == TYPE_SAMPLES:
            first, c, s = struct.unpack_from("<IBB", payload)
            counts = np.frombuffer(payload, dtype="<i2", offset=6).reshape(s, c).astype(np.int16)
            if self._accept_samples(Samples(first, counts), out):
                self._shape = (buf[p : p + 5], buf[p + 9 : p + 11], end - p)
        elif ftype == TYPE_DESCRIPTOR:
            d = _parse_descriptor(payload)
            if d is None:
                st.bad_length += 1
                return _BAD
            self.descriptor = d
            self._last_descriptor = (buf[p:end], d)
            self._shape = None
            out.append(d)
        elif ftype == TYPE_STATUS:
            if length == STATUS_LEN_V1:
                out.append(Status(*struct.unpack("<BBH", payload)))
            else:  # version 2: the feed override follows; a later version's tail is ignored
                out.append(Status(*struct.unpack_from("<BBHH", payload)))
        elif ftype == TYPE_CONTEXT:
            out.append(Context(*struct.unpack("<IIIHB", payload)))
        else:
            cmd = payload[0]
            arg = None
            if length == 2:
                arg = payload[1]
            elif length == 3:
                arg = payload[1] | (payload[2] << 8)
            out.append(Command(cmd, arg))
        st.frames += 1
        return end

    def _accept_samples(self, s: Samples, out: list) -> bool:
        st = self.stats
        n, c = s.counts.shape
        if self.descriptor is None:
            st.samples_before_descriptor += n
        elif c != self.descriptor.channel_count:
            st.descriptor_mismatch += 1
        else:
            st.samples += n
            out.append(s)
            return True
        return False

    # -- the vectorised path --------------------------------------------------

    def _fast_run(self, buf: bytes, p: int, out: list) -> int:
        """Decode a run of identical-shape SAMPLES frames at ``p``; return the new position.

        Returns ``p`` unchanged when fewer than ``_MIN_RUN`` such frames are available,
        leaving the frame-by-frame path to decide.
        """
        n = len(buf)
        if n - p < 11 or buf[p + 2] != TYPE_SAMPLES:
            return p
        length = buf[p + 3] | (buf[p + 4] << 8)
        c, s = buf[p + 9], buf[p + 10]
        if c != self.descriptor.channel_count or not 1 <= s <= 64 or length != 6 + 2 * c * s:
            return p
        flen = length + OVERHEAD
        kmax = min((n - p) // flen, _MAX_RUN_ROWS)
        if kmax < _MIN_RUN:
            return p
        all_rows = np.frombuffer(buf, dtype=np.uint8, count=kmax * flen, offset=p).reshape(kmax, flen)
        head = all_rows[0, :11]
        # how far does the run of identical headers go?  Look in a growing window, so
        # that a run broken early (noise) costs little.
        window = min(kmax, 128)
        while True:
            rows = all_rows[:window]
            same = rows[:, :11] == head      # sync, type, length, channels, samples; not the index (5:9)
            same[:, 5:9] = True
            same = same.all(axis=1)
            if not same.all():
                k = int(np.argmin(same))
                break
            if window == kmax:
                k = kmax
                break
            window = min(kmax, window * 4)
        if k < _MIN_RUN:
            return p
        rows = rows[:k]
        crc = crc16_modbus_rows(rows[:, 2 : flen - 2])
        good = crc == rows[:, flen - 2 : flen].copy().view("<u2")[:, 0]
        if not good.all():
            # A bad frame is skipped whole only if hunting inside it could not
            # find a sync; otherwise stop here and let the byte-wise path decide.
            for r in np.flatnonzero(~good).tolist():
                start = p + r * flen
                if buf.find(SYNC, start + 1, start + flen) >= 0 or r == k - 1:
                    k = r
                    break
            rows = rows[:k]
            good = good[:k]
        if k == 0:
            return p
        st = self.stats
        nbad = k - int(good.sum())
        st.bad_crc += nbad
        st.dropped_bytes += nbad * flen
        st.frames += k - nbad
        ok = rows[good]
        if len(ok):
            firsts = np.ascontiguousarray(ok[:, 5:9]).view("<u4")[:, 0].astype(np.int64)
            counts = np.ascontiguousarray(ok[:, 11 : flen - 2]).view("<i2").reshape(len(ok) * s, c)
            # split where the index does not continue (a skipped frame, a restart)
            breaks = np.flatnonzero((firsts[1:] - firsts[:-1]) % INDEX_MOD != s) + 1
            starts = [0, *breaks.tolist()]
            ends = [*breaks.tolist(), len(ok)]
            first_list = firsts.tolist()
            for a, b in zip(starts, ends):
                out.append(Samples(first_list[a], counts[a * s : b * s]))
            st.samples += len(ok) * s
        return p + k * flen


def _plausible_length(ftype: int, length: int, buf: bytes, p: int, descriptor: Descriptor | None) -> bool:
    """Is ``length`` consistent with the frame type?  The caller ensured the bytes are there.

    Version 1 lengths are exact.  A DESCRIPTOR that says version >= 2 carries the
    capabilities byte and may carry up to MAX_EXTENSION bytes more; a STATUS has the
    version-2 feed override (6 bytes), and a longer tail only once the device's
    descriptor said version >= 2.
    """
    if ftype == TYPE_SAMPLES:
        c, s = buf[p + 9], buf[p + 10]
        return c >= 1 and 1 <= s <= MAX_SAMPLES_PER_FRAME and length == 6 + 2 * c * s
    if ftype == TYPE_DESCRIPTOR:
        c = buf[p + 8]
        if c < 1:
            return False
        v1_len = 4 + 9 * c
        return length == v1_len or (buf[p + 5] >= 2 and v1_len < length <= v1_len + 1 + MAX_EXTENSION)
    if ftype == TYPE_STATUS:
        if length == STATUS_LEN_V1 or length == STATUS_LEN_V2:
            return True
        return (
            descriptor is not None
            and descriptor.protocol_version >= 2
            and STATUS_LEN_V2 < length <= STATUS_LEN_V2 + MAX_EXTENSION
        )
    if ftype == TYPE_CONTEXT:
        return length == CONTEXT_LEN
    arg_len = _COMMAND_ARG_LEN.get(buf[p + 5])
    return arg_len is not None and length == 1 + arg_len


def _parse_descriptor(payload: bytes) -> Descriptor | None:
    version, rate, c = struct.unpack_from("<BHB", payload)
    channels = []
    for i in range(c):
        kind, raw = struct.unpack_from("<B8s", payload, 4 + 9 * i)
        try:
            name = raw.rstrip(b"\0").decode("ascii")
            channels.append(Channel(ChannelKind(kind), name))
        except (UnicodeDecodeError, ValueError):
            channels.append(Channel(ChannelKind.OTHER, raw.rstrip(b"\0").decode("latin-1")))
    if rate == 0:
        return None
    capabilities = 0
    if version >= 2 and len(payload) > 4 + 9 * c:
        capabilities = payload[4 + 9 * c]
    return Descriptor(rate, tuple(channels), version, capabilities)


def _merge(frames: list[Frame]) -> list[Frame]:
    """Merge consecutive Samples with contiguous indices into one."""
    if len(frames) < 2:
        return frames
    merged: list[Frame] = []
    group: list[Samples] = []
    next_index = -1

    def flush() -> None:
        if len(group) == 1:
            merged.append(group[0])
        elif group:
            merged.append(Samples(group[0].first_index, np.concatenate([g.counts for g in group])))
        group.clear()

    for f in frames:
        if isinstance(f, Samples):
            if group and f.first_index == next_index:
                group.append(f)
            else:
                flush()
                group.append(f)
            next_index = (f.first_index + len(f.counts)) % INDEX_MOD
        else:
            flush()
            merged.append(f)
    flush()
    return merged
