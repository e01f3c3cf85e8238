"""The supervisor's judgment of its nodes: each node's beats read from its private pipe
(exolink.liveness) when its deadline timer runs out or at a sweep, a late one killed (and the
watchdog tripped if it is critical and armed), a due restart started, and when the loop must
look next. ``Supervisor`` is a ``NodeJudge``; the watchdog decides what a trip does.

The loop wakes for the nodes that are due, not on a tick: a short deadline (the controller
manager's 50 ms) judged by polling woke the supervisor 20 times a second on the board's one
core (docs/performance.md)."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

from exolink import liveness
from exolink.supervisor import starving
from exolink.supervisor.osproc import apply_priority, proc_state, runnable_others

if TYPE_CHECKING:
    from exolink.config import ApplianceConfig
    from exolink.supervisor.processes import NodeProcess
    from exolink.supervisor.watchdog import Watchdog

MAX_SLEEP_S = 0.25  # the loop looks at least this often, whatever its deadlines say
SWEEP_S = 1.0  # and at every node at least this often (_check_nodes)
STARTING_SLEEP_S = 0.02  # while a node awaits its first beat (its priority comes with it)


class NodeJudge:
    """The node-judging half of the supervisor: the state it shares with it, declared here."""

    cfg: ApplianceConfig
    nodes: dict[str, NodeProcess]
    watchdog: Watchdog
    log: Any
    _expired: set[str]  # nodes whose deadline timer ran out (liveness)
    _sweep_at: float  # when _check_nodes next looks at every node

    def _node_up(self, node: NodeProcess, now: float) -> None:
        """A spawn's first liveness beat: it imported and configured, its loop runs."""
        node.start_s = (node.heartbeat_at or now) - node.started_at  # the beat's own time
        if (pid := node.pid) is not None:
            apply_priority(node.cfg, pid)  # only now: see plain_priority
        self.log.info("node_up", node_name=node.name, start_s=round(node.start_s, 2))

    def _check_nodes(self, now: float) -> None:
        """The nodes whose deadline (a heartbeat's, a restart's) has come, and every node each
        SWEEP_S; between sweeps a node's beats wait in its pipe until its own deadline nears.
        A short deadline (the controller manager's 50 ms) wakes the loop often, so a wake
        judges only the nodes that are due (measured: docs/performance.md)."""
        grace = self.cfg.watchdog.start_grace_ms / 1000
        nodes: Any = self.nodes.values()
        beating = None  # a due node's pipe is read as it is judged: no select first
        if now >= self._sweep_at:
            self._sweep_at = now + SWEEP_S
            beating = liveness.with_beats(n.channel for n in nodes if n.channel)
        else:
            nodes = [n for n in nodes if n.due_at <= now]
        for node in nodes:
            with node.lock:
                late = self._judge_node(node, now, grace, beating)
            if not late:
                continue
            hb, deadline = node.heartbeat_at, self.cfg.deadline_s(node.cfg, node.pace)
            starved = "" if node.starved_after is None else ", starved past its limit"
            detail = (
                f"{node.name}: no heartbeat for {(now - hb) * 1000:.0f} ms (deadline {deadline * 1000:.0f} ms{starved})"
                if hb is not None
                else f"{node.name}: no heartbeat {grace:g} s after start"
            )
            if node.cfg.critical and self.watchdog.armed:
                self.watchdog.trip("heartbeat late", detail)
            # A hung node is killed so its sockets close: a broadcast-manager task it set up in the
            # kernel would otherwise go on sending. The restart policy brings it back.
            self.log.error(
                "node_hung_killed", node_name=node.name, detail=detail, threads=self._threads_now()
            )
            node.kill()

    def _threads_now(self) -> dict[str, str]:
        """Each node's main thread as the kernel sees it when one is found hung: runnable (R)
        while it missed its deadline says the core was busy with others; sleeping in a futex,
        that it waited for a lock (the GIL: with another of its threads runnable, for that one);
        elsewhere, where it blocked."""
        out = {}
        for n in self.nodes.values():
            if (pid := n.pid) is not None:
                runnable, others = runnable_others(pid)
                out[n.name] = f"{proc_state(pid)}; {runnable} of {others} other threads runnable"
        return out

    def _judge_node(
        self, node: NodeProcess, now: float, grace: float, beating: set[Any] | None
    ) -> bool:
        """Under ``node.lock``: a due restart, the beats in its pipe (``beating``: the pipes
        known to hold some; None: read it), and whether it is late; ``due_at`` is set to when
        it next needs a look (a state change by another thread sets it to 0)."""
        if node.state == "backoff" and now >= node.next_start:
            self.log.info("node_restarting", node_name=node.name, restarts=node.restarts)
            node.start()
        late, expired = False, node.name in self._expired
        self._expired.discard(node.name)
        if node.state == "running" and node.pid is not None:
            if (beating is None or node.channel in beating) and node.poll_liveness(now):
                self._node_up(node, now)
            hb = node.heartbeat_at
            if hb is None:
                late = now - node.started_at > grace
            else:
                late = now - hb > self.cfg.deadline_s(node.cfg, node.pace)
                if (limit := self.cfg.starved_deadline_s(node.cfg)) is not None:
                    if not late:
                        threads = node.threads()
                        node.sched_mark = None if threads is None else threads.read(now)
                        node.starved_after = None
                    elif now - hb <= limit and self._starved(node, now, hb):
                        node.due_at = min(hb + limit, now + self._recheck_s(node))
                        return False
        node.due_at = self._due(node, now, grace, expired)
        return late

    def _starved(self, node: NodeProcess, now: float, hb: float) -> bool:
        """Past its deadline but waiting for the CPU (exolink.supervisor.starving): judged
        again until its ``starved_deadline_ms``; logged once per silence, and counted."""
        threads = node.threads()
        now_sched = None if threads is None else threads.read(now, states=True)
        shares = starving.starved(node.sched_mark, now_sched)
        if shares is None:
            return False
        if node.starved_after != hb:
            node.starved_after, node.starved = hb, node.starved + 1
            self.log.warning(
                "node_starved",
                node_name=node.name,
                silent_ms=round((now - hb) * 1000),
                loop=now_sched.state if now_sched else "?",  # R, or S: on a thread of its own
                waited_pct=round(100 * shares[0]),
                ran_pct=round(100 * shares[1]),
                limit_ms=round(1000 * (self.cfg.starved_deadline_s(node.cfg) or 0)),
            )
        return True

    def _recheck_s(self, node: NodeProcess) -> float:
        """How often a starved node is looked at again: a quarter of its deadline."""
        return max(self.cfg.deadline_s(node.cfg, node.pace) / 4, 0.02)

    def _due(self, node: NodeProcess, now: float, grace: float, expired: bool = False) -> float:
        """When ``node`` next needs a look, given what the loop knows of it now (inf: only the
        sweeps look; a state change sets ``due_at`` to 0). A node that sets its deadline timer
        (exolink.liveness) is looked at when the timer runs out; one whose timer is not set,
        or ran out though its pipe holds a later beat, by polling its deadline."""
        if node.state == "backoff":
            return node.next_start
        if node.state != "running":
            return math.inf
        hb = node.heartbeat_at
        if hb is None:  # starting: its first beat brings its priority
            return min(now + STARTING_SLEEP_S, node.started_at + grace)
        longest = max(node.deadlines or self.cfg.deadlines_s(node.cfg))  # set at spawn
        if not expired and node.channel is not None and node.channel.armed(longest):
            return math.inf
        due = hb + self.cfg.deadline_s(node.cfg, node.pace)  # the beats in its pipe read then
        if node.pace != liveness.Pace.OWN:  # its first beat by its own deadline is judged on time
            due = min(due, now + self.cfg.deadline_s(node.cfg))
        return due

    def take_beats(self) -> None:
        """Every node's beats read now, for an answer about them (arming, status): between
        sweeps the loop reads a pipe only when its node's deadline timer runs out."""
        now = time.monotonic()
        for node in self.nodes.values():
            with node.lock:
                if node.state == "running" and node.pid is not None and node.poll_liveness(now):
                    self._node_up(node, now)

    def node_blockers(self) -> list[str]:
        """What keeps the watchdog from arming on the nodes' side: a critical node not running,
        or without a beat within its deadline (every pipe read now)."""
        out = []
        self.take_beats()
        now = time.monotonic()
        for n in self.nodes.values():
            if not (n.cfg.critical and n.cfg.enabled):
                continue
            if n.state != "running":
                out.append(f"critical node {n.name} is {n.state}")
            elif n.heartbeat_at is None or now - n.heartbeat_at > self.cfg.deadline_s(
                n.cfg, n.pace
            ):
                out.append(f"critical node {n.name} has no recent heartbeat")
        return out

    def _timer_ran_out(self, node: NodeProcess, fd: int) -> None:
        """A node's deadline timer ran out: judged at once (its pipe says whether it beat
        meanwhile). The descriptor is read only if it is still this node's timer."""
        with node.lock:
            if node.channel is not None and node.channel.timer == fd and node.channel.expired():
                self._expired.add(node.name)
                node.due_at = 0.0

    def _next_due(self, now: float) -> float:
        """The nearest deadline of the nodes (their ``due_at``) and the watchdog."""
        return min(
            now + MAX_SLEEP_S,
            self.watchdog.next_due(),
            min((n.due_at for n in self.nodes.values()), default=math.inf),
        )
