"""Set-points on the kernel's timer, leased: a broadcast-manager send op (``CyclicLease``) that
sends at most a lease of frames after its owner's last renewal, so an owner stopped, hung or
killed stops the motion by itself; on a bus without a broadcast manager the same contract in
a thread of the owner (``ThreadLease``). The controller manager's timer (``timed``) is their
one user. ``struct bcm_msg_head``: exolink.canbus.bcm."""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Protocol

from exolink.canbus.bcm import HEAD, SentCounts, open_bcm, tx_delete
from exolink.canbus.frames import CAN_FRAME
from exolink.canbus.opening import CanOpenError

if TYPE_CHECKING:
    import can


def _check_lease(lease: int, planned: int, ring: int) -> None:
    """A lease of 1 frame up to what is planned, at most the op's ring (both leases' rule)."""
    if not 1 <= lease <= min(planned, ring):
        raise ValueError(
            f"lease of {lease} frames: must be 1..{min(planned, ring)} "
            f"(the frames planned, at most the op's {ring})"
        )


def _checked(slot: int, payload: bytes) -> bytes:
    if len(payload) > 8:
        raise ValueError(f"slot {slot}: a CAN frame carries 8 bytes, got {len(payload)}")
    return payload


def _place_ahead(
    frames_from: Mapping[int, bytes],
    n: int,
    written: int,
    ring: int,
    put: Callable[[int, bytes], None],
) -> int:
    """Both leases' renewal: slot k sits at ring position k mod ``ring`` from ``start`` on, and
    each is placed once (a plan does not change what it planned), so only slots from
    ``max(n, written)`` up to a ring ahead of ``n`` are put. The first slot not placed."""
    k, end = max(n, written), n + ring
    # one lookup a slot (``get``), not a test and a fetch: on the board proxy the two were a
    # fifth of a renewal's Python (F71, cProfile)
    while k < end and (frame := frames_from.get(k)) is not None:
        put(k, frame)
        k += 1
    return k


# PeriodTrim: the window over which the timer's lateness is averaged (enough frames that a
# count read one frame off moves the estimate a few microseconds), and the most it makes up,
# as a share of the period (also the shortest interval it sets).
TRIM_WINDOW_S = 2.0
TRIM_MIN_FRAMES = 100
TRIM_MAX = 0.2
PACKED_MAX = 4096  # payloads packed and kept (a gait's cycle: four joints' ~50 slots)


class OpLost(ValueError):
    """The op is gone, or where it is is not known (deleted by the supervisor's copy at a
    safe action, frames the device refused): no renewal can bring it back, and none is tried
    again (a short plan, the other ValueError of ``renew``, is waited for)."""


class PeriodTrim:
    """The interval to give the broadcast manager so that the op's mean period is the one
    asked for. The kernel arms each frame's timer when the last one went out (``now + ival``),
    so a timer's lateness adds to every period: on the board proxy a slot of the gait came out
    at 21.20 ms on average for 20 (B67), on vcan under UML 20.25. Renewals read how many frames
    went out by when; over ``TRIM_WINDOW_S`` that gives the mean lateness per frame, and the
    next interval is the period less it. A renewal's interval later than ``TRIM_MAX`` a frame
    (and a period for the count's rounding) was a stall, not the timer's lateness: it counts
    as late as the estimate already was, so a stall shifts the phase instead of making the
    frames after it short."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.ival_s = period_s
        # (monotonic time, frames sent, the lateness counted up to then), oldest first
        self._marks: deque[tuple[float, int, float]] = deque()

    def restart(self, t: float, sent: int) -> None:
        """A new phase (``start``, ``resume``) at ``t``, with ``sent`` frames gone out
        (the one the start sends at once included); what was learnt of the lateness stays."""
        self._marks.clear()
        self._marks.append((t, sent, 0.0))

    def update(self, t: float, sent: int) -> float:
        """``sent`` frames had gone out at ``t``: the interval for the frames from now on."""
        if not self._marks:
            self.restart(t, sent)
        t1, n1, late1 = self._marks[-1]
        frames = sent - n1
        excess = (t - t1) - frames * self.ival_s
        if excess > (frames * TRIM_MAX + 1) * self.period_s:  # a stall
            excess = frames * (self.period_s - self.ival_s)
        late = late1 + excess
        self._marks.append((t, sent, late))
        while len(self._marks) > 2 and self._marks[1][0] <= t - TRIM_WINDOW_S:
            self._marks.popleft()
        _, n0, late0 = self._marks[0]
        if sent - n0 >= TRIM_MIN_FRAMES:
            lateness = (late - late0) / (sent - n0)
            shortest = self.period_s * (1 - TRIM_MAX)
            self.ival_s = min(self.period_s, max(shortest, self.period_s - lateness))
        return self.ival_s


class CyclicLease:
    """A broadcast-manager send op on ``can_id``: frames the kernel sends one per ``period_s``
    on its own timer, for at most ``lease`` frames after the last ``start`` or ``renew``.

    Set-points known ahead (a gait pattern) leave on the kernel's timer, not on a Python
    process's wake-up, and the owner's silence bounds them: an owner stopped, hung or starved
    stops renewing, and the kernel sends what the lease still allows, then nothing (``count``
    frames at ``ival1``, no ``ival2``: the op's timer ends). Closing the socket (the process
    killed) deletes the op at once; ``stop`` (TX_DELETE) does the same on purpose; on a socket
    the supervisor holds too (exolink.canbus.held) its watchdog does, at every safe action,
    and at the owner's exit.

    Content is planned by slot: slot n is the n-th frame the op sends since ``start``, and it
    sits at ring position n mod ``ring``, always: the op's index is never reset after
    ``start``. A renewal writes slots at their positions, reads the op's remaining
    ``count`` (TX_READ) and then the kernel's own count of its frames (``SentCounts``), and
    sets a new ``count`` without restarting the timer (SETTIMER without STARTTIMER keeps the
    phase; the same number of frames keeps the index). Frames the kernel sends before that
    setup lands were already at their positions: nothing is repeated or skipped, and the new
    count is bounded from where the old one ends, so no frame the renewal did not place goes
    out however late the setup lands (``renew``). If the old count ran out before the setup,
    the timer ended and the setup does not start it: the op stays silent with a full count
    (the board proxy under a CPU cap, I63). The renewal then, or ``resume``, halts the timer,
    reads the exact count and starts it from there: the next slot now, the rest one a period
    after it, a new phase (Timed: a lapse resumed). An op whose count went back (deleted by
    the supervisor's copy and made again by a setup) is deleted, never started.
    """

    def __init__(
        self,
        channel: str,
        can_id: int,
        period_s: float,
        ring: int = 16,
        sock: socket.socket | None = None,
    ) -> None:
        """``sock``: a broadcast-manager socket connected to ``channel`` that the supervisor
        holds too (exolink.canbus.held), kept open by ``close``; else the op's own."""
        if not 0 < period_s < 60:
            raise ValueError(f"broadcast-manager period must be in (0, 60) s, got {period_s}")
        if not 2 <= ring <= 256:
            raise ValueError(f"broadcast-manager frames per op must be 2..256, got {ring}")
        self.can_id, self.period_s, self.ring = can_id, period_s, ring
        self._frames = [CAN_FRAME.pack(can_id, 0, bytes(8))] * ring  # packed, by ring position
        self._written = 0  # slots below this are placed (in increasing order: never again)
        self._base = 0  # slot of the op's first frame since the last start or renew
        self._lease = 0  # the count that start or renew set
        self._final: int | None = None  # the kernel's count of the op's frames at ``stop``
        self.recounted = 0  # frames the op's count lost and the kernel's own count found
        self.restarted = 0  # renewals that started the timer again at the lease's end
        self._trim = PeriodTrim(period_s)
        self._packed: dict[bytes, bytes] = {}  # payload -> its can_frame (``_put``)
        self._own_sock = sock is None
        self._sock = open_bcm(channel) if sock is None else sock
        self._sock.settimeout(1.0)  # a TX_READ's answer is immediate; never wait forever
        try:
            self._counts = SentCounts(self._sock)
        except CanOpenError:
            self._drop_sock()
            raise

    def _drop_sock(self) -> None:
        if self._own_sock:
            self._sock.close()

    @property
    def interval_s(self) -> float:
        """The interval the kernel is given: the period, trimmed (``PeriodTrim``)."""
        return self._trim.ival_s

    def _setup(
        self, flags: int, lease: int, ring: bytes | None = None, ival_s: float | None = None
    ) -> None:
        """TX_SETUP with the ring's frames (``ring``: joined ahead, by ``renew``), at the
        trimmed interval unless ``ival_s`` is given (0 with SETTIMER: the timer halted)."""
        ival = self._trim.ival_s if ival_s is None else ival_s
        sec, usec = int(ival), round((ival % 1) * 1e6)
        head = HEAD.pack(
            socket.CAN_BCM_TX_SETUP, flags, lease, sec, usec, 0, 0, self.can_id, self.ring
        )
        self._sock.send(head + (b"".join(self._frames) if ring is None else ring))
        self._lease = lease

    def _put(self, slot: int, payload: bytes) -> None:
        """A replayed gait places the same ~200 payloads over and over: each is packed once."""
        frame = self._packed.get(payload)
        if frame is None:
            payload = _checked(slot, payload)
            frame = CAN_FRAME.pack(self.can_id, len(payload), payload.ljust(8, b"\0"))
            if len(self._packed) >= PACKED_MAX:
                self._packed.clear()
            self._packed[payload] = frame
        self._frames[slot % self.ring] = frame

    def start(self, frames: list[bytes], lease: int) -> None:
        """Slot 0 (``frames[0]``) now, then one frame per period: a new phase."""
        _check_lease(lease, len(frames), self.ring)
        for k, f in enumerate(frames[: self.ring]):
            self._put(k, f)
        self._written = min(len(frames), self.ring)
        tx_delete(self._sock, self.can_id)  # a new op: the kernel counts its frames from 0
        self._final = None
        self._setup(
            socket.CAN_BCM_SETTIMER | socket.CAN_BCM_STARTTIMER | socket.CAN_BCM_TX_RESET_MULTI_IDX,
            lease,
        )
        self._trim.restart(time.monotonic(), 1)  # slot 0 went out with the setup
        self._base = 0

    def remaining(self) -> int:
        """Frames the op may still send (0: the lease ran out, or no op)."""
        return self._read_count() or 0

    def _read_count(self) -> int | None:
        """TX_READ's count (None: no op on this id, or no answer: never taken for 0 by a
        renewal, whose bound it is)."""
        head = HEAD.pack(socket.CAN_BCM_TX_READ, 0, 0, 0, 0, 0, 0, self.can_id, 0)
        try:
            self._sock.send(head)
            reply = self._sock.recv(HEAD.size + self.ring * CAN_FRAME.size)
            return int(HEAD.unpack_from(reply)[2])
        except (OSError, struct.error):  # EINVAL: no op (never started, or deleted); timeout
            return None

    def sent(self) -> int:
        """The slot the op sends next: how many it sent since ``start``, by its count."""
        return self._base + self._lease - self.remaining()

    @property
    def ends_at(self) -> int:
        """The slot the count set last ends before (the op sends no slot from it on, unless a
        setup landed late: then a few slots later, within what was placed)."""
        return self._base + self._lease

    def renew(self, frames_from: Mapping[int, bytes], lease: int) -> int:
        """Slots ``n, n+1, ...`` from ``frames_from`` (slot -> payload; n, returned: the next
        slot, by the kernel's own count) and up to ``lease`` frames from now, never one the
        renewal did not place (none placeable: ValueError, no renewal; the op gone or its place
        not known: OpLost, the op deleted). A lease that already ran out is not restarted
        (``start`` is a new phase, on purpose).

        The reads and the setup are system calls apart, and the owner can be preempted between
        them for any time: the timer goes on sending the old count meanwhile, and the new
        count starts wherever the op is when the setup lands. Bounded by the slots placed from
        the read alone (``n + lease`` within the plan), a setup that landed three frames late
        (a starved manager, C74: calibration 867 ms) sent two frames past the plan, from ring
        positions a ring old: the gait jumped back 280 ms (a knee 45 -> 0 -> 58 deg). So the
        op's count is read first (TX_READ: it sends at most ``left`` more frames), then the
        kernel's count of its frames (``SentCounts``: exact, no setup resets it, no sender on
        the bus moves it): the op is at most at ``n + left`` when the setup lands, and the new
        count is bounded from there. The slots are placed before the reads (from the last
        renewal's slot; a slot placed over one already sent is harmless). The ring holds two
        leases (on_timer), so the bound costs nothing while renewals come in time."""
        k = _place_ahead(frames_from, self._base, self._written, self.ring, self._put)
        self._written = max(self._written, k)
        ring = b"".join(self._frames)
        t0 = time.monotonic()
        left = self._read_count()  # the old count: at most this many more frames ...
        seen = self._counts.sent(self.can_id)  # ... after these (read after it)
        if left is None or seen is None:
            # gone, or a read that failed (a socket error pending from the device going
            # down): where the op is is not known, so it goes, as below
            self.stop()
            raise OpLost(f"op {self.can_id:#x}: no count to bound a renewal by: op deleted")
        counted = self._base + self._lease - left  # the op's count of them: short after a race
        if seen < self._base or counted > seen + 1:
            # The kernel's count went back (the op was deleted, by the supervisor's copy at a
            # safe action, and a setup made a new one) or is behind the op's own count (frames
            # the device refused: the op's index went on, its count of sent frames did not;
            # one frame is the count's own lag before 6.15, which the bound below allows for):
            # where the op is is not known, so it goes (TX_DELETE).
            self.stop()
            raise OpLost(
                f"op {self.can_id:#x}: the kernel counts {seen} frames sent, the op "
                f"{counted} since slot {self._base}: its index is not known, op deleted"
            )
        n = seen
        # never past the plan, however late the setup lands; one frame less for a kernel
        # that counts a frame down before it counts it sent (before 6.15)
        bound = k - n - left - 1
        lease = min(lease, bound)
        _check_lease(lease, bound, self.ring)  # ValueError: no renewal, nothing counted
        self.recounted += max(0, n - counted)
        self._setup(socket.CAN_BCM_SETTIMER, lease, ring)
        # frames the timer may have sent since the read: one, and one more each period it took
        window = 1 + int((time.monotonic() - t0) / self.interval_s)
        self._base = n
        if 0 < left <= window and lease >= 2:
            # The old count's last frames may have gone out before the setup: the timer then
            # ended, and the count just set waits for a start that never comes (silent until
            # a later renewal saw no progress: two gaps, 50 and 87 ms, in B69). Started again
            # now (a new phase, at most an interval off) from where it stopped.
            self._start_here(n + lease)
            self.restarted += 1
        elif left > 0:
            self._trim.update(t0, n)  # the interval for the next renewal's setup
        # (left == 0: the lease ran out before the read; the caller resumes, a new phase)
        return n

    def _start_here(self, end: int) -> None:
        """The timer halted (a setup without an interval: the op's index stays), the kernel's
        count of its frames read (exact: nothing moves it now), then started from there for
        the frames up to slot ``end`` (exclusive), never past what is placed: a new phase. A
        start read from the count before a halt could begin wherever a preempted owner's
        timer had got to meanwhile."""
        self._setup(socket.CAN_BCM_SETTIMER, 0, ival_s=0.0)
        at = self._counts.sent(self.can_id)
        if at is None or at < self._base:
            # gone, or made again by that setup after the supervisor's copy deleted it (a safe
            # action): nothing may start, and the op so made goes too
            self.stop()
            return
        self._base = at
        count = min(end, self._written) - at
        if count >= 1:  # else halted: the next renewal finds no progress (a lapse)
            self._setup(socket.CAN_BCM_SETTIMER | socket.CAN_BCM_STARTTIMER, count)
            self._trim.restart(time.monotonic(), at + 1)

    def resume(self) -> None:
        """After a renewal of an op whose timer ended (its lease ran out, or the race above):
        the timer started again from where the op is (its index kept, so each slot stays at
        its ring position), for what that renewal allowed: the next slot now, the rest one a
        period after it. A new phase, as ``start``'s."""
        self._start_here(self._base + self._lease)

    def settled(self, counted: int) -> int:
        """After ``stop``: how many of the op's frames went out, ``counted`` (a ``sent`` read
        before the stop) made good by the kernel's own count, which ``stop`` read with the
        timer halted: a frame the timer sent after that read, or one a renewal's race left
        out of the op's count, was on the bus (the step limit goes on from the slot the joint
        is at, Timed.leave)."""
        return max(counted, self._final or 0)

    def stop(self) -> None:
        """Nothing more from this op, now: its timer halted (a setup without an interval
        cancels it and keeps the op), so the kernel's count of its frames is final when read,
        then TX_DELETE. An op already stopped, or never started, is only deleted."""
        if self._lease:
            with contextlib.suppress(OSError):  # the TX_DELETE below ends it all the same
                self._setup(socket.CAN_BCM_SETTIMER, 0, ival_s=0.0)
                self._final = self._counts.sent(self.can_id)
        tx_delete(self._sock, self.can_id)  # no op: nothing to delete
        self._lease = 0

    def close(self) -> None:
        """Closing the socket deletes its op in the kernel; a held socket (the supervisor's
        too) stays open for the owner's next op, its op deleted."""
        if self._own_sock:
            self._sock.close()
        elif self._lease:  # not deleted yet (``Timed.abort`` stops first: one TX_DELETE)
            self.stop()
        self._counts.close()


class Lease(Protocol):
    """What the controller manager asks of a lease (``CyclicLease``, ``ThreadLease``)."""

    can_id: int
    period_s: float
    ring: int
    recounted: int
    restarted: int

    @property
    def interval_s(self) -> float: ...

    @property
    def ends_at(self) -> int: ...

    def start(self, frames: list[bytes], lease: int) -> None: ...
    def sent(self) -> int: ...
    def settled(self, counted: int) -> int: ...
    def renew(self, frames_from: Mapping[int, bytes], lease: int) -> int: ...
    def resume(self) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


# A sleep wakes up to the timer slack late (50 us by default): ThreadLease sleeps to this much
# before a slot and spins the rest, as a simulated bus is timed on a development machine.
SPIN_S = 0.0003


class ThreadLease:
    """``CyclicLease``'s contract on a bus without a broadcast manager (the simulated bus, the
    virtual one): a thread of the owner's process sends the slots through ``bus``, one per
    ``period_s`` from ``start``, at most ``lease`` after the last ``start`` or ``renew``, with
    the same slot arithmetic (a renewal keeps the phase and does not restart a lapsed lease;
    ``resume`` does, in a new phase).

    Only the owner's failure modes differ, to the safe side: stopped or killed with its owner,
    where the kernel's op sends out its lease (stopped) or ends at once (killed)."""

    def __init__(self, bus: can.BusABC, can_id: int, period_s: float, ring: int = 16) -> None:
        if not 0 < period_s < 60:
            raise ValueError(f"lease period must be in (0, 60) s, got {period_s}")
        if not 2 <= ring <= 256:
            raise ValueError(f"frames per lease must be 2..256, got {ring}")
        self.can_id, self.period_s, self.ring = can_id, period_s, ring
        self._bus = bus
        self._cond = threading.Condition()
        self._frames = [bytes(8)] * ring  # by ring position, as CyclicLease's
        self._written = 0
        self._index = 0  # the op's next frame
        self._count = 0  # frames the lease still allows
        self._base = 0
        self._lease = 0
        self._running = False
        self._stopped = False  # stop()ped: gone, as a deleted op (a renewal: OpLost)
        self.recounted = 0  # never: this count loses nothing
        self.restarted = 0  # never: its thread cannot end between a read and a setup
        self._next_at = 0.0  # monotonic time of the next frame
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"lease-{can_id}", daemon=True)
        self._thread.start()

    @property
    def interval_s(self) -> float:
        """The period: each frame is due a period after the last was due, never trimmed."""
        return self.period_s

    def start(self, frames: list[bytes], lease: int) -> None:
        _check_lease(lease, len(frames), self.ring)
        with self._cond:
            for k, f in enumerate(frames[: self.ring]):
                self._put(k, f)
            self._written = min(len(frames), self.ring)
            self._index, self._count, self._base, self._lease = 0, lease, 0, lease
            self._running, self._next_at, self._stopped = True, time.monotonic(), False
            self._cond.notify()

    @property
    def ends_at(self) -> int:
        """``CyclicLease.ends_at`` (exact here: a renewal cannot land late)."""
        with self._cond:
            return self._base + self._lease

    def remaining(self) -> int:
        """The op's count, as TX_READ says it: a renewal sets it even on a timer that ended."""
        with self._cond:
            return self._count

    def sent(self) -> int:
        with self._cond:
            return self._base + self._lease - self._count

    def renew(self, frames_from: Mapping[int, bytes], lease: int) -> int:
        """As the kernel's SETTIMER without STARTTIMER (its count loses nothing: one lock):
        the new count is set, and a timer that
        ended (its count reached 0, even between this renewal's read and its setup) stays
        ended, the op silent with a full count (Timed.keep tells that from a stall). A stopped
        lease is gone, as a deleted op: OpLost."""
        with self._cond:
            if self._stopped:
                raise OpLost(f"lease {self.can_id:#x}: stopped, nothing to renew")
            n = self._base + self._lease - self._count
            k = _place_ahead(frames_from, n, self._written, self.ring, self._put)
            self._written = max(self._written, k)
            lease = min(lease, k - n - 1)  # the kernel's rule (CyclicLease.renew)
            _check_lease(lease, k - n - 1, self.ring)
            self._base, self._lease, self._count = n, lease, lease
            return n

    def settled(self, counted: int) -> int:
        """``CyclicLease.settled``: this count loses nothing, and a frame sent after the
        caller's read is counted too."""
        return max(counted, self.sent())

    def resume(self) -> None:
        """``CyclicLease.resume``: the timer started again now, from the op's next frame (its
        index kept), for the count the last renewal set."""
        with self._cond:
            if self._count > 0:
                self._running, self._next_at = True, time.monotonic()
                self._cond.notify()

    def _put(self, slot: int, payload: bytes) -> None:
        self._frames[slot % self.ring] = bytes(_checked(slot, payload))

    def stop(self) -> None:
        with self._cond:
            self._running, self._count, self._lease, self._stopped = False, 0, 0, True

    def close(self) -> None:
        with self._cond:
            self._closed, self._running, self._count = True, False, 0
            self._cond.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(1.0)

    def _due(self) -> can.Message | None:
        """Under the lock at the slot's time: the frame to send, or None (stopped meanwhile)."""
        import can  # lazy: python-can: only a process that sends through the op

        if not self._running or self._count <= 0:
            return None
        data = self._frames[self._index]
        self._index = (self._index + 1) % self.ring
        self._count -= 1
        self._next_at += self.period_s
        if self._count == 0:
            self._running = False  # the lease ran out: the timer ends, as the kernel's
        return can.Message(arbitration_id=self.can_id, data=data, is_extended_id=False)

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and not self._running:
                    self._cond.wait()
                if self._closed:
                    return
                at = self._next_at
            while (delay := at - time.monotonic()) > SPIN_S:
                time.sleep(delay - SPIN_S)
            while time.monotonic() < at:
                pass
            with self._cond:
                msg = self._due() if at == self._next_at else None
            if msg is not None:
                with contextlib.suppress(Exception):  # a full queue: that slot is lost
                    self._bus.send(msg)


def open_lease(
    interface: str,
    channel: str,
    bus: can.BusABC,
    can_id: int,
    period_s: float,
    ring: int,
    sock: socket.socket | None = None,
) -> Lease:
    """The kernel's broadcast manager on SocketCAN (``sock``: the supervisor's held socket,
    exolink.canbus.held, else its own), a thread of this process elsewhere."""
    if interface == "socketcan":
        return CyclicLease(channel, can_id, period_s, ring, sock)
    return ThreadLease(bus, can_id, period_s, ring)
