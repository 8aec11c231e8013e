"""The MCAP writer: one recording per log, ROOT/<log>.mcap, with Foxglove's protobuf schemas
(foxglove-sdk's message classes encode the messages; the `mcap` package writes the file), so a
drive opens in Foxglove like a ROS 2 recording:

  /tf_static               foxglove.FrameTransform  ego -> each sensor, once at the start
  /tf                      foxglove.FrameTransform  world -> ego at every tick
  /<camera>/image          foxglove.CompressedImage JPEG, frame_id <camera> (OpenCV axes)
  /<camera>/camera_info    foxglove.CameraCalibration (K, P; no distortion), per image
  /LIDAR_TOP               foxglove.PointCloud      x, y, z, intensity (float32), ring
                                                    (uint16), class_id (uint8), in the LiDAR
                                                    frame at the sweep's start
  /markers/annotations     foxglove.SceneUpdate     a cube per actor in the world frame (its
                                                    3D box), metadata class, kind, prim, speed

Times are the log's microsecond timestamps (datasets.tokens) in nanoseconds. The file is
written as ROOT/.<log>.mcap.partial and renamed when the log is done.

Other recorders (sim.record) reuse the writer: ``stem`` names the file instead of the log,
``boxes_with_cameras=False`` writes the boxes at every sample (not only when the cameras
fire), and ``log_json`` adds a schema-less JSON channel (MCAP's "json" message encoding, its
schema optional; Foxglove plots its fields).

Resuming: a checkpoint (after every keyframe) ends the chunk in progress and flushes the file
to disk, so the recording up to the keyframe is whole chunks in the file, and notes how many
messages that is. ``restore`` reads the unfinished file's chunks back with the `mcap` stream
reader and replays their records (schemas, channels, messages, in order; the chunk ends where
they ended) into a new file, which then goes on from the checkpoint: the same writer calls as
an uninterrupted run, so the same bytes. What followed the checkpoint (rendered again) and the
file's torn tail are dropped.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from lsd3d_usd.datasets.tokens import timestamp_us
from lsd3d_usd.datasets.writers import encode_image, quat_wxyz
from lsd3d_usd.views import labels as L

POINT_STRIDE = 20


def _fm():
    import foxglove.messages as fm  # heavy (native): only when writing MCAP
    return fm


def _time(fm, ns: int):
    return fm.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _pose(fm, M):
    w, x, y, z = quat_wxyz(M)
    t = np.asarray(M)[:3, 3]
    return (fm.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
            fm.Quaternion(x=x, y=y, z=z, w=w))


class McapWriter:
    name = "mcap"
    files = ("*.mcap", ".*.mcap.partial", ".*.mcap.partial.new")
    record_shape = {"file": str, "messages": {str: int}}    # datasets.build.record_problem

    def __init__(self, root: Path, options, *, stem: str | None = None,
                 boxes_with_cameras: bool = True):
        self.root = Path(root)
        self.stem = stem
        self.boxes_with_cameras = boxes_with_cameras

    def begin_log(self, info) -> None:
        self._start(info)
        for stale in self.root.glob(f".{self.name_}.mcap.*"):   # of a killed run
            stale.unlink()
        self._open(self.tmp)
        self._static(info)

    def _static(self, info) -> None:
        """The rig's fixed transforms, once at the start of a log."""
        t0 = self._ns(0.0)
        for c in info.cameras:
            self._log("/tf_static", self._tf("ego", c.name, info.ego_from_camera[c.name], t0), t0)
        if info.lidar is not None:
            self._log("/tf_static", self._tf("ego", "LIDAR_TOP", info.ego_from_lidar, t0), t0)

    def _start(self, info) -> None:
        self.fm, self.info = _fm(), info
        self.name_ = self.stem or f"lsd3d-{info.plan.index:04d}-{info.plan.scene_name}"
        self.root.mkdir(parents=True, exist_ok=True)
        self.tmp = self.root / f".{self.name_}.mcap.partial"

    def _open(self, path: Path) -> None:
        from mcap.writer import Writer
        self.f = open(path, "wb")  # noqa: SIM115 -- open for the log, closed in end_log
        self.w = Writer(self.f)
        self.w.start(profile="", library="lsd3d-usd")
        self.schemas, self.channels, self.counts = {}, {}, {}
        self.n_messages = 0

    # ---------------------------------------------------------------- resuming
    def checkpoint(self) -> dict:
        """End the chunk, flush the file to disk; the messages so far."""
        self.w.flush()
        os.fsync(self.f.fileno())
        return {"messages": self.n_messages}

    def restore(self, info, deltas: list) -> None:
        from lsd3d_usd.errors import InputError
        self._start(info)
        want = deltas[-1].get("messages") if deltas else None
        if type(want) is not int or want < 0:
            raise InputError(f"{self.tmp}: the checkpoint's message count is {want!r}, not a "
                             "count; give --overwrite")
        final = self.root / f"{self.name_}.mcap"
        src = self.tmp if self.tmp.is_file() else final     # killed after the rename
        if src.is_symlink():                # its target's bytes would be echoed and copied
            raise InputError(f"{src}: a symbolic link; give --overwrite")
        new = self.root / f".{self.name_}.mcap.partial.new"
        self._open(new)
        try:
            self._copy_back(src, want)
        except Exception as e:  # noqa: BLE001 -- a torn or tampered recording, whatever breaks
            self.f.close()
            new.unlink(missing_ok=True)     # a refused resume leaves no half copy behind
            if isinstance(e, InputError):
                raise
            reason = str(e).splitlines()[0][:80] if str(e).strip() else type(e).__name__
            raise InputError(f"{src}: cannot read the unfinished recording back ({reason}); "
                             "give --overwrite") from None
        os.fsync(self.f.fileno())
        os.replace(new, self.tmp)

    def _copy_back(self, src: Path, want: int) -> None:
        """Copy ``src``'s chunks into the open writer up to ``want`` messages (the last
        checkpoint); what follows may be torn by the kill and is dropped."""
        from mcap.records import Channel, Chunk, Message, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk

        from lsd3d_usd.errors import InputError
        topic_of = {}
        with open(src, "rb") as f:
            for rec in StreamReader(f, emit_chunks=True, validate_crcs=True).records:
                if not isinstance(rec, Chunk):
                    continue
                for r in breakup_chunk(rec, validate_crc=True):
                    if isinstance(r, Schema):
                        self.schemas[r.name] = self.w.register_schema(r.name, r.encoding, r.data)
                    elif isinstance(r, Channel):
                        self.channels[r.topic] = self.w.register_channel(
                            r.topic, r.message_encoding, r.schema_id, dict(r.metadata))
                        topic_of[r.id] = r.topic
                    elif isinstance(r, Message):
                        self.w.add_message(r.channel_id, log_time=r.log_time, data=r.data,
                                           publish_time=r.publish_time, sequence=r.sequence)
                        t = topic_of[r.channel_id]
                        self.counts[t] = self.counts.get(t, 0) + 1
                        self.n_messages += 1
                self.w.flush()              # the chunk ends where it ended
                if self.n_messages >= want:
                    break                   # before the next record: it may be torn
        if self.n_messages != want:
            raise InputError(f"{src}: holds {self.n_messages} messages up to its checkpoint, "
                             f"not {want}; give --overwrite")

    def _ns(self, seconds: float) -> int:
        return timestamp_us(self.info.plan.index, seconds) * 1000

    def _channel(self, topic: str, msg) -> int:
        if topic not in self.channels:
            schema = type(msg).get_schema()
            if schema.name not in self.schemas:
                self.schemas[schema.name] = self.w.register_schema(
                    schema.name, schema.encoding, bytes(schema.data))
            self.channels[topic] = self.w.register_channel(topic, "protobuf",
                                                           self.schemas[schema.name])
        return self.channels[topic]

    def _log(self, topic: str, msg, ns: int) -> None:
        self._add(topic, self._channel(topic, msg), msg.encode(), ns)

    def _add(self, topic: str, ch: int, data: bytes, ns: int) -> None:
        self.w.add_message(ch, log_time=ns, data=data, publish_time=ns,
                           sequence=self.counts.get(topic, 0))
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.n_messages += 1

    def log_json(self, topic: str, obj, seconds: float) -> None:
        """One JSON message (``obj`` must be JSON-ready: no NaN) on a schema-less channel."""
        import json
        if topic not in self.channels:
            self.channels[topic] = self.w.register_channel(topic, "json", 0)
        self._add(topic, self.channels[topic],
                  json.dumps(obj, allow_nan=False, sort_keys=True).encode(), self._ns(seconds))

    def _tf(self, parent, child, M, ns):
        fm = self.fm
        t, q = _pose(fm, M)
        return fm.FrameTransform(timestamp=_time(fm, ns), parent_frame_id=parent,
                                 child_frame_id=child, translation=t, rotation=q)

    def write(self, s) -> None:
        fm = self.fm
        ns = self._ns(s.time)
        stamp = _time(fm, ns)
        self._log("/tf", self._tf("world", "ego", s.world_from_ego, ns), ns)
        for shot in s.cameras:
            h, w = shot.image.shape[:2]
            self._log(f"/{shot.channel}/image", fm.CompressedImage(
                timestamp=stamp, frame_id=shot.channel, data=encode_image(shot.image, "jpg"),
                format="jpeg"), ns)
            P = np.hstack([shot.K, np.zeros((3, 1))])
            self._log(f"/{shot.channel}/camera_info", fm.CameraCalibration(
                timestamp=stamp, frame_id=shot.channel, width=int(w), height=int(h),
                distortion_model="plumb_bob", D=[0.0] * 5, K=shot.K.ravel().tolist(),
                R=np.eye(3).ravel().tolist(), P=P.ravel().tolist()), ns)
        if s.lidar is not None:
            self._log("/LIDAR_TOP", self._cloud(s.lidar.sweep, stamp), ns)
        if (s.cameras or not self.boxes_with_cameras) and s.boxes is not None:
            self._log("/markers/annotations", self._boxes(s.boxes, stamp), ns)

    def _cloud(self, sw, stamp):
        fm = self.fm
        n = len(sw.range)
        rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4"),
                                 ("ring", "<u2"), ("cls", "u1"), ("pad", "u1")])
        rec["x"], rec["y"], rec["z"] = sw.xyz[:, 0], sw.xyz[:, 1], sw.xyz[:, 2]
        rec["i"], rec["ring"], rec["cls"] = sw.intensity, sw.ring, sw.class_id
        T = fm.PackedElementFieldNumericType
        fields = [fm.PackedElementField(name=nm, offset=off, type=tp) for nm, off, tp in (
            ("x", 0, T.Float32), ("y", 4, T.Float32), ("z", 8, T.Float32),
            ("intensity", 12, T.Float32), ("ring", 16, T.Uint16), ("class_id", 18, T.Uint8))]
        origin = fm.Pose(position=fm.Vector3(x=0.0, y=0.0, z=0.0),
                         orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
        return fm.PointCloud(timestamp=stamp, frame_id="LIDAR_TOP", pose=origin,
                             point_stride=POINT_STRIDE, fields=fields, data=rec.tobytes())

    def _boxes(self, boxes, stamp):
        fm = self.fm
        pal = L.palette()
        ents = []
        for b in boxes:
            from scipy.spatial.transform import Rotation
            x, y, z, w = Rotation.from_quat(b.rotation_xyzw).as_quat()
            c = pal[b.class_id if 0 <= b.class_id < 256 else L.UNLABELLED] / 255.0
            cx, cy, cz = b.center
            sx, sy, sz = b.size
            cube = fm.CubePrimitive(
                pose=fm.Pose(position=fm.Vector3(x=cx, y=cy, z=cz),
                             orientation=fm.Quaternion(x=x, y=y, z=z, w=w)),
                size=fm.Vector3(x=sx, y=sy, z=sz),
                color=fm.Color(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=0.5))
            meta = [fm.KeyValuePair(key=k, value=str(v)) for k, v in (
                ("class", b.label), ("kind", b.kind), ("prim", b.prim),
                ("speed", f"{b.speed():.3f}"))]
            ents.append(fm.SceneEntity(timestamp=stamp, frame_id="world", id=b.prim,
                                       lifetime=fm.Duration(0, 0), frame_locked=False,
                                       metadata=meta, cubes=[cube]))
        return fm.SceneUpdate(entities=ents)

    def end_log(self) -> dict:
        self.w.finish()
        self.f.close()
        final = self.root / f"{self.name_}.mcap"
        os.replace(self.tmp, final)
        return {"file": final.name, "messages": dict(sorted(self.counts.items()))}

    def finish(self, records: list) -> dict:
        return {r["file"]: sum(r["messages"].values()) for r in records}
