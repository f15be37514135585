"""ROS1 ``.bag`` files and ROS2 bag folders (sqlite3 ``.db3`` or ``.mcap`` + ``metadata.yaml``)
as a :class:`~aerovis_slam.io.source.Recording`, read with the ``rosbags`` package (no ROS).

Message types understood:

* events: ``dvs_msgs/msg/EventArray`` (and the identical ``prophesee_event_msgs/msg/EventArray``),
  ``event_camera_msgs/msg/EventPacket`` (and its predecessor ``event_array_msgs/msg/EventArray``)
  with ``encoding`` ``evt3``, ``libcaer``, ``libcaer_cmp`` or ``mono``;
* IMU: ``sensor_msgs/msg/Imu`` (rad/s, m/s²);
* ground truth: ``geometry_msgs/msg/PoseStamped``, ``nav_msgs/msg/Odometry``;
* calibration: ``sensor_msgs/msg/CameraInfo`` (intrinsics only; ``T_imu_cam`` is identity
  because a bag does not say it).

Event topics become ``cam0``, ``cam1``... in sorted topic order, or in the order of ``topics=``.

Time: everything is returned in int64 µs on the ROS (header) clock. ``dvs_msgs`` events carry ROS
times already. ``event_camera_msgs`` packets carry *sensor* times: ``evt3`` and ``mono`` are on
the camera's own clock (the EVT 3.0 words are µs; ``time_base`` is unused by ``evt3``), so they
are shifted onto the header clock by one constant offset, ``header.stamp`` minus the sensor time
of the first event of the first packet; ``libcaer``/``libcaer_cmp`` sensor times are already
host (epoch) times. ``time_reference="sensor"`` turns the shift off. :meth:`RosbagRecording.
iter_decoded` gives the raw sensor times in ns (what ``event_camera_codecs`` reports).

Type definitions come from the bag where it embeds them and can be parsed; types it lacks
(older ROS2 sqlite3 bags store none; some mcap IDL does not parse) come from the ``rosbags``
stock store plus the event-message definitions below.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..calib import CameraCalibration, RigCalibration
from ..errors import DataError
from ..events import EventArray
from ..measurements import ImuSamples, PoseSamples
from .libcaer_codec import LibcaerCmpDecoder, LibcaerDecoder
from .prophesee_codecs import CodecError, DecodedEvents, make_decoder, regroup_events
from .source import Recording, register_format

__all__ = ["RosbagRecording", "EVENT_MSG_DEFINITIONS", "decode_mono_packet"]

_DVS_EVENT = """uint16 x
uint16 y
time ts
bool polarity
"""
_DVS_ARRAY = """Header header
uint32 height
uint32 width
{pkg}/Event[] events
"""
# event_camera_msgs/EventPacket as shipped by ros-event-camera (same field order for ROS1 and 2,
# and for its predecessor event_array_msgs/EventArray).
_EVENT_PACKET = """Header header
uint32 height
uint32 width
uint64 seq
uint64 time_base
string encoding
bool is_bigendian
uint8[] events
"""

#: msgtype -> .msg text of the event messages that ROS installs do not ship with rosbags
EVENT_MSG_DEFINITIONS = {
    "dvs_msgs/msg/Event": _DVS_EVENT,
    "dvs_msgs/msg/EventArray": _DVS_ARRAY.format(pkg="dvs_msgs"),
    "prophesee_event_msgs/msg/Event": _DVS_EVENT,
    "prophesee_event_msgs/msg/EventArray": _DVS_ARRAY.format(pkg="prophesee_event_msgs"),
    "event_camera_msgs/msg/EventPacket": _EVENT_PACKET,
    "event_array_msgs/msg/EventArray": _EVENT_PACKET,
}

_DVS_TYPES = {"dvs_msgs/msg/EventArray", "prophesee_event_msgs/msg/EventArray"}
_PACKET_TYPES = {"event_camera_msgs/msg/EventPacket", "event_array_msgs/msg/EventArray"}
EVENT_TYPES = _DVS_TYPES | _PACKET_TYPES
IMU_TYPES = {"sensor_msgs/msg/Imu"}
GT_TYPES = {"geometry_msgs/msg/PoseStamped", "nav_msgs/msg/Odometry"}
CAMINFO_TYPES = {"sensor_msgs/msg/CameraInfo"}
# Packet encodings whose sensor time is already host (epoch) time.
_EPOCH_ENCODINGS = {"libcaer", "libcaer_cmp"}


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def decode_mono_packet(data, time_base_ns: int) -> DecodedEvents:
    """Decode an ``event_camera_msgs`` ``mono`` packet (deprecated encoding).

    Each event is a little-endian uint64: [63] polarity, [62:48] y, [47:32] x, [31:0] dt (ns);
    sensor time (ns) = ``time_base`` + dt.

    Raises:
        CodecError: the packet is not a whole number of 8-byte events.
    """
    buf = np.frombuffer(memoryview(data).cast("B") if not isinstance(data, np.ndarray) else data.view(np.uint8).reshape(-1), np.uint8)
    if len(buf) % 8:
        raise CodecError(f"mono packet of {len(buf)} bytes is not a whole number of 8-byte events")
    w = buf.view("<u8")
    t = int(time_base_ns) + (w & 0xFFFFFFFF).astype(np.int64)
    return DecodedEvents(t, ((w >> 32) & 0xFFFF).astype(np.uint16), ((w >> 48) & 0x7FFF).astype(np.uint16),
                         (w >> 63).astype(np.int8))


# ------------------------------------------------------------------ dvs_msgs fast path
_DVS_ROS1 = np.dtype({"names": ["x", "y", "sec", "nsec", "p"], "formats": ["<u2", "<u2", "<u4", "<u4", "u1"],
                      "offsets": [0, 2, 4, 8, 12], "itemsize": 13})


def _dvs_from_raw(raw: bytes, is2: bool) -> tuple[np.ndarray, ...] | None:
    """Parse a dvs_msgs/EventArray straight from its serialized bytes (rosbags builds one Python
    object per event, ~100x slower). Returns (t_ns, x, y, p, width, height) or None when the
    bytes do not match the expected layout, in which case the caller deserializes normally."""
    buf = memoryview(raw)
    try:
        if is2:
            if len(buf) < 4 or buf[1] != 1:  # little-endian CDR only
                return None
            body = buf[4:]
            o = 8  # stamp sec, nanosec
            n_frame = int(np.frombuffer(body, "<u4", 1, o)[0])
            o += 4 + n_frame
            o = (o + 3) & ~3
            height, width, n = (int(v) for v in np.frombuffer(body, "<u4", 3, o))
            o += 12
            # element layout depends on its start's alignment (CDR aligns relative to the body):
            # at 0 mod 4: x@0 y@2 sec@4 nsec@8 pol@12 (13 bytes, next at +14);
            # at 2 mod 4: x@0 y@2 sec@6 nsec@10 pol@14 (next at +16), so all but the first stride 16
            if n == 0:
                return np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.int8), width, height
            end = o + 14 + (n - 1) * 16 - 1 if n > 1 else o + 13
            if end != len(body):
                return None
            arr = np.frombuffer(body, np.uint8)
            def field(off0, off, fmt, size):
                first = np.frombuffer(body, fmt, 1, o + off0)
                rest = np.ndarray((n - 1,), fmt, arr.data, o + 14 + off, (16,)) if n > 1 else np.empty(0, fmt)
                return np.concatenate([first, rest])
            x = field(0, 0, "<u2", 2)
            y = field(2, 2, "<u2", 2)
            sec = field(4, 6, "<i4", 4).astype(np.int64)
            nsec = field(8, 10, "<u4", 4).astype(np.int64)
            p = field(12, 14, "u1", 1)
        else:
            o = 12  # seq, stamp sec, nsec
            n_frame = int(np.frombuffer(buf, "<u4", 1, o)[0])
            o += 4 + n_frame
            height, width, n = (int(v) for v in np.frombuffer(buf, "<u4", 3, o))
            o += 12
            if o + 13 * n != len(buf):
                return None
            ev = np.frombuffer(buf, _DVS_ROS1, n, o)
            x, y, p = ev["x"], ev["y"], ev["p"]
            sec, nsec = ev["sec"].astype(np.int64), ev["nsec"].astype(np.int64)
    except (ValueError, IndexError):
        return None
    if n and p.max() > 1:
        return None
    return sec * 1_000_000_000 + nsec, x.astype(np.uint16), y.astype(np.uint16), p.astype(np.int8), width, height


class _TopicDecoder:
    """Per-topic decoding state: codec decoders persist across the topic's messages."""

    def __init__(self):
        self.decoder = None
        self.encoding: str | None = None


class RosbagRecording(Recording):
    """A ROS1 bag or ROS2 bag folder.

    Args:
        path: a ``.bag`` file, a ROS2 bag folder (with ``metadata.yaml``), or a bare ``.db3``/``.mcap``.
        topics: event topics in camera order (default: all event topics, sorted).
        imu_topic: the IMU topic (default: the first ``sensor_msgs/Imu`` topic, sorted).
        gt_topic: the ground-truth topic (default: the first PoseStamped/Odometry topic, sorted).
        time_reference: ``"ros"`` (events on the header clock, consistent with IMU and ground
            truth) or ``"sensor"`` (packet events on the camera's own clock).

    Raises:
        DataError: unreadable/truncated bag, missing topic, or a requested topic whose message
            type is not an event type.
    """

    format_name = "rosbag"

    def __init__(self, path, topics: list[str] | None = None, imu_topic: str | None = None,
                 gt_topic: str | None = None, time_reference: str = "ros"):
        super().__init__(path)
        if time_reference not in ("ros", "sensor"):
            raise DataError(self.path, f"time_reference must be 'ros' or 'sensor', not {time_reference!r}")
        self.time_reference = time_reference
        self._readers = self._open_readers()
        self.is2 = not (self.path.is_file() and self.path.suffix == ".bag")
        self.format_name = "rosbag2" if self.is2 else "rosbag1"
        self.connections = [c for r in self._readers for c in r.connections]
        self.topic_types: dict[str, str] = {}
        for c in self.connections:
            self.topic_types.setdefault(c.topic, c.msgtype)
        self.typestore = self._build_typestore()

        if topics is None:
            topics = sorted(t for t, ty in self.topic_types.items() if ty in EVENT_TYPES)
        for t in topics:
            if t not in self.topic_types:
                raise DataError(self.path, f"topic {t!r} is not in the bag (it has {sorted(self.topic_types)})")
            if self.topic_types[t] not in EVENT_TYPES:
                raise DataError(self.path, f"topic {t!r} has message type {self.topic_types[t]!r}, which is not an "
                                f"event type (expected one of {sorted(EVENT_TYPES)})")
        self.event_topics = list(topics)
        self.imu_topic = self._pick(imu_topic, IMU_TYPES, "IMU")
        self.gt_topic = self._pick(gt_topic, GT_TYPES, "ground truth")
        self._sizes: dict[str, tuple[int, int]] = {}
        self._offsets: dict[str, int] = {}
        self._triggers: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}

    # ------------------------------------------------------------------ opening
    def _open_readers(self) -> list:
        from rosbags.rosbag1 import Reader as Reader1
        from rosbags.rosbag1 import ReaderError as ReaderError1
        from rosbags.rosbag2 import Reader as Reader2
        from rosbags.rosbag2 import ReaderError as ReaderError2

        p = self.path
        try:
            if p.is_file() and p.suffix == ".bag":
                readers = [Reader1(p)]
            elif p.is_dir():
                try:
                    readers = [Reader2(p)]
                    readers[0].open()
                    return readers
                except ReaderError2 as exc:
                    # metadata.yaml that rosbags refuses (e.g. an empty storage_identifier written by
                    # some recorders): open the storage files themselves
                    files = sorted([*p.glob("*.mcap"), *p.glob("*.db3")])
                    if not files:
                        raise DataError(p, f"ROS2 bag folder: {exc}") from None
                    readers = [Reader2(f) for f in files]
            else:
                readers = [Reader2(p)]
            for r in readers:
                r.open()
            return readers
        except (ReaderError1, ReaderError2) as exc:
            raise DataError(p, f"cannot read the bag ({exc}); it may be truncated or corrupt") from None
        except DataError:
            raise
        except Exception as exc:  # sqlite/mcap/lz4 errors of damaged files surface as many types
            raise DataError(p, f"cannot read the bag ({type(exc).__name__}: {exc}); it may be truncated or corrupt") from None

    def _build_typestore(self):
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        ts = get_typestore(Stores.EMPTY)
        for c in self.connections:
            if c.msgtype in ts.fielddefs or c.msgdef.format == MessageDefinitionFormat.NONE:
                continue
            try:
                if c.msgdef.format == MessageDefinitionFormat.MSG:
                    typs = get_types_from_msg(c.msgdef.data, c.msgtype)
                else:
                    typs = {}
                    sep = "=" * 80 + "\n"
                    parts = c.msgdef.data.split(sep)[1:] if c.msgdef.data.startswith(f"{sep}IDL: ") else [c.msgdef.data]
                    for part in parts:
                        typs.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
                ts.register(typs)
            except Exception:  # unparsable embedded definition: fall back to the stock/known ones
                continue
        missing = {c.msgtype for c in self.connections} - ts.fielddefs.keys()
        if missing:
            stock = get_typestore(Stores.ROS1_NOETIC if not self.is2 else Stores.LATEST)
            extra = {k: v for k, v in stock.fielddefs.items() if k not in ts.fielddefs}
            for name, text in EVENT_MSG_DEFINITIONS.items():
                if name not in ts.fielddefs:
                    extra.update(get_types_from_msg(text, name))
            try:
                ts.register(extra)
            except Exception as exc:
                raise DataError(self.path, f"cannot build message types for {sorted(missing)}: {exc}") from None
        return ts

    def _pick(self, topic: str | None, types: set[str], what: str) -> str | None:
        if topic is not None:
            if self.topic_types.get(topic) not in types:
                raise DataError(self.path, f"{what} topic {topic!r} has type {self.topic_types.get(topic)!r}, "
                                f"expected one of {sorted(types)}")
            return topic
        found = sorted(t for t, ty in self.topic_types.items() if ty in types)
        return found[0] if found else None

    def _messages(self, topic: str) -> Iterator[tuple[int, str, bytes]]:
        """(bag time ns, msgtype, raw bytes) of ``topic`` in time order."""
        gens = []
        for r in self._readers:
            conns = [c for c in r.connections if c.topic == topic]
            if conns:
                gens.append(((t, c.msgtype, raw) for c, t, raw in r.messages(connections=conns)))
        try:
            yield from heapq.merge(*gens, key=lambda m: m[0]) if len(gens) > 1 else (gens[0] if gens else ())
        except DataError:
            raise
        except Exception as exc:
            raise DataError(self.path, f"topic {topic!r}: cannot read messages ({type(exc).__name__}: {exc}); "
                            "the bag may be truncated or corrupt") from None

    def _deserialize(self, raw: bytes, msgtype: str, topic: str):
        try:
            if self.is2:
                return self.typestore.deserialize_cdr(raw, msgtype)
            return self.typestore.deserialize_ros1(raw, msgtype)
        except Exception as exc:
            raise DataError(self.path, f"topic {topic!r}: cannot deserialize a {msgtype} message ({exc})") from None

    # ------------------------------------------------------------------ events
    def cameras(self) -> list[str]:
        return [f"cam{i}" for i in range(len(self.event_topics))]

    def topic_of(self, cam: str) -> str:
        """The event topic of camera ``cam``."""
        cams = self.cameras()
        if cam not in cams:
            raise DataError(self.path, f"camera {cam!r} does not exist (cameras: {cams}, topics {self.event_topics})")
        return self.event_topics[cams.index(cam)]

    def sensor_size(self, cam: str) -> tuple[int, int]:
        if cam not in self._sizes:
            topic = self.topic_of(cam)
            for _, msgtype, raw in self._messages(topic):
                msg = self._deserialize(raw, msgtype, topic) if msgtype in _PACKET_TYPES else None
                if msg is None:
                    fast = _dvs_from_raw(raw, self.is2)
                    w, h = (fast[4], fast[5]) if fast is not None else (lambda m: (m.width, m.height))(
                        self._deserialize(raw, msgtype, topic))
                else:
                    w, h = msg.width, msg.height
                if w and h:
                    self._sizes[cam] = (int(w), int(h))
                    break
            else:
                info = self._camera_info(cam)
                if info is None:
                    raise DataError(self.path, f"topic {topic!r}: no message gives a width/height and there is no CameraInfo")
                self._sizes[cam] = (int(info.width), int(info.height))
        return self._sizes[cam]

    def _decode_message(self, raw: bytes, msgtype: str, topic: str, state: _TopicDecoder) -> tuple[DecodedEvents, int, bool]:
        """One message -> (decoded events, header stamp ns, sensor-time-is-epoch)."""
        if msgtype in _DVS_TYPES:
            fast = _dvs_from_raw(raw, self.is2)
            if fast is not None:
                t, x, y, p, _, _ = fast
                return DecodedEvents(t, x, y, p), int(t[0]) if len(t) else 0, True
            msg = self._deserialize(raw, msgtype, topic)
            ev = msg.events
            t = np.array([_stamp_ns(e.ts) for e in ev], np.int64)
            return (DecodedEvents(t, np.array([e.x for e in ev], np.uint16), np.array([e.y for e in ev], np.uint16),
                                  np.array([e.polarity for e in ev], np.int8)), _stamp_ns(msg.header.stamp), True)
        msg = self._deserialize(raw, msgtype, topic)
        enc = str(msg.encoding)
        if msg.is_bigendian:
            raise DataError(self.path, f"topic {topic!r}: big-endian event packets are not supported (is_bigendian=true)")
        if state.decoder is None or state.encoding != enc:
            state.encoding = enc
            try:
                if enc in ("evt3", "evt2"):
                    state.decoder = make_decoder(enc, msg.width or None, msg.height or None)
                elif enc == "libcaer":
                    state.decoder = LibcaerDecoder(msg.width or None, msg.height or None)
                elif enc == "libcaer_cmp":
                    state.decoder = LibcaerCmpDecoder(msg.width or None, msg.height or None)
                elif enc == "mono":
                    state.decoder = "mono"
                else:
                    raise CodecError(f"unsupported encoding {enc!r} (expected evt3, libcaer, libcaer_cmp or mono)")
            except CodecError as exc:
                raise DataError(self.path, f"topic {topic!r}: {exc}") from None
        try:
            if enc in ("evt3", "evt2"):
                d = state.decoder.decode(msg.events)
                d.t = d.t * 1000  # µs -> ns
                d.trig_t = d.trig_t * 1000
            elif enc == "mono":
                d = decode_mono_packet(msg.events, msg.time_base)
            else:
                d = state.decoder.decode_packet(msg.events, msg.time_base)
        except CodecError as exc:
            raise DataError(self.path, f"topic {topic!r}, packet seq {msg.seq}: {exc}") from None
        return d, _stamp_ns(msg.header.stamp), enc in _EPOCH_ENCODINGS

    def iter_decoded(self, cam: str) -> Iterator[tuple[DecodedEvents, int]]:
        """Per message: (events and triggers with *sensor* times in ns, header stamp ns).

        For ``evt3`` this is the sensor's µs clock times 1000, exactly what ``event_camera_codecs``
        reports; for ``dvs_msgs`` it is the events' own ROS times.
        """
        topic = self.topic_of(cam)
        state = _TopicDecoder()
        for _, msgtype, raw in self._messages(topic):
            d, stamp, _ = self._decode_message(raw, msgtype, topic, state)
            yield d, stamp

    def _iter_ros_time(self, cam: str) -> Iterator[DecodedEvents]:
        """Decoded messages with times in ns on the clock chosen by ``time_reference``."""
        topic = self.topic_of(cam)
        state = _TopicDecoder()
        offset = self._offsets.get(cam)
        for _, msgtype, raw in self._messages(topic):
            d, stamp, epoch = self._decode_message(raw, msgtype, topic, state)
            if msgtype in _DVS_TYPES or epoch or self.time_reference == "sensor":
                yield d
                continue
            if offset is None:
                if not len(d):
                    continue  # the offset comes from the first packet with events
                offset = stamp - int(d.t[0])
                self._offsets[cam] = offset
            d.t = d.t + offset
            d.trig_t = d.trig_t + offset
            yield d

    def iter_events(self, cam: str, chunk_events: int = 1 << 20) -> Iterator[EventArray]:
        """Stream the CD events of ``cam`` (int64 µs) in chunks of about ``chunk_events``."""
        trig: list[DecodedEvents] = []
        yield from regroup_events(self._iter_ros_time(cam), chunk_events, trig, divisor=1000)  # ns -> µs
        self._store_triggers(cam, trig)

    def _store_triggers(self, cam: str, parts: list[DecodedEvents]) -> None:
        d = DecodedEvents.concatenate(parts)
        self._triggers[cam] = (d.trig_t // 1000, d.trig_edge) if len(d.trig_t) else None

    def triggers(self, cam: str) -> tuple[np.ndarray, np.ndarray] | None:
        """External triggers ``(t µs int64, edge int8 1 = rising)`` of ``cam``, or None."""
        if cam not in self._triggers:
            self._store_triggers(cam, [d for d in self._iter_ros_time(cam) if len(d.trig_t)])
        return self._triggers[cam]

    # ------------------------------------------------------------------ other streams
    def imu(self) -> ImuSamples | None:
        """IMU samples by header stamp: gyro rad/s, acc m/s² (as ``sensor_msgs/Imu`` defines)."""
        if self.imu_topic is None:
            return None
        t, gyro, acc = [], [], []
        for bag_t, msgtype, raw in self._messages(self.imu_topic):
            m = self._deserialize(raw, msgtype, self.imu_topic)
            stamp = _stamp_ns(m.header.stamp) or bag_t
            t.append(stamp // 1000)
            w, a = m.angular_velocity, m.linear_acceleration
            gyro.append((w.x, w.y, w.z))
            acc.append((a.x, a.y, a.z))
        return ImuSamples(np.array(t, np.int64), np.array(gyro).reshape(-1, 3), np.array(acc).reshape(-1, 3))

    def gt(self) -> PoseSamples | None:
        """Ground-truth poses ``tx ty tz qx qy qz qw`` (m) by header stamp."""
        if self.gt_topic is None:
            return None
        t, pose = [], []
        for bag_t, msgtype, raw in self._messages(self.gt_topic):
            m = self._deserialize(raw, msgtype, self.gt_topic)
            p = m.pose.pose if msgtype == "nav_msgs/msg/Odometry" else m.pose
            stamp = _stamp_ns(m.header.stamp) or bag_t
            t.append(stamp // 1000)
            pose.append((p.position.x, p.position.y, p.position.z,
                         p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w))
        return PoseSamples(np.array(t, np.int64), np.array(pose).reshape(-1, 7))

    def _camera_info(self, cam: str):
        """The first CameraInfo of the topic sharing ``cam``'s namespace (or the only one)."""
        infos = sorted(t for t, ty in self.topic_types.items() if ty in CAMINFO_TYPES)
        if not infos:
            return None
        ns = self.topic_of(cam).rsplit("/", 1)[0]
        match = [t for t in infos if t.rsplit("/", 1)[0] == ns]
        if not match and len(infos) == 1 and len(self.event_topics) == 1:
            match = infos
        if not match:
            return None
        for _, msgtype, raw in self._messages(match[0]):
            return self._deserialize(raw, msgtype, match[0])
        return None

    def calibration(self) -> RigCalibration | None:
        """Intrinsics from CameraInfo for every camera, or None if any camera lacks one."""
        cams = {}
        for cam in self.cameras():
            info = self._camera_info(cam)
            if info is None:
                return None
            K = np.asarray(info.k, float).reshape(3, 3)
            D = [float(v) for v in info.d]
            model = str(info.distortion_model)
            if model == "equidistant":
                dist, coeffs = "equidistant", D[:4]
            elif not any(D):
                dist, coeffs = "none", []
            else:
                dist, coeffs = "radtan", D[:5]
            R = np.asarray(info.r, float).reshape(3, 3)
            P = np.asarray(info.p, float).reshape(3, 4)
            cams[cam] = CameraCalibration(
                int(info.width), int(info.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], dist, coeffs,
                R_rect=R if R.any() else None, P_rect=P if P.any() else None)
        return RigCalibration(cams)

    def close(self) -> None:
        for r in self._readers:
            try:
                r.close()
            except Exception:
                pass
        self._readers = []


def _probe(path: Path) -> bool:
    if path.is_file():
        return path.suffix.lower() in (".bag", ".mcap", ".db3")
    return path.is_dir() and (path / "metadata.yaml").is_file()


register_format("rosbag", _probe, RosbagRecording)
