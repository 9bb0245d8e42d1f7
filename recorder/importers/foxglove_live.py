"""``record live``: a robot's Foxglove WebSocket stream recorded into an MCAP recording, crash-safe, gaps and all.

The client (:mod:`.foxglove_ws`) subscribes to the channels :mod:`.live_plan` maps onto logical topics; each
message is written through `Recorder` as it is received, with ``log_time`` = the publisher's stamp of it (its
header's, else the server's log time of it: the sensor time, which replay takes as its clock, as for every other
source) and ``publish_time`` = when it was received here (the wall clock), so both times are kept.

- Crash-safe: the file is ``FILE.partial`` until a clean end (``--duration-s`` over, a stop request, Ctrl-C),
  and every second the chunk in progress is written out, so ``kill -9`` loses at most the last second;
  ``slamreplay recover FILE.partial --out FILE`` salvages the rest.
- A dropped connection is retried with backoff (0.25 s doubling to 2 s) until it is back, the recording stops,
  or ``give_up_s`` passes; each gap is written as an MCAP metadata record ``slamreplay.gap`` (``start_ns`` and
  ``end_ns``: the log times of the messages around it; ``wall_start_ns``, ``wall_end_ns``, ``duration_s``: when
  the connection was lost and back; ``reason``, ``attempts``) and said.
- A channel silent for 5 of its periods (at least 3 s) while the connection lives is named once, and again
  when it resumes; at the end a ``slamreplay.live`` metadata record holds the counts per topic, the channels
  skipped and stopped, and why the recording ended.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

from slamreplay.recorder.errors import CodecError, RecorderError
from slamreplay.recorder.importers.foxglove_ws import (
    Advertise,
    ChannelInfo,
    ConnectError,
    ConnectionLostError,
    MessageData,
    Session,
    Status,
    Unadvertise,
    check_url,
    connect,
)
from slamreplay.recorder.importers.live_plan import (
    TF,
    ChannelPlan,
    Conversion,
    Converted,
    compile_patterns,
    plan_channels,
)
from slamreplay.recorder.importers.pole_config import PoleConfig
from slamreplay.recorder.messages import TOPIC_RANGE_BEARING
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.writer import Recorder, refuse_existing

IMPORTER = "live"
GAP_METADATA = "slamreplay.gap"
LIVE_METADATA = "slamreplay.live"
BACKOFF_S = (0.25, 0.5, 1.0, 2.0)  # then the last, until connected
STALL_MIN_S, STALL_PERIODS = 3.0, 5
SCAN_HOLD_S = 2.0  # scans wait this long for /tf_static (the laser's mounting) after subscribing
TICK_S = 1.0  # flush, status, stalls


@dataclass(frozen=True)
class LiveOptions:
    """What to record from where; see ``slamreplay record live --help``."""

    url: str
    out: Path
    topics: tuple[str, ...] = ()
    topic_map: Mapping[str, str] = field(default_factory=dict)
    duration_s: float | None = None
    sensor_model: SensorModel | None = None
    base_frame: str = "base_link"
    odom_frame: str = "odom"  # /tf: odometry is base_frame in it, when no channel gives odometry
    ground_truth_frame: str | None = None  # /tf: ground truth is base_frame in it (e.g. map)
    poles: PoleConfig = field(default_factory=PoleConfig)
    wait_s: float = 5.0  # for a channel to record, after connecting
    give_up_s: float | None = None  # reconnecting; None: until stopped
    open_timeout_s: float = 5.0


@dataclass
class TopicCount:
    """One recorded channel of the stream: messages received, written, refused (bad), payload bytes."""

    topic: str
    maps_to: str
    received: int = 0
    written: int = 0
    bad: int = 0
    bytes: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    rate_hz: float = 0.0  # over the last status interval
    stopped: bool = False
    received_before: int = field(default=0, repr=False)  # at the last status

    def period_s(self) -> float | None:
        if self.received < 3 or self.first_ns is None or self.last_ns is None:
            return None
        return (self.last_ns - self.first_ns) / 1e9 / (self.received - 1)


@dataclass(frozen=True)
class Gap:
    """A time without data: the connection was lost at ``wall_start_ns`` and back at ``wall_end_ns`` (0: not before
    the end), after the message at log time ``start_ns`` and before the one at ``end_ns`` (0: none came)."""

    wall_start_ns: int
    reason: str
    start_ns: int = 0
    wall_end_ns: int = 0
    end_ns: int = 0
    attempts: int = 0

    @property
    def duration_s(self) -> float:
        """Seconds without a connection (to the end of the recording when it did not come back)."""
        return ((self.wall_end_ns or time.time_ns()) - self.wall_start_ns) / 1e9

    def record(self, url: str) -> dict[str, str]:
        """The ``slamreplay.gap`` metadata record."""
        return {"start_ns": str(self.start_ns), "end_ns": str(self.end_ns), "wall_start_ns": str(self.wall_start_ns),
                "wall_end_ns": str(self.wall_end_ns), "duration_s": f"{self.duration_s:.3f}", "reason": self.reason,
                "attempts": str(self.attempts), "url": url}


@dataclass(frozen=True)
class LiveStatus:
    """A snapshot for progress: seconds recorded, connection, topics, totals, bytes of the file so far."""

    elapsed_s: float
    connected: bool
    topics: tuple[TopicCount, ...]
    messages: int
    bytes_on_disk: int
    gaps: int


@dataclass(frozen=True)
class LiveSummary:
    path: Path
    messages: int
    duration_s: float
    topics: tuple[TopicCount, ...]
    gaps: tuple[Gap, ...]
    skipped: tuple[ChannelPlan, ...]
    stopped: tuple[str, ...]
    end_reason: str
    bytes_on_disk: int


class LiveRecording:
    """One recording of a stream; :meth:`run` blocks until it ends. :meth:`stop` (any thread) ends it cleanly."""

    def __init__(self, options: LiveOptions, *, say: Callable[[str], None] = lambda line: None,
                 status: Callable[[LiveStatus], None] = lambda s: None) -> None:
        self.opts, self._say, self._status = options, say, status
        self._stop = threading.Event()
        self._selected = compile_patterns(options.topics)
        self._taken: dict[str, str] = {}
        self._plans: dict[int, ChannelPlan] = {}  # this session's channels by id
        self._subs: dict[int, int] = {}  # subscription id -> channel id
        self._counts: dict[str, TopicCount] = {}
        self._skipped: dict[str, ChannelPlan] = {}
        self._conv = Conversion(options.base_frame, options.poles, options.odom_frame, options.ground_truth_frame)
        self._rec: Recorder | None = None
        self._gaps: list[Gap] = []
        self._gap: Gap | None = None  # lost and not yet written: its end is the next message written
        self._last_log_ns = 0  # log time of the last message written
        self._said_bad: set[str] = set()
        self._start = self._last_tick = 0.0
        self._hold_until = 0.0
        self._connected = False
        self.end_reason = ""

    def stop(self) -> None:
        """End the recording cleanly at the next message or within 0.1 s."""
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def status(self) -> LiveStatus:
        elapsed = time.monotonic() - self._start if self._start else 0.0
        size = self._rec.partial.stat().st_size if self._rec is not None and self._rec.partial.exists() else 0
        topics = tuple(replace(c) for c in self._counts.values())
        return LiveStatus(elapsed, self._connected, topics, sum(c.written for c in topics), size, len(self._gaps))

    # -- the loop ---------------------------------------------------------------------------------------

    def run(self) -> LiveSummary:
        """Record until the duration is over or :meth:`stop`; RecorderError (one line) when the server cannot be
        reached at the start, or offers nothing to record."""
        o = self.opts
        check_url(o.url)
        refuse_existing(Path(o.out))
        try:
            while not self._over():
                try:
                    with connect(o.url, open_timeout_s=o.open_timeout_s) as session:
                        self._connected = True
                        if self._rec is None:
                            self._open(session)
                        else:
                            self._resume(session)
                        self._stream(session)
                except ConnectionLostError as err:
                    self._connected = False
                    self._gap = Gap(time.time_ns(), str(err), start_ns=self._last_log_ns)
                    self._say(f"connection lost: {err}; reconnecting to {o.url} ...")
                except ConnectError as err:
                    self._connected = False
                    if self._rec is None:
                        raise
                    if self._gap is None:  # lost while resuming
                        self._gap = Gap(time.time_ns(), str(err), start_ns=self._last_log_ns)
                    self._gap = replace(self._gap, attempts=self._gap.attempts + 1)
                    self._backoff(self._gap)
        except KeyboardInterrupt:
            self.end_reason = "interrupted (Ctrl-C)"
        except BaseException:
            if self._rec is not None:  # an error mid-way: what was written stays FILE.partial, to be recovered
                self._rec.close(keep_partial=True)
            raise
        finally:
            self._connected = False
        if self._rec is not None:
            self._finish()
        return self._summary()

    def _over(self) -> bool:
        if self._stop.is_set():
            self.end_reason = self.end_reason or "stopped"
            return True
        if self._start and self.opts.duration_s is not None and time.monotonic() - self._start >= self.opts.duration_s:
            self.end_reason = self.end_reason or f"--duration-s {self.opts.duration_s:g} reached"
            return True
        return False

    def _backoff(self, gap: Gap) -> None:
        if self.opts.give_up_s is not None and gap.duration_s > self.opts.give_up_s:
            self.end_reason = (f"the server was unreachable for {gap.duration_s:.0f} s (--give-up-s "
                               f"{self.opts.give_up_s:g})")
            self._stop.set()
            return
        self._stop.wait(BACKOFF_S[min(gap.attempts, len(BACKOFF_S)) - 1])

    def _await_channels(self, session: Session) -> list[ChannelPlan]:
        """Channels advertised within ``wait_s`` (and 0.2 s after the first advertise), planned."""
        deadline, settle = time.monotonic() + self.opts.wait_s, None
        plans: list[ChannelPlan] = []
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= deadline or (settle is not None and now >= settle and any(p.maps_to for p in plans)):
                break
            event = session.recv(min(0.1, deadline - now))
            if isinstance(event, Advertise):
                plans += plan_channels(event.channels, self._selected, self.opts.topic_map, self._taken,
                                       self.opts.ground_truth_frame)
                settle = settle or time.monotonic() + 0.2
            elif isinstance(event, Status) and event.level >= 2:
                self._say(f"server error: {event.message}")
        return plans

    def _open(self, session: Session) -> None:
        o = self.opts
        plans = self._await_channels(session)
        if self._stop.is_set():
            raise RecorderError("stopped before any channel was subscribed: nothing recorded")
        if not any(p.maps_to for p in plans):
            seen = ", ".join(f"{p.channel.topic} ({p.channel.encoding} {p.channel.schema_name})" for p in plans)
            if not plans:
                raise RecorderError(f"{o.url} advertised no channel within {o.wait_s:g} s: is anything publishing?")
            if not any(self._selected(p.channel.topic) for p in plans):
                raise RecorderError(f"no channel of {o.url} matches --topics {' '.join(o.topics)} (channels: {seen})")
            raise RecorderError(f"no channel of {o.url} can be recorded (channels: {seen}): "
                                + "; ".join(f"{p.channel.topic}: {p.note}" for p in plans))
        server = session.server
        model = o.sensor_model
        if model is None and any(p.maps_to == TOPIC_RANGE_BEARING and p.channel.encoding == "cdr" for p in plans):
            from slamreplay.recorder.importers.ros2bag import sensor_model

            model = SensorModel.from_mapping({**sensor_model(o.poles), "source": (
                "the pole extractor's noise floors (each scan states the sigma of its circle fits, never below them)")})
        self._rec = Recorder(Path(o.out), source={"importer": IMPORTER, "url": o.url, "server": server.name if server
                                                   else "", "subprotocol": session.subprotocol},
                             parameters={"topics": list(o.topics), "topic_map": {p.channel.topic: p.maps_to
                                                                               for p in plans if p.maps_to},
                                         "base_frame": o.base_frame, "odom_frame": o.odom_frame,
                                         "ground_truth_frame": o.ground_truth_frame,
                                         "pole_extractor": o.poles.as_dict()},
                             sensor_model=model)
        self._rec.open()
        self._start = self._last_tick = time.monotonic()
        self._say(f"recording {o.url} ({session.subprotocol}) into {self._rec.partial}")
        self._subscribe(session, plans, prefix="  ")

    def _subscribe(self, session: Session, plans: list[ChannelPlan], prefix: str | None) -> None:
        """Subscribe to the planned channels that map somewhere; say each (``prefix``: None, only failures)."""
        chosen = []
        for p in plans:
            c = p.channel
            if p.maps_to is not None:
                try:
                    self._conv.add(p)
                except CodecError as err:
                    p = ChannelPlan(c, None, str(err))
            if prefix is not None and (prefix == "  " or p.maps_to is not None):
                self._say(prefix + p.line())
            if p.maps_to is None:
                if self.opts.topics == () or self._selected(c.topic):
                    self._skipped[c.topic] = p
                continue
            self._plans[c.id] = p
            self._counts.setdefault(c.topic, TopicCount(c.topic, p.maps_to))
            chosen.append(c.id)
        self._subs.update(session.subscribe(chosen))
        if self._conv.hold_scans:
            self._hold_until = time.monotonic() + SCAN_HOLD_S

    def _resume(self, session: Session) -> None:
        self._plans.clear()
        self._subs.clear()
        advertised: list[ChannelInfo] = []
        deadline = time.monotonic() + self.opts.wait_s
        while time.monotonic() < deadline and not self._stop.is_set():
            event = session.recv(0.1)
            if isinstance(event, Advertise):
                advertised += event.channels
                if any(c.topic in self._counts for c in advertised):
                    break
        plans = plan_channels(advertised, self._selected, self.opts.topic_map, self._taken,
                              self.opts.ground_truth_frame)
        self._subscribe(session, plans, prefix=None)
        if self._gap is not None:
            self._gap = replace(self._gap, wall_end_ns=time.time_ns())
            self._say(f"reconnected after {self._gap.duration_s:.1f} s ({self._gap.attempts} failed attempts)")

    def _close_gap(self, end_ns: int) -> None:
        """Write the open gap, ended by the message at log time ``end_ns`` (0: by the end of the recording)."""
        assert self._rec is not None and self._gap is not None
        gap, self._gap = replace(self._gap, end_ns=end_ns), None
        self._gaps.append(gap)
        self._rec.add_metadata(GAP_METADATA, gap.record(self.opts.url))
        data = f"{(gap.end_ns - gap.start_ns) / 1e9:.1f} s of log time between messages" if end_ns and gap.start_ns \
            else "no message after it" if gap.start_ns else "no message before it"
        self._say(f"gap: {gap.duration_s:.1f} s without a connection ({gap.reason}); {data}; written to the "
                  f"recording as metadata {GAP_METADATA}")

    def _stream(self, session: Session) -> None:
        while not self._over():
            now = time.monotonic()
            if now - self._last_tick >= TICK_S:
                self._tick(now)
            event = session.recv(max(0.0, min(0.1, self._last_tick + TICK_S - now)))
            if isinstance(event, MessageData):
                self._message(event)
            elif isinstance(event, Advertise):
                known = {p.channel.kind for p in self._plans.values()}
                new = [c for c in event.channels if c.id not in self._plans and c.kind not in known]
                self._subscribe(session, plan_channels(new, self._selected, self.opts.topic_map, self._taken,
                                                       self.opts.ground_truth_frame),
                                prefix="new channel: ")
            elif isinstance(event, Unadvertise):
                for cid in event.channel_ids:
                    p = self._plans.pop(cid, None)
                    if p is not None:
                        self._say(f"channel {p.channel.topic} was unadvertised by the server: it stopped publishing")
                        self._counts[p.channel.topic].stopped = True
            elif isinstance(event, Status) and event.level >= 1:
                self._say(f"server {'error' if event.level >= 2 else 'warning'}: {event.message}")

    def _message(self, m: MessageData) -> None:
        cid = self._subs.get(m.subscription_id)
        plan = self._plans.get(cid) if cid is not None else None
        if plan is None:
            return  # a subscription of a channel unadvertised since
        count = self._counts[plan.channel.topic]
        count.received += 1
        count.bytes += len(m.payload)
        count.first_ns = count.first_ns or m.receive_ns
        count.last_ns = m.receive_ns
        if count.stopped:
            count.stopped = False
            self._say(f"channel {count.topic} resumed")
        try:
            out = self._conv(plan.channel.id, m.payload, m.log_time_ns)
        except RecorderError as err:  # a payload that does not decode: counted, said once per topic
            count.bad += 1
            if count.topic not in self._said_bad:
                self._said_bad.add(count.topic)
                self._say(f"{count.topic}: a message was skipped ({err}); further ones are counted")
            return
        self._write(out, m.receive_ns)
        count.written += len(out)

    def _write(self, out: list[Converted], receive_ns: int) -> None:
        """Messages at their own stamp (the log time, the replay clock), received at ``receive_ns``."""
        assert self._rec is not None
        for topic, msg, encoded in out:
            if self._gap is not None and self._gap.wall_end_ns:
                self._close_gap(msg.stamp_ns)
            self._rec.write(topic, msg, publish_time_ns=receive_ns, encoded=encoded)
            self._last_log_ns = msg.stamp_ns

    def _compose(self, final: bool) -> None:
        """Write the odometry and ground truth composed through /tf since the last tick; say once why a composed
        topic has none (after STALL_MIN_S of recording, when the tree has had time to fill, or at the end)."""
        if not self._conv.composed:
            return
        out, problems = self._conv.compose()
        self._write(out, time.time_ns())
        tf = self._counts.get(TF)
        if tf is not None:
            tf.written += len(out)
        if final or time.monotonic() - self._start >= STALL_MIN_S:
            for problem in problems:
                key = problem.split(":")[0]
                if key not in self._said_bad:
                    self._said_bad.add(key)
                    self._say(problem)

    def _tick(self, now: float) -> None:
        assert self._rec is not None
        if self._conv.held and self._conv.hold_scans and now >= self._hold_until:
            self._say(f"no /tf_static within {SCAN_HOLD_S:g} s: scans are taken as seen from {self.opts.base_frame}")
            self._conv.hold_scans = False
        if self._conv.held and not self._conv.hold_scans:
            self._write(self._conv.release(), time.time_ns())
        self._compose(final=False)
        self._rec.flush()
        dt, wall = now - self._last_tick, time.time_ns()
        for c in self._counts.values():
            c.rate_hz = (c.received - c.received_before) / dt if dt > 0 else 0.0
            c.received_before = c.received
            period = c.period_s()
            if self._connected and not c.stopped and period is not None and c.last_ns is not None:
                silent = (wall - c.last_ns) / 1e9
                if silent > max(STALL_MIN_S, STALL_PERIODS * period):
                    c.stopped = True
                    self._say(f"channel {c.topic} stopped: no message for {silent:.1f} s (it ran at "
                              f"{1 / period:.1f} Hz)")
        self._last_tick = now
        self._status(self.status())

    def _finish(self) -> None:
        rec = self._rec
        assert rec is not None
        self._write(self._conv.release(force=True), time.time_ns())
        self._compose(final=True)
        if self._gap is not None:
            self._close_gap(0)
        summary = {c.topic: {"maps_to": c.maps_to, "received": c.received, "written": c.written, "bad": c.bad}
                   for c in self._counts.values()}
        rec.add_metadata(LIVE_METADATA, {
            "url": self.opts.url, "end_reason": self.end_reason or "stopped", "topics": json.dumps(summary),
            "gaps": str(len(self._gaps)), "stopped": json.dumps(sorted(c.topic for c in self._counts.values()
                                                                         if c.stopped)),
            "skipped": json.dumps({t: p.note for t, p in sorted(self._skipped.items())})})
        self._final_size = rec.partial.stat().st_size
        rec.close()

    def _summary(self) -> LiveSummary:
        rec = self._rec
        path = rec.partial if rec is not None and rec.partial.exists() else Path(self.opts.out)
        counts = tuple(replace(c) for c in self._counts.values())
        return LiveSummary(path, sum(c.written for c in counts), time.monotonic() - self._start if self._start else 0.0,
                           counts, tuple(self._gaps), tuple(self._skipped.values()),
                           tuple(c.topic for c in counts if c.stopped), self.end_reason or "stopped",
                           getattr(self, "_final_size", 0))


def record_live(options: LiveOptions, *, say: Callable[[str], None] = lambda line: None,
                status: Callable[[LiveStatus], None] = lambda s: None,
                stop: threading.Event | None = None) -> LiveSummary:
    """Record the stream at ``options.url`` into ``options.out`` until the duration is over or ``stop`` is set."""
    live = LiveRecording(options, say=say, status=status)
    if stop is not None:
        live._stop = stop
    return live.run()

