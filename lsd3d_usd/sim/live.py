"""`sim run --live` / `sim serve --live`: the drive streamed to Foxglove as it happens, over
the foxglove-sdk WebSocket server (loopback by default). The messages are `sim run --mcap`'s
(sim.record, datasets.mcap): the same topics and schemas, sent to the server's channels
instead of a file. Without --live nothing listens.

Open it in the Foxglove app: "Open connection" -> Foxglove WebSocket -> ws://127.0.0.1:8765.
"""
from __future__ import annotations

import sys
from pathlib import Path

from lsd3d_usd.datasets.mcap import McapWriter
from lsd3d_usd.errors import InputError


class _ChannelSink:
    """The three calls McapWriter makes on an mcap Writer, onto foxglove channels. Channels
    are kept by topic across episodes (one advertisement per topic for the session)."""

    def __init__(self, context):
        import foxglove
        self.fox, self.ctx = foxglove, context
        self.schemas: dict[int, object] = {}
        self.by_topic: dict[str, object] = {}
        self.ids: list = []

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        self.schemas[len(self.schemas) + 1] = self.fox.Schema(name=name, encoding=encoding,
                                                              data=data)
        return len(self.schemas)

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, **_) -> int:
        if topic not in self.by_topic:
            self.by_topic[topic] = self.fox.Channel(topic, schema=self.schemas.get(schema_id),
                                                    message_encoding=message_encoding,
                                                    context=self.ctx)
        self.ids.append(self.by_topic[topic])
        return len(self.ids) - 1

    def add_message(self, channel_id: int, log_time: int, data: bytes, **_) -> None:
        self.ids[channel_id].log(data, log_time=log_time)

    def finish(self) -> None:
        pass


class _LiveWriter(McapWriter):
    """McapWriter's messages into a _ChannelSink: no file, no folder."""

    def __init__(self, sink: _ChannelSink):
        super().__init__(Path("."), None, stem="live", boxes_with_cameras=False)   # no file
        self.sink = sink

    def begin_log(self, info) -> None:
        import foxglove.messages
        self.fm, self.info, self.name_ = foxglove.messages, info, "live"
        self.w = self.sink
        self.schemas, self.channels, self.counts = {}, {}, {}
        self.n_messages = 0
        self._static(info)

    def end_log(self) -> dict:
        return {"file": None, "messages": dict(sorted(self.counts.items()))}


class LiveView:
    """A Foxglove WebSocket server on (host, port) for the episodes of one env."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, allow_remote: bool = False,
                 log=None):
        import foxglove

        from lsd3d_usd.sim.service import is_loopback
        if not is_loopback(host):
            if not allow_remote:
                raise InputError(f"--live-host {host}: not a loopback address; add "
                                 "--allow-remote to stream to other machines")
            (log or (lambda m: print(m, file=sys.stderr)))(
                f"live view: WARNING: listening on {host} (no authentication)")
        self.ctx = foxglove.Context()      # our channels reach this server only
        try:
            self.server = foxglove.start_server(name="lsd3d-usd sim", host=host, port=port,
                                                context=self.ctx)
        except Exception as e:
            raise InputError(f"--live-port {port}: cannot listen on {host}:{port} ({e})") from None
        self.port = self.server.port
        self.sink = _ChannelSink(self.ctx)

    def episode(self, env, index: int):
        """An episode's recorder: ``.write(obs, info)`` after reset and each step."""
        from lsd3d_usd.sim.record import EpisodeMcap
        return EpisodeMcap(None, env, index, writer=_LiveWriter(self.sink))

    def close(self) -> None:
        self.server.stop()
