"""H2 reader [thesis: H2ros]: CAN ids 110/120/130 -> ``joint_states`` and ``foot_switches``; with
``maccepa_boards``, those boards' status frames -> ``maccepa/b<N>/state`` from the same read
(exolink.hardware.maccepa), so one process reads the bus.

``foot_switches`` goes out when the switches or the battery count change, stamped with that
frame's kernel time (no transition is lost or moved), and at least every
``foot_switches_refresh_s`` for late joiners: on the board a Zenoh sample costs ~1 ms of the one
core (benchmarks/board/units.py), and 100 copies a second of an unchanged state were a fifth of
the appliance's samples. ``foot_switches_refresh_s: 0`` publishes every cycle.

On SocketCAN the kernel compares the foot-switch frames (a broadcast-manager receive op,
``exolink.canbus.bcm.CyclicWatch``, every bit in its mask): only a change, the first frame
after a silence, or a silence of ``FEET_SILENCE_S`` reaches this process, not 100 frames a
second (a third of the reader's frames, each ~200 us of the board proxy's CPU to receive and
~130 us to handle). Then ``frames["130"]`` counts the changes the kernel reported,
``missing["130"]`` the silences, and a refresh is stamped when it is made: the kernel would
have told of any change or silence before it. Not with ``foot_switches_refresh_s: 0`` or a
reader woken by id 130 (``wake_on_id``), nor on the simulated bus: there every frame is read.

Every message carries the CAN frame's kernel receive time, never the time Python got to it.
A 10 ms stream makes gaps measurable: a period longer than 1.5x nominal counts the frames it
lost. Malformed frames are counted and skipped. Counters go out on ``diagnostics`` every second.

The hot path of the whole appliance (300 frames/s on one Cortex-A8 core): frames are read in
batches straight from the socket (``canbus.FrameReader``) and published from CDR templates
(``exolink.wire.cdr``), so this process never loads rosbags or numpy.
"""

from __future__ import annotations

import math
import operator
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Annotated, Any, Literal

import msgspec

from exolink import messaging
from exolink.canbus import Cadence, Frame, open_reader
from exolink.canbus.filters import Drop
from exolink.config import ConfigError, node_params
from exolink.hardware import maccepa as maccepa_state
from exolink.loops import Frames, each
from exolink.node import Node
from exolink.phaseclock import PhaseClock
from exolink.protocol import h2
from exolink.wire import cdr

JOINT_STATE = "sensor_msgs/msg/JointState"
FOOT_SWITCHES = "exolink_msgs/msg/FootSwitches"
DIAGNOSTICS = messaging.DIAGNOSTICS_TYPE
_DEG = math.pi / 180.0
_LOW = tuple(h2.RANGES[j][0] for j in h2.JOINTS)  # each joint's mechanical range
_HIGH = tuple(h2.RANGES[j][1] for j in h2.JOINTS)
# <= in C for the range check; operator.le, not int.__le__, whose NotImplemented for a float
# (a scaled angle) is truthy and would pass every frame
_LE: Callable[[float, float], bool] = operator.le
# No foot-switch frame for this long: a silence (the kernel's watch); five H2 periods, so one
# late frame on a busy bus is none
FEET_SILENCE_S = 0.05


class ReaderParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    reduction: Annotated[int, msgspec.Meta(ge=1, le=100)] = 1  # publish 1 of N samples
    start_stream: bool = True  # send the start frame (id 85) on start
    restart_stream_after_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 1.0  # 0 = never
    torque_nm_per_count: Annotated[float, msgspec.Meta(gt=0, le=100)] = 1.0
    battery_volts_per_count: Annotated[float, msgspec.Meta(gt=0, le=10)] = 0.1
    diagnostics_period_s: Annotated[float, msgspec.Meta(gt=0, le=60)] = 1.0
    # The id that ends each 10 ms cycle (the protocol sends 110, 120, 130): only its arrival
    # wakes the reader, which then takes the cycle's other frames with it: one wake-up per
    # cycle instead of three. 0: wake for every frame (firmware with another order).
    wake_on_id: Literal[0, 110, 120, 130] = h2.FOOT_SWITCHES
    # Frames read later than this after they arrived are skipped and counted (rx_stale), not
    # published as news: a reader that fell behind catches up. 0: publish every frame.
    stale_after_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 0.5
    # Wake once per this many H2 cycles and publish their samples back to back (canbus.Cadence:
    # on the board a wake-up and a Zenoh hop cost more than a sample). Subscribers get every
    # sample, up to N-1 cycles later; the watchdog and controller manager read the bus itself.
    # At most 25: a quarter second, what a live plot still follows.
    cycles_per_read: Annotated[int, msgspec.Meta(ge=1, le=25)] = 1
    # Foot switches + battery: on change, and at least this often (s); 0: every cycle.
    foot_switches_refresh_s: Annotated[float, msgspec.Meta(ge=0, le=60)] = 1.0
    # MACCEPA boards whose state this reader publishes too (maccepa/b<N>/state, as the MACCEPA
    # bridge does: exolink.hardware.maccepa), from the same socket and read: the bus in one
    # process, one wake-up and one beat per read on the board's one core instead of two
    # (docs/performance.md). Not with the bridge reading the same boards (checked at start).
    maccepa_boards: list[Annotated[int, msgspec.Meta(ge=0, le=9)]] = []


@dataclass
class ReaderStats:
    frames: dict[int, int] = field(default_factory=lambda: dict.fromkeys(h2.DATA_IDS, 0))
    missing: dict[int, int] = field(default_factory=lambda: dict.fromkeys(h2.DATA_IDS, 0))
    malformed: int = 0
    unknown: int = 0
    published_joint_states: int = 0
    published_foot_switches: int = 0
    foot_switch_changes: int = 0  # published because the switches or the battery count changed
    feet_on_change: bool = False  # id 130 watched by the kernel: only changes reach the reader
    without_torque: int = 0
    stream_restarts: int = 0
    socket_dropped: int | None = 0  # kernel drops from a full receive buffer (None: not known)
    out_of_range: int = 0  # angle frames with a joint outside its mechanical range (a fault)
    # The socket's losses and the reader's backlog (canbus.FrameReader.counters): dropped,
    # frames, late, lag_max_ms, batch_max, batches_full, rcvbuf.
    receive: dict[str, int | float | None] = field(default_factory=dict)


def _count(value: float | None) -> int | None:
    """A counter from FrameReader.counters() as the count it is (None: not known)."""
    return None if value is None else int(value)


class GapCounter:
    """Counts frames lost in a periodic stream from the receive timestamps alone."""

    def __init__(self, period_s: float) -> None:
        self.period = period_s
        self.last: dict[int, float] = {}

    def missed(self, fid: int, ts: float) -> int:
        prev = self.last.get(fid)
        self.last[fid] = ts
        if prev is None:
            return 0
        gap = ts - prev
        return max(0, round(gap / self.period) - 1) if gap > 1.5 * self.period else 0


class H2Reader(Node):
    Params = ReaderParams

    def configure(self) -> None:
        m = self.ctx.messaging
        wake = self.params.wake_on_id
        self.cadence = Cadence(h2.PERIOD_S, self.params.cycles_per_read)
        bundled = self.params.cycles_per_read > 1  # a read's samples: one bundle per topic
        self.out = messaging.Outbox()  # a read's samples go out together, after its frames
        boards = self._boards()
        self.pub_boards = {
            b: self.own(
                m.publisher(maccepa_state.topic(b), maccepa_state.STATE, raw=True, bundled=bundled)
            )
            for b in boards
        }
        self.boards = maccepa_state.BoardStates(
            boards, lambda b, payload, ns: self.out.add(self.pub_boards[b], payload, ns)
        )
        self.feet_watch = self._watch_feet()
        ids = [i for i in h2.DATA_IDS if not (self.feet_watch and i == h2.FOOT_SWITCHES)]
        self.reader = self.own(
            open_reader(
                self.ctx.config.can,
                [*ids, *sorted(self.boards.ids)],
                every_s=self.cadence.every_s,
                wake_on=[wake] if wake else None,
                stale_s=self.params.stale_after_s,
                # the H2's own frames on a board's ids (joint control on board 0's 70)
                drop=[Drop(i, n) for i, n in self.boards.drops()],
                # a wake's frames in one read: 3 a cycle from the H2, 3 from each board
                batch=self.cadence.batch(len(ids) + len(self.boards.ids)),
            )
        )
        self.bus = self.reader.bus
        # Read in batches, joint_states reaches the recorder as one bundle per read
        self.pub_js = self.own(m.publisher("joint_states", JOINT_STATE, raw=True, bundled=bundled))
        self.pub_fs = self.own(m.publisher("foot_switches", FOOT_SWITCHES, raw=True))
        self.pub_diag = self.own(
            m.publisher(f"nodes/{self.name}/diagnostics", DIAGNOSTICS, raw=True)
        )
        self.stats = ReaderStats(feet_on_change=self.feet_watch is not None)
        self.gaps = GapCounter(h2.PERIOD_S)
        # where the loop's CPU goes, by phase, and each phase's longest wall (stats: loop_cpu)
        self.clock = PhaseClock(walls=True)
        self.own(m.serve(("nodes", self.name, "stats"), lambda _req: self._stats()))
        self.js = cdr.JointStateCdr(h2.JOINTS)
        self._reported_out_of_range = 0
        self._reported_dropped: float = 0  # frames: the stale count may come as a float
        self.fs = cdr.FootSwitchesCdr()
        self._last_feet: tuple[h2.FootSwitches, float] | None = None  # the last published, when
        self._feet_silent = False  # the kernel's watch said the frames stopped (and not resumed)
        self._pending: tuple[float, h2.JointAngles] | None = None
        self._cycle = 0
        self._next_diag = time.monotonic() + self.params.diagnostics_period_s
        self._last_restart = time.monotonic()
        if self.params.start_stream:
            self.bus.send(h2.encode_stream(True))

    def _watch_feet(self) -> Any:
        """The kernel's watch of the foot-switch frames (module docstring), or None: every frame
        is read."""
        can_cfg, p = self.ctx.config.can, self.params
        if can_cfg.interface != "socketcan" or not p.foot_switches_refresh_s:
            return None
        if p.wake_on_id == h2.FOOT_SWITCHES:
            return None
        from exolink.canbus.bcm import CyclicWatch  # Linux only (its socket constants)

        used = h2.dlc_of(h2.FOOT_SWITCHES) or 8  # the frame's bytes, not the padding after them
        mask = (b"\xff" * used).ljust(8, b"\0")
        return self.own(CyclicWatch(can_cfg.channel, h2.FOOT_SWITCHES, FEET_SILENCE_S, mask))

    def _feet_changes(self) -> None:
        """What the kernel's watch reported since the last wake: each change handled as its
        frame (on its kernel time), a silence counted; then the refresh of an unchanged state
        that is still streaming, stamped now."""
        watch = self.feet_watch
        assert watch is not None  # a phase of the loop only with the watch
        st, now = self.stats, time.time()  # before the poll: a change read after has a later stamp
        for at, frame in watch.poll():
            if frame is None:  # no frame for FEET_SILENCE_S: no state to refresh until one
                st.missing[h2.FOOT_SWITCHES] += 1
                self._feet_silent = True
                continue
            self._feet_silent = False
            decoded = h2.decode(frame)
            if not isinstance(decoded, h2.FootSwitches):  # a length change: reported too
                st.malformed += 1
                continue
            st.frames[h2.FOOT_SWITCHES] += 1
            self._feet(at, decoded)
        last, refresh = self._last_feet, self.params.foot_switches_refresh_s
        if last is not None and not self._feet_silent and not 0 <= now - last[1] < refresh:
            self._publish_feet(now, last[0])

    def _publish_joints(self, ts: float, angles: h2.JointAngles, torques: Any) -> None:
        ns = int(ts * 1e9)
        k = self.params.torque_nm_per_count
        payload = self.js.encode(
            ns,
            [a * _DEG for a in angles],
            None if torques is None else [t * k for t in torques],
        )
        self.out.add(self.pub_js, payload, ns)
        self.stats.published_joint_states += 1

    def _boards(self) -> list[int]:
        """The MACCEPA boards this reader publishes; refused when an enabled bridge reads one
        of them too (two publishers of one board's state)."""
        boards = list(self.params.maccepa_boards)
        for n in self.ctx.config.nodes:
            if n.plugin == "maccepa_bridge" and n.enabled and boards:
                theirs = set(getattr(node_params(self.ctx.config, n.name), "boards", []))
                if both := sorted(theirs & set(boards)):
                    raise ConfigError(
                        f"{self.name} params: maccepa_boards {both} are also read by the "
                        f"enabled {n.name}: one of them publishes a board's state"
                    )
        return boards

    def handle(self, msg: Frame | Any) -> None:
        """One frame; never raises for bad input (counted instead)."""
        if msg.arbitration_id in self.boards.ids:
            self.boards.handle(msg)
            return
        frame = h2.decode(msg)
        st = self.stats
        if isinstance(frame, h2.Unknown):
            if frame.reason == "bad length":
                st.malformed += 1
            else:
                st.unknown += 1
            return
        ts, fid = msg.timestamp, msg.arbitration_id
        st.frames[fid] += 1
        st.missing[fid] += self.gaps.missed(fid, ts)
        if isinstance(frame, h2.JointAngles):
            # in C, not a generator per joint: 100 frames a second on the board's one core
            if not (all(map(_LE, _LOW, frame)) and all(map(_LE, frame, _HIGH))):
                st.out_of_range += 1  # still published: the diagnostics say it is a fault
            if self._pending is not None:  # the torque frame of the last cycle never came
                st.without_torque += 1
                if self._selected():
                    self._publish_joints(*self._pending, None)
            self._cycle += 1
            self._pending = (ts, frame)
        elif isinstance(frame, h2.JointTorques):
            if self._pending is not None:
                if self._selected():
                    self._publish_joints(*self._pending, frame)
                self._pending = None
        elif isinstance(frame, h2.FootSwitches):
            self._feet(ts, frame)

    def _selected(self) -> bool:
        """The reduction factor: cycles 1, 1+N, 1+2N... are published."""
        return (self._cycle - 1) % self.params.reduction == 0

    def _feet(self, ts: float, f: h2.FootSwitches) -> None:
        """Every change (on the frame's own time), else a refresh once the period is up."""
        refresh, last = self.params.foot_switches_refresh_s, self._last_feet
        if not refresh:
            if self._selected():
                self._publish_feet(ts, f)
            return
        if last is not None and last[0] == f and 0 <= ts - last[1] < refresh:
            return
        if last is not None and last[0] != f:
            self.stats.foot_switch_changes += 1
        self._publish_feet(ts, f)

    def _publish_feet(self, ts: float, f: h2.FootSwitches) -> None:
        self._last_feet = (f, ts)
        ns = int(ts * 1e9)
        switches = (bool(f.r_heel), bool(f.r_toe), bool(f.l_heel), bool(f.l_toe))
        volts = f.battery * self.params.battery_volts_per_count
        self.out.add(self.pub_fs, self.fs.encode(ns, switches, f.battery, volts), ns)
        self.stats.published_foot_switches += 1

    def _stats(self) -> dict[str, Any]:
        st = self.stats
        st.receive = self.reader.counters()
        st.socket_dropped = _count(st.receive["dropped"])
        return {
            "node": self.name,  # a wildcard query's replies say whose they are
            **asdict(st),
            "joint_states_out": self.pub_js.counters(),
            "maccepa": {
                "boards": self.boards.boards,
                "published": self.boards.published,
                "malformed": self.boards.malformed,
            },
            "loop_cpu": self.clock.counters(),
        }

    def _diagnostics(self) -> None:
        st = self.stats
        rx = st.receive = self.reader.counters()
        dropped = st.socket_dropped = _count(rx["dropped"])
        values = {
            **{f"frames_{i}": n for i, n in st.frames.items()},
            **{f"missing_{i}": n for i, n in st.missing.items()},
            "malformed": st.malformed,
            "unknown": st.unknown,
            "without_torque": st.without_torque,
            "published_joint_states": st.published_joint_states,
            "stream_restarts": st.stream_restarts,
            "out_of_range": st.out_of_range,
            # rx_*: receive losses and backlog; the supervisor shows them in `exolink status`
            **{f"rx_{k}": v for k, v in rx.items()},
        }
        silent = self._silent_for() > 0.1 + self.cadence.every_s  # read every_s apart
        fault = st.out_of_range > self._reported_out_of_range
        self._reported_out_of_range = st.out_of_range
        # Dropped by a full queue, or skipped as stale by a reader that fell behind.
        gone = (dropped or 0) + int(rx["stale"] or 0)
        lost = gone - self._reported_dropped
        self._reported_dropped = gone
        now = time.time_ns()
        level = "error" if silent or fault else "warn" if lost > 0 else "ok"
        if silent:
            message = "no H2 data"
        elif fault:
            message = "joint angle outside its mechanical range"
        elif lost > 0:
            message = (
                f"{lost} frames lost in the receive queue ({dropped} dropped, "
                f"{rx['stale']} skipped as stale in all)"
            )
        else:
            message = "streaming"
        payload = cdr.diagnostics(
            now, f"{self.name}/h2_stream", messaging.LEVELS[level], message, "h2", values
        )
        self.pub_diag.put(payload, now)

    def _silent_for(self) -> float:
        last = max(self.gaps.last.values(), default=None)
        return float("inf") if last is None else time.time() - last

    def loop(self) -> Frames:
        """A wake's frames (and the kernel's foot-switch reports, when it watches them), then
        their samples out together, then the periodic work."""
        after = [("publish", self.out.flush), ("rest", self._periodic)]
        if self.feet_watch is not None:  # no phase (and no clock mark) a wake without it
            after.insert(0, ("feet", self._feet_changes))
        return Frames(self.reader, each(self.handle), self.cadence, after=after, clock=self.clock)

    def _periodic(self) -> None:
        """Diagnostics every period; with ``start_stream``, the stream asked for again while the
        H2 stays silent (it may have been powered after this node started)."""
        now = time.monotonic()
        if now >= self._next_diag:
            self._next_diag += self.params.diagnostics_period_s
            self._diagnostics()
        restart = self.params.restart_stream_after_s
        if (
            self.params.start_stream
            and restart
            and self._silent_for() > restart
            and now - self._last_restart > restart
        ):
            self._last_restart = now
            self.stats.stream_restarts += 1
            self.bus.send(h2.encode_stream(True))
