"""The hardware simulator: an H2 HAL board and MACCEPA boards on any python-can bus.

``Simulator`` drives the board models on absolute deadlines (no drift: each period is scheduled
from the first, not from when the last one finished) and can inject faults for tests: go silent,
send malformed frames, flood the bus. ``SimulatorNode`` runs it under the node runtime with a
Zenoh queryable for faults; ``exolink sim`` runs it bare on a chosen bus.

On SocketCAN the H2's cyclic frames go out on the kernel's timer (``KernelStream``: the
broadcast manager, as the real board's hardware timer sends them) and each cycle only updates
their contents, which a send may carry up to one cycle late (the kernel's and Python's phases
are not locked). On a slow CPU Python-timed frames
stray far from their 10 ms period and trip the watchdog's silence limit (measured:
docs/performance.md): a late Python costs stale contents, not a gap in the stream.
"""

from __future__ import annotations

import ctypes
import threading
import time
from dataclasses import dataclass
from typing import Annotated, Any, cast

import can
import msgspec
from exolink.nodes.simulator.boards import H2Board, MaccepaBoard

from exolink import roles
from exolink.canbus import FrameReader, open_reader
from exolink.messaging import Refused
from exolink.node import Node
from exolink.protocol import h2, maccepa
from exolink.wire import management
from exolink.wire.replies import FaultInjected

FAULTS = ("none", "silent", "malformed", "flood")
PREPARE_S = 0.002  # the models step and the frames are built this long before they are due
SPIN_S = 0.0003  # the last stretch before a deadline is spun, not slept (as the pattern player)
PR_SET_TIMERSLACK = 29  # linux/prctl.h


class SimParams(msgspec.Struct, forbid_unknown_fields=True, frozen=True):
    h2: bool = True
    maccepa_boards: list[Annotated[int, msgspec.Meta(ge=0, le=9)]] = []
    maccepa_rate_hz: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 100.0
    max_speed_dps: Annotated[float, msgspec.Meta(gt=0, le=1000)] = 120.0
    tau_s: Annotated[float, msgspec.Meta(gt=0, le=10)] = 0.15
    battery_start: Annotated[int, msgspec.Meta(ge=0, le=255)] = 225
    battery_drain_per_min: Annotated[float, msgspec.Meta(ge=0)] = 1.0
    seed: int = 0
    # SocketCAN: the H2's frames on the kernel's timer (KernelStream); False: sent by Python
    kernel_timer: bool = True
    # With the kernel's timer only: the models step, their frames' contents change and commands
    # are read every this many periods (the kernel still sends every period). A slow CPU
    # (TCG in `make bench-board`) cannot step them every 10 ms, and its timers then come late:
    # gaps in the H2 stream that the appliance takes for silence. 1: as the boards do.
    update_cycles: Annotated[int, msgspec.Meta(ge=1, le=10)] = 1


@dataclass
class SimStats:
    periods: int = 0
    overruns: int = 0
    frames_sent: int = 0
    send_errors: int = 0
    commands: int = 0


class KernelStream:
    """Cyclic frames sent by the kernel's broadcast manager (python-can's SocketCAN periodic
    tasks, one per id, started in the order of the first cycle's frames and each on an exact
    period, so that order holds). ``update`` replaces the contents the next sends carry; a frame
    of each id is sent every period whether or not Python kept up."""

    def __init__(self, bus: can.BusABC, period_s: float) -> None:
        self._bus, self._period = bus, period_s
        self._tasks: dict[int, Any] = {}
        self._heads: dict[int, bytes] = {}  # id -> its task's TX_SETUP update header
        from can.interfaces.socketcan import socketcan  # SocketCAN's: only a kernel-timed bus

        self._sc = socketcan

    @property
    def running(self) -> bool:
        return bool(self._tasks)

    def update(self, frames: list[can.Message]) -> None:
        """New contents for each id's task: one TX_SETUP update written to its BCM socket, as
        python-can's ``modify_data`` writes it, without re-checking the task's messages on
        every call (11 us of its 14 on x86, for six frames every 10 ms)."""
        sc = self._sc
        for m in frames:
            fid = m.arbitration_id
            task = self._tasks.get(fid)
            if task is None:
                # socketcan's CyclicSendTask: its task id and flags head each update
                task = self._tasks[fid] = cast(Any, self._bus.send_periodic(m, self._period))
                self._heads[fid] = sc.build_bcm_update_header(task.task_id, task.flags, 1)
            else:
                sc.send_bcm(task.bcm_socket, self._heads[fid] + sc.build_can_frame(m))

    def stop(self) -> None:
        tasks, self._tasks, self._heads = self._tasks, {}, {}
        for task in tasks.values():
            task.stop()


def kernel_timed(bus: can.BusABC) -> bool:
    """Whether ``bus`` sends periodic frames from the kernel (SocketCAN's broadcast manager);
    python-can's other buses would run them on a Python thread."""
    return type(bus).__name__ == "SocketcanBus"


class Simulator:
    """``reader``: receive commands through it (a batch per wake-up, as the appliance's
    readers do) instead of python-can's ``recv``, a select and a checked ``can.Message`` per
    frame: with the pattern running the H2 alone gets 400 commands a second."""

    def __init__(
        self, bus: can.BusABC, params: SimParams, reader: FrameReader | None = None
    ) -> None:
        self.bus = bus
        self.params = params
        self.reader = reader
        self.h2 = (
            H2Board(
                params.max_speed_dps,
                params.tau_s,
                float(params.battery_start),
                params.battery_drain_per_min,
                params.seed,
            )
            if params.h2
            else None
        )
        self.boards = {b: MaccepaBoard(b) for b in params.maccepa_boards}
        kernel = params.kernel_timer and kernel_timed(bus)
        self.stream = KernelStream(bus, h2.PERIOD_S) if kernel else None
        # The boards' state frames on the kernel's timer too: a MACCEPA board sends them from
        # its own timer, like the H2
        self.mc_stream = (
            KernelStream(bus, 1.0 / params.maccepa_rate_hz) if kernel and self.boards else None
        )
        self.stats = SimStats()
        self._lock = threading.Lock()
        self._fault = "none"
        self._fault_until = 0.0

    @staticmethod
    def command_ids(params: SimParams) -> list[int]:
        ids = list(h2.COMMAND_IDS) if params.h2 else []
        return ids + maccepa.command_ids(params.maccepa_boards)

    def inject(self, fault: str, duration_s: float = 1.0) -> None:
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r} (valid: {', '.join(FAULTS)})")
        if not 0 < duration_s <= 3600:
            raise ValueError(f"fault duration {duration_s} s is outside (0, 3600]")
        with self._lock:
            self._fault = fault
            self._fault_until = time.monotonic() + duration_s

    def fault(self) -> str:
        with self._lock:
            if self._fault != "none" and time.monotonic() >= self._fault_until:
                self._fault = "none"
            return self._fault

    def handle(self, msg: can.Message) -> None:
        self.stats.commands += 1
        if self.h2 is not None and msg.arbitration_id in h2.COMMAND_IDS:
            self.h2.handle(msg)
            return
        f = maccepa.decode(msg)
        if not isinstance(f, maccepa.Unknown) and f.board in self.boards:
            self.boards[f.board].handle(msg)

    def _send(self, msgs: list[can.Message]) -> None:
        for m in msgs:
            try:
                self.bus.send(m)
                self.stats.frames_sent += 1
            except can.CanError:
                self.stats.send_errors += 1

    def _emit(self, msgs: list[can.Message], stream: KernelStream | None = None) -> None:
        """Send a cycle's frames with the fault in force; ``stream``: the kernel sends them (a
        silent fault stops it, malformed frames go out before its next cycle)."""
        fault = self.fault()
        if fault == "silent":
            if stream is not None:
                stream.stop()
            return
        if fault == "malformed":
            bad = [
                can.Message(
                    arbitration_id=m.arbitration_id, data=bytes(m.data[:3]), is_extended_id=False
                )
                for m in msgs
            ]
            bad.append(can.Message(arbitration_id=0x3FF, data=b"\xde\xad", is_extended_id=False))
            if stream is None:
                msgs = bad + msgs
            else:
                self._send(bad)  # the kernel keeps sending the well-formed ones
        if stream is None:
            self._send(msgs)
        else:
            stream.update(msgs)
            self.stats.frames_sent += len(msgs)  # one of each per period, from the kernel

    def _receive(self, timeout: float, frames_wake: bool = True) -> list[Any]:
        if self.reader is not None:
            return self.reader.read(timeout, frames_wake=frames_wake)
        msg = self.bus.recv(timeout=timeout)
        return [] if msg is None else [msg]

    def _flood(self, until: float) -> None:
        junk = can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False)
        while time.monotonic() < until and self.fault() == "flood":
            self._send([junk])

    def run(self, stop: threading.Event, beat: Any = None) -> None:
        """Frames go out on the deadline, as a board's hardware timer sends them: the models
        step and the frames are built ``PREPARE_S`` ahead, the wait until ``SPIN_S`` before the
        deadline is a sleep and the rest a spin, so neither the models' work nor a command
        handled meanwhile nor a late timer wake-up moves the frame. (Stepping and sending in
        one go at a slept-for deadline put 0.23 ms of p99 jitter on the H2's own frames on x86,
        which the controller manager, paced by them, passed on to every set-point.)

        When the kernel sends every cyclic frame (SocketCAN), Python only updates their
        contents: it steps and updates at the deadline in one wake-up and never spins (on a slow
        CPU the spin and the second wake-up take CPU the kernel's timers need)."""
        kernel = self.stream is not None  # then the boards' frames are kernel-timed too
        prepare_s, spin_s = (0.0, 0.0) if kernel else (PREPARE_S, SPIN_S)
        every = self.params.update_cycles if kernel else 1
        h2_period = h2.PERIOD_S * every
        mc_period = every / self.params.maccepa_rate_hz
        start = time.monotonic()
        next_h2, next_mc = start + h2_period, start + mc_period
        last = start
        ready: tuple[list[can.Message], list[can.Message]] | None = None  # (H2, boards)
        _precise_timers()
        while not stop.is_set():
            if beat is not None:
                beat()
            deadline = min(next_h2, next_mc) if self.boards else next_h2
            now = time.monotonic()
            if ready is None and now >= deadline - prepare_s:
                dt, last = now - last, now
                if self.h2 is not None:
                    self.h2.step(dt)
                for b in self.boards.values():
                    b.step(dt)
                h2_frames = (
                    self.h2.frames()
                    if self.h2 is not None and self.h2.streaming and now >= next_h2 - prepare_s
                    else []
                )
                mc_frames = (
                    [f for b in self.boards.values() for f in b.frames()]
                    if self.boards and now >= next_mc - prepare_s
                    else []
                )
                ready = h2_frames, mc_frames
                continue
            if now < deadline - spin_s:
                wake = deadline - (spin_s if ready is not None else prepare_s)
                for msg in self._receive(max(0.0, wake - now), frames_wake=every == 1):
                    self.handle(msg)
                continue
            while time.monotonic() < deadline:
                pass
            h2_frames, mc_frames = ready or ([], [])
            ready = None
            now = time.monotonic()
            if now >= next_h2:
                self.stats.periods += 1
                if h2_frames:  # not streaming (or built for a later deadline): nothing
                    self._emit(h2_frames, self.stream)
                elif self.stream is not None and self.h2 is not None and not self.h2.streaming:
                    self.stream.stop()  # the H2 was told to stop its stream (id 85)
                next_h2 += h2_period
                if now - next_h2 > 5 * h2_period:  # fell far behind (machine stalled): resync
                    self.stats.overruns += 1
                    next_h2 = now + h2_period
            if self.boards and now >= next_mc:
                if mc_frames:
                    self._emit(mc_frames, self.mc_stream)
                next_mc += mc_period
                if now - next_mc > 5 * mc_period:
                    next_mc = now + mc_period
            if self.fault() == "flood":
                self._flood(deadline + h2_period)


def _precise_timers() -> None:
    """This thread's timer slack to 1 ns (Linux' default 50 us is added to every sleep)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(1), 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the default slack only
        pass


class SimulatorNode(Node):
    """The simulator as a supervised node (``exolink up --sim`` runs it)."""

    Params = SimParams
    stall_s = 1.0

    def configure(self) -> None:
        self.reader = self.own(open_reader(self.ctx.config.can, Simulator.command_ids(self.params)))
        self.sim = Simulator(self.reader.bus, self.params, self.reader)
        self.own(self.ctx.messaging.serve(("sim", "fault"), self._on_fault, roles.ADMIN))

    def _on_fault(self, req: dict[str, Any]) -> FaultInjected:
        ask = management.convert(req, management.Fault, "fault")
        try:
            self.sim.inject(ask.fault, ask.duration_s)
        except (TypeError, ValueError) as exc:
            raise Refused(str(exc)) from None
        self.log.warning("fault_injected", fault=ask.fault, duration_s=ask.duration_s)
        return FaultInjected(ask.fault)

    def run(self, stop: threading.Event) -> None:
        self.sim.run(stop, self.beat)
