"""The receive hot path: ``FrameReader`` reads the socket under a python-can bus itself, in
batches, and counts what python-can does not report: what the kernel dropped, how late frames
were read, how far behind the reader runs. Opening its buses is canbus.opening's; the batch
system calls are canbus.mmsg's."""

from __future__ import annotations

import bisect
import functools
import operator
import select
import socket
import time
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import structlog

from exolink.canbus import filters as canfilter
from exolink.canbus.frames import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_FRAME,
    CAN_RTR_FLAG,
    Frame,
    id_filters,
)
from exolink.canbus.mmsg import BATCH, MSG_SIZE, BatchReceiver
from exolink.canbus.sockets import (
    RCVBUF_BYTES,
    bus_socket,
    receive_none,
    size_receive_buffer,
    socket_drops,
)
from exolink.canbus.writer import FrameWriter
from exolink.config import CanConfig

if TYPE_CHECKING:
    import can

_CAN_FLAGS = CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG
LATE_S = 0.01  # a frame read later than this after it arrived is counted late (one H2 period)
_arrival = operator.itemgetter(0)  # a Frame's timestamp, in C: sort and bisect keys per frame


def next_read(due: float, now: float, every_s: float) -> float:
    """When a reader that reads every ``every_s`` looks next, its last read due at ``due`` and
    done at ``now``: on its cadence, so the time spent on a read's frames does not stretch the
    period (a 10-cycle reader on the board proxy read every ~12 cycles, too many for its
    batch); one that fell more than half a period behind (a busy core) starts afresh."""
    on_cadence = due + every_s
    return on_cadence if on_cadence >= now + every_s / 2 else now + every_s


class FrameReader:
    """Reads the socket under a python-can bus directly, in batches.

    python-can opens, configures and filters the bus (kernel filters on SocketCAN and on the
    simulated bus) and still sends; only receiving bypasses it: its ``recv`` builds a checked
    ``can.Message`` per frame behind a ``select`` per frame (~35 us per frame on an x86 core, the
    reader's largest cost). Here one ``select`` is followed by every frame already queued, each a
    ``recvmsg`` and one ``struct`` unpack.

    What was lost and how far behind the reader runs, none of which python-can reports:
    ``dropped`` is the kernel's count of frames this socket lost (a full receive buffer), read
    from the socket when asked: exact on SocketCAN and on the simulated bus, where the kernel
    filters never queue, so never count, other ids (on the sim bus, a reader of more ids than
    the kernel filter takes hears, and may drop, every id: ``filtered`` counts the others). ``late`` counts frames read more than
    ``late_s`` after they arrived, ``lag_max_s`` is the oldest a frame was when read,
    ``batches_full`` counts reads that stopped at the batch limit with frames still queued.

    ``quiet``: a second bus (same interface) whose frames are read only when this one wakes.
    A periodic source that sends several frames per cycle (the H2: 110, 120, 130 every 10 ms)
    costs one wake-up per cycle instead of one per frame when only the cycle's last id wakes the
    reader: on x86 and on the emulated board a wake-up (select, scheduler, the GIL) costs far
    more CPU than the frames it brings (docs/performance.md). Frames of both sockets come out in kernel-timestamp
    order; a cycle whose waking frame never comes is read when the caller's timeout ends.

    ``every_s`` bounds how often a busy reader wakes: after a read that found frames, the next
    waits until ``every_s`` after the last one was due (a fixed cadence: the time the caller
    spends on a read's frames does not stretch the period), so frames arriving meanwhile are
    read as one batch. A wake-up (select, context switch, the GIL) costs more than parsing the frames
    it brings, so a reader that does not need each frame at once (the timing monitor, which
    works from kernel timestamps) trades that latency for CPU. Never longer than the caller's
    timeout; 0 (default) wakes for each frame.

    ``drop``: content filters (``exolink.canbus.filters``), frames of its ids it never needs: the
    kernel's socket filter on SocketCAN, these rules in Python on the other buses (``filtered``).

    ``batch``: frames read per socket and read at most (``Cadence.batch``: what one wake of a
    batched reader brings; a read that stops short is followed at once by another, a whole
    iteration of its node's loop more).
    """

    def __init__(
        self,
        bus: can.BusABC,
        cfg: CanConfig,
        ids: Iterable[int] | None,
        late_s: float = LATE_S,
        rcvbuf: int | None = None,
        every_s: float = 0.0,
        quiet: can.BusABC | None = None,
        stale_s: float = 0.0,
        wake_ids: Iterable[int] = (),
        drop: Sequence[canfilter.Drop] = (),
        batch: int = BATCH,
    ) -> None:
        self.bus = bus
        self.wake_ids = frozenset(wake_ids)  # with ``quiet``: the ids ``bus`` reads
        self.stale_s = stale_s
        self.quiet_bus = quiet
        self.every_s = every_s
        self._next_read = 0.0
        late_s = max(late_s, every_s + LATE_S)  # waiting out every_s is not lateness
        self.ids = frozenset(ids) if ids is not None else None
        self.late_s = late_s
        self.malformed = 0
        self.filtered = 0  # frames of other ids that reached this process
        self.frames = 0
        self.batches = 0
        self.batch_max = 0
        self.batches_full = 0
        self.late = 0
        self.stale = 0  # frames read more than stale_s after arrival, skipped (counted here)
        self.lag_max_s = 0.0
        # How far behind the bus the last read was: the age of the newest frame it returned
        # when it left frames queued (0: it read all there was). A watchdog that is behind
        # cannot tell a silent H2 from its own backlog.
        self.behind_s = 0.0
        self.rcvbuf: int | None = None  # bytes the kernel grants this socket's queue
        # The last read left nothing queued that arrived before it (no batch limit hit; the
        # virtual bus reads one frame at a time, so only an empty read says so there). True
        # before the first read: nothing was left by one, so it waits for frames.
        self.complete = True
        # Read from the sockets but not returned yet: newer than where a socket that stopped
        # at its batch limit ended (see _in_step).
        self._held: list[Frame] = []
        # the in-process virtual bus has no socket: python-can's own receive path
        self._sock = bus_socket(bus)
        self._quiet = bus_socket(quiet) if quiet is not None else None
        # What the socket carries: SocketCAN's can_frame (_drain_socketcan), else the simulated
        # bus's datagrams (python-can's udp_multicast msgpack, _parse_udp).
        family = self._sock.family if self._sock is not None else None
        in_kernel = family == socket.AF_CAN
        if family == socket.AF_INET:
            self._parse = self._parse_udp
            import msgpack  # lazy: the udp_multicast bus only (its datagrams)

            self._unpackb = msgpack.unpackb
        # one recvmmsg per socket and read, into buffers made here (not on the hot path)
        size = CAN_FRAME.size if in_kernel else MSG_SIZE
        self._rx = {
            s: BatchReceiver(s, size, batch) for s in (self._sock, self._quiet) if s is not None
        }
        self._cfg = cfg
        # Content filters (canfilter): the kernel's on SocketCAN, else these rules in Python.
        if in_kernel and drop:
            for s in self._rx:
                canfilter.attach(s, drop)
        self._drops = canfilter.Predicate(() if in_kernel else drop)
        if self._sock is not None:
            want = rcvbuf or RCVBUF_BYTES[self._sock.family]
            self.rcvbuf = size_receive_buffer(self._sock, want)
            if self._quiet is not None:
                size_receive_buffer(self._quiet, want)
            if self.rcvbuf < 2 * want:
                structlog.get_logger().bind(node="canbus").warning(
                    "receive_buffer_capped",
                    wanted=2 * want,
                    granted=self.rcvbuf,
                    fix=f"sysctl -w net.core.rmem_max={want} (or run with CAP_NET_ADMIN)",
                )

    @property
    def dropped(self) -> int | None:
        """Frames the kernel dropped at this reader's sockets since they opened (None: no
        socket to ask)."""
        if self._sock is None:
            return None
        counts = [socket_drops(s) for s in (self._sock, self._quiet) if s is not None]
        return None if None in counts else sum(c for c in counts if c is not None)

    @functools.cached_property
    def writer(self) -> FrameWriter:
        """Sends batches through the socket that reads the ids that do not wake (the quiet
        one; the only one without): a socket never reads its own frames back (SocketCAN's
        CAN_RAW_RECV_OWN_MSGS is off), so a reader that also reads what it sends (the
        controller manager reads anyone's joint control, id 70, and sends its set-points
        there) does not decode its own frames. Made on first use (its buffers cost a few ms
        under TCG, and most readers never send a batch)."""
        return FrameWriter(self.quiet_bus or self.bus, self._cfg)

    def set_ids(self, ids: Iterable[int]) -> None:
        """Read ``ids`` from now on, without reopening: nothing queued is lost and the counters
        go on. The waking ids stay as opened; the others become the kernel filter of the quiet
        socket (of the one socket without one). On the sim bus the kernel keeps delivering the
        sources it joined at open, and ids no longer read are dropped here (``filtered``)."""
        new = frozenset(ids)
        if new == self.ids:
            return
        if self.quiet_bus is not None:
            rest = new - self.wake_ids
            if not self.wake_ids <= new or not rest:
                raise ValueError(
                    f"set_ids {sorted(new)} must keep the waking ids {sorted(self.wake_ids)} "
                    "and add others"
                )
            self.quiet_bus.set_filters(id_filters(rest))
        else:
            self.bus.set_filters(id_filters(new))
        self.ids = new

    @property
    def parkable(self) -> bool:
        """Its sockets are SocketCAN's, whose id filter can be emptied (``park``)."""
        return self._sock is not None and self._sock.family == socket.AF_CAN

    def park(self) -> None:
        """Nothing reaches this reader until ``unpark``, and nothing read before it is kept:
        an owner idle for a while parks it instead of closing it. Closing a socket that
        carries a content filter frees the BPF program in a kernel worker, which held the
        board proxy's CPU 0 for 90-190 ms without preemption (A69, B69: the controller
        manager's reader at each gait's stop, where the h2 reader missed its deadline), and
        opening one compiles the program again. Only on SocketCAN (``parkable``)."""
        if not self.parkable:
            raise ValueError("only a SocketCAN reader parks (an empty id filter)")
        for s, rx in self._rx.items():
            receive_none(s)
            rx.discard()  # what queued before: read nowhere
        self._held.clear()
        self.complete, self.behind_s, self._next_read = True, 0.0, 0.0

    def unpark(self) -> None:
        """Its id filters back as they were set (``set_ids`` after, for new ids)."""
        for bus in (self.bus, self.quiet_bus):
            if bus is not None:
                bus.set_filters(bus.filters)

    def close(self) -> None:
        """Shut down the buses this reader opened (the quiet one too)."""
        for bus in (self.quiet_bus, self.bus):
            if bus is not None:
                bus.shutdown()

    def __enter__(self) -> FrameReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def counters(self) -> dict[str, int | float | None]:
        """The receive-loss and backlog counters, for stats and diagnostics."""
        return {
            "dropped": self.dropped,
            "frames": self.frames,
            "late": self.late,
            "lag_max_ms": round(self.lag_max_s * 1e3, 2),
            "batches": self.batches,
            "batch_max": self.batch_max,
            "batches_full": self.batches_full,
            "filtered": self.filtered,
            "stale": self.stale,
            "rcvbuf": self.rcvbuf,
        }

    def read(
        self, timeout: float, wake_fds: Sequence[int] = (), frames_wake: bool = True
    ) -> list[Frame]:
        """Every frame queued now (up to a batch per socket), waiting up to ``timeout`` for the
        first one. ``wake_fds``: other descriptors that end the wait when readable (a
        state change); ``frames_wake=False``: no frame ends the wait, every socket is read when
        it ends (a reader that needs the frames only by a deadline). The in-process virtual bus
        ignores both and waits for a frame."""
        if self.every_s:
            wait = self._next_read - time.monotonic()
            if wait > 0:  # frames that come meanwhile are read together, below
                time.sleep(min(wait, timeout))
                timeout = max(0.0, timeout - wait)
        out = self._read(timeout, wake_fds, frames_wake)
        if out and self.every_s:  # a full batch left frames queued: read them at once
            now = time.monotonic()
            if not self.complete and self._sock is not None:
                self._next_read = now
            else:
                self._next_read = next_read(self._next_read, now, self.every_s)
        self.behind_s = 0.0
        if out:
            n = len(out)
            self.frames += n
            self.batches += 1
            if n > self.batch_max:
                self.batch_max = n
            now = time.time()
            if not self.complete and self._sock is not None:  # stopped at the batch limit
                self.batches_full += 1
                self.behind_s = now - out[-1].timestamp
            lag = now - out[0].timestamp  # the oldest of the batch (in arrival order)
            if lag > self.lag_max_s:
                self.lag_max_s = lag
            if lag > self.late_s:
                old = now - self.late_s
                self.late += sum(1 for f in out if f.timestamp < old)
            if self.stale_s and lag > self.stale_s:
                out = self._skip_stale(out, now - self.stale_s)
        return out

    def _skip_stale(self, out: list[Frame], cut: float) -> list[Frame]:
        """A reader that falls behind (a CPU saturated for a while) skips what is older than
        ``stale_s`` instead of publishing it as news; counted in ``stale``. Without it, a reader
        that falls behind never catches up (docs/performance.md)."""
        fresh = [f for f in out if f.timestamp >= cut]
        self.stale += len(out) - len(fresh)
        return fresh

    def _read(self, timeout: float, wake_fds: Sequence[int], frames_wake: bool) -> list[Frame]:
        """Every frame read, in arrival order."""
        if self._sock is None:
            msg = self.bus.recv(timeout)
            self.complete = msg is None
            if msg is None:
                return []
            frame = Frame(
                msg.timestamp,
                msg.arbitration_id,
                bytes(msg.data),
                msg.is_extended_id,
                msg.is_remote_frame,
                msg.is_error_frame,
            )
            if self._dropped(frame):
                self.filtered += 1
                return []
            return [frame]
        sock, quiet = self._sock, self._quiet
        behind = not self.complete  # the last read left frames queued or held: no waiting
        if behind:
            timeout = 0.0
        watch: list[Any] = [sock, *wake_fds] if frames_wake else list(wake_fds)
        if watch:
            woke = sock in select.select(watch, (), (), timeout)[0]
        else:
            if timeout > 0:
                time.sleep(timeout)
            woke = False
        waking, w_full = self._drain(sock) if woke or behind or not frames_wake else ([], False)
        if quiet is None:
            self.complete = not w_full
            return waking
        out, q_full = self._drain(quiet)
        return self._in_step(out, waking, q_full, w_full)

    def _in_step(
        self, quiet: list[Frame], waking: list[Frame], q_full: bool, w_full: bool
    ) -> list[Frame]:
        """Both sockets' frames in kernel-time order, up to where a socket that stopped at its
        batch limit ended: what the other one read past that waits for the next read.

        Behind by more than a batch, a read takes a batch of each socket: 64 cycles of the h2
        reader's waking 130 but only 32 of its quiet 110/120, so the quiet socket would fall
        further behind every read until its frames go stale and overflow, and no joint_states
        come out at all."""
        out = self._held + quiet + waking
        if sum(map(bool, (self._held, quiet, waking))) > 1:  # more than one source: merge
            out.sort(key=_arrival)
        cut = min(
            (b[-1].timestamp for b, full in ((quiet, q_full), (waking, w_full)) if full and b),
            default=None,
        )
        if cut is None:
            self._held = []
        else:
            i = bisect.bisect_right(out, cut, key=_arrival)
            out, self._held = out[:i], out[i:]
        self.complete = not (q_full or w_full or self._held)
        return out

    def _drain(self, sock: socket.socket) -> tuple[list[Frame], bool]:
        """Every frame queued on ``sock`` now, up to a batch (True: it stopped there, more may
        be queued); never blocks. Kernel receive times (SO_TIMESTAMPNS, set by python-can and
        exolink.canbus.simbus); a frame without one gets the time it was read."""
        rx = self._rx[sock]
        if rx.msg_size == CAN_FRAME.size:
            return self._drain_socketcan(rx)
        got = rx.receive()
        out: list[Frame] = []
        parse, now = self._parse, 0.0
        for raw, ts in got:
            if ts is None:
                ts = now = now or time.time()
            frame = parse(raw, ts)
            if frame is not None:
                out.append(frame)
        return out, len(got) == rx.batch

    def _drain_socketcan(self, rx: BatchReceiver) -> tuple[list[Frame], bool]:
        """_drain for SocketCAN: the whole batch parsed by one ``iter_unpack``; a standard
        data frame (the H2's and the MACCEPA boards' every frame) takes no flag arithmetic."""
        n, data, whole, stamps = rx.receive_fixed()
        out: list[Frame] = []
        append, now = out.append, 0.0
        for (can_id, dlc, payload), ok, ts in zip(
            CAN_FRAME.iter_unpack(data), whole, stamps, strict=True
        ):
            if not ok or dlc > 8:  # truncated (a CAN FD frame) or a length no frame has
                self.malformed += 1
                continue
            if ts is None:
                ts = now = now or time.time()
            if can_id & _CAN_FLAGS:
                ext = bool(can_id & CAN_EFF_FLAG)
                fid = can_id & (0x1FFFFFFF if ext else 0x7FF)
                append(
                    Frame(
                        ts,
                        fid,
                        payload[:dlc],
                        ext,
                        bool(can_id & CAN_RTR_FLAG),
                        bool(can_id & CAN_ERR_FLAG),
                    )
                )
            else:
                append(Frame(ts, can_id, payload[:dlc], False, False, False))
        return out, n == rx.batch

    def _parse_udp(self, raw: bytes, ts: float) -> Frame | None:
        try:
            d = self._unpackb(raw)
            fid = d["arbitration_id"]
            frame = Frame(
                ts,
                fid,
                bytes(d["data"]),
                bool(d.get("is_extended_id")),
                bool(d.get("is_remote_frame")),
                bool(d.get("is_error_frame")),
            )
        except Exception:  # anything on the group that is not python-can's msgpack layout
            self.malformed += 1
            return None
        if self.ids is not None and (frame.is_extended_id or fid not in self.ids):
            self.filtered += 1  # past the kernel filter (too many ids for it, or not exact)
            return None
        if self._dropped(frame):
            self.filtered += 1
            return None
        return frame

    def _dropped(self, f: Frame) -> bool:
        """A content filter's drop, where no kernel ran it (the simulated and virtual buses)."""
        return (
            bool(self._drops)
            and not (f.is_extended_id or f.is_remote_frame or f.is_error_frame)
            and self._drops.drops(f.arbitration_id, f.data)
        )
