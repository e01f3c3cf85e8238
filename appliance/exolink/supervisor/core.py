"""The supervisor (``exolink up``): safe state first, then nodes, watchdog and management API.

Start order is the safety order: validate the whole config (nothing starts on an error), bring up
CAN, send the safe action on the watchdog's own socket, open the Zenoh router, then spawn nodes.
Stop order is the reverse with the safe action first.
"""

from __future__ import annotations

import contextlib
import gc
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec
import structlog
import yaml

from exolink import hardware, messaging
from exolink.board import update
from exolink.board.clock import BoardClock
from exolink.canbus.held import HeldOps
from exolink.config import ApplianceConfig
from exolink.control.arming import WATCHDOG_TOPIC, WATCHDOG_TYPE
from exolink.runtime import profiled, stop_on_signals
from exolink.supervisor import canlink, trigger
from exolink.supervisor.api import ManagementApi
from exolink.supervisor.device_watch import watch_device
from exolink.supervisor.forking import Zygote, become_subreaper
from exolink.supervisor.judging import NodeJudge
from exolink.supervisor.memory import MemoryTrim
from exolink.supervisor.osproc import kill_strays
from exolink.supervisor.processes import Exit, NodeProcess, relay
from exolink.supervisor.ros2api import Ros2Api
from exolink.supervisor.systemd import Notifier
from exolink.supervisor.telemetry import DIAGNOSTICS_TYPE, NodeTelemetry
from exolink.supervisor.wakeup import Wakeup
from exolink.supervisor.watchdog import Watchdog
from exolink.wire import cdr, replies

if TYPE_CHECKING:
    pass

SUPERVISOR = "supervisor"  # its name as a ROS 2 node, in the logs and among the nodes' tokens
STRAY_SWEEP_S = 5.0  # the loop looks for node processes it does not count as any node's
# ... in the main thread's children (a forked node's parent: osproc.children), and in every
# thread's this often: reading ~50 threads' lists every 5 s was a ~50-70 ms burst of the
# supervisor's Python on the board proxy (0.6 points of CPU 0: docs/performance.md)
STRAY_FULL_SWEEP_S = 60.0
HEALTH_PERIOD_S = 2.0
SLOW_LOOP_S = 0.5  # one pass of the loop taking this long is logged (a CPU starved of it)
STATE_PERIOD_S = 1.0
TRIGGER_TYPE = "exolink_msgs/msg/TriggerEvent"
TRIM_PERIOD_S = 10.0
TRIM_GROWTH_MB = 8.0
PAGE_SIZE = os.sysconf("SC_PAGE_SIZE")


class _Stop(threading.Event):
    """Set on a stop request; wakes the supervisor's loop too."""

    def __init__(self, wake: Wakeup) -> None:
        super().__init__()
        self._wake = wake

    def set(self) -> None:
        super().set()
        self._wake.set()


class Supervisor(NodeJudge, NodeTelemetry):
    def __init__(self, cfg: ApplianceConfig) -> None:
        self.cfg = cfg
        # the hardware guarded (exolink.hardware): an unknown name starts nothing
        self.device = hardware.load(cfg.hardware)
        self.log = structlog.get_logger().bind(node=SUPERVISOR)
        # The loop sleeps until its next deadline; whatever moves one closer sets this.
        self.wake = Wakeup()
        self._sweep_at = 0.0  # when _check_nodes next looks at every node
        self._expired: set[str] = set()  # nodes whose deadline timer ran out (liveness)
        self.stop_event = _Stop(self.wake)
        self.stopping = False
        self.notifier = Notifier()
        self.trigger_count = 0
        self.bad_samples: dict[str, int] = {}  # "<topic>: <error>" -> count (see _bad_sample)
        self.last_trigger_ns: int | None = None
        self.health: canlink.LinkHealth | None = None
        self.link: canlink.LinkMonitor | None = None
        self._decls: list[Any] = []
        self._workdir = Path(tempfile.mkdtemp(prefix="exolink-"))
        self.nodes: dict[str, NodeProcess] = {}
        self.held: HeldOps | None = None  # leased nodes' send-op sockets (exolink.canbus.held)
        self.memory = MemoryTrim()
        self.node_api: dict[str, dict[str, int]] = {}  # each node's Admission counters
        self.clock = BoardClock(Path(state_dir(cfg, self._workdir)), cfg.clock.from_laptop)
        # Bundles from an admin laptop (exolink.board.update; on the board /var/lib/exolink/update,
        # where the root agent picks them up) and this boot's healthy mark, left once.
        self.update = update.Receiver(update.local_dir(self._workdir))
        self._healthy_marked = False

    # --- start-up ---------------------------------------------------------------------------

    def start(self) -> None:
        cfg, dev = self.cfg, self.device
        runtime = messaging.zenoh_runtime(cfg.zenoh)  # before any session: nodes inherit it
        if runtime is not None:
            self.log.info("zenoh_runtime", setting=runtime)
        self.zygote = self._start_zygote()  # a fork: before any socket, session or thread
        if cfg.can.interface == "socketcan":
            if cfg.can.require_overlay:
                canlink.check_overlay()
            if cfg.can.bring_up:
                canlink.bring_up_apart(cfg.can)  # pyroute2 in a child, never resident here
        eyes = watch_device(cfg, dev)  # the watchdog's reader, and the kernel's watches
        self.reader = eyes.reader
        self.bus = self.reader.bus
        self.session = messaging.open_hub_session(cfg)
        self.msg = messaging.Messaging(self.session, cfg, ros_node=SUPERVISOR)
        self.pub_wd = self.msg.publisher(WATCHDOG_TOPIC, WATCHDOG_TYPE, raw=True)
        self.watchdog = Watchdog(
            cfg.watchdog,
            self.reader,
            self._publish_watchdog,
            dev,
            eyes.pulse,
            eyes.command,
            reopen=eyes.reopen,
        )
        self.watchdog.wake = self.wake.set  # a trip's repeats are due within 50 ms
        if cfg.can.interface == "socketcan":  # leased nodes' send ops, deleted by every trip
            self.held = self.watchdog.held = HeldOps(cfg.can.channel, (dev.command_id,))
        self.watchdog.start()  # safe action before anything else can move
        self._check_bus()  # before READY: a link already bad is known at start
        if cfg.can.interface == "socketcan":
            self._link_thread = threading.Thread(target=self._link_loop, daemon=True, name="link")
            self._link_thread.start()
        # CDR from exolink.wire.cdr: no typestore (rosbags, numpy: ~13 MB, seconds of start on the A8)
        self.pub_trigger = self.msg.publisher("trigger", TRIGGER_TYPE, raw=True)
        self.pub_diag = self.msg.publisher("supervisor/diagnostics", DIAGNOSTICS_TYPE, raw=True)
        config_path = self._workdir / "appliance.yaml"
        config_path.write_text(yaml.safe_dump(_config_data(cfg, self._workdir), sort_keys=False))
        # Every node in the dict before the API answers: its handlers iterate the dict on their
        # own threads, and a node added meanwhile failed a boot-time `status` ("dictionary
        # changed size during iteration", H69's journal). Never added to after this.
        for ncfg in cfg.nodes:
            node = NodeProcess(ncfg, str(config_path), self._on_exit, self._on_line)
            node.zygote = self.zygote
            node.deadlines = cfg.deadlines_s(ncfg)
            if ncfg.leased_deadline_ms is not None:
                node.held = self.held
            self.nodes[ncfg.name] = node
        self.api = ManagementApi(self)
        self._decls += self.api.serve(self.msg)
        # Laptops find the device by these tokens (exolink.client): the supervisor's own, so an
        # appliance whose nodes are all stopped, failed or not configured still answers
        # `exolink status` without --device, and the operator can see why.
        alive = self.msg.mgmt("nodes", SUPERVISOR, "alive")
        self._decls.append(self.session.liveliness().declare_token(alive))
        self.ros2 = Ros2Api(self)  # the same commands as ROS 2 services (rmw_zenoh)
        self._decls += self._hear_nodes()
        self.trigger_src = trigger.open_source(cfg.trigger, self._on_edge)
        self.trigger_out = trigger.open_output(cfg.trigger)
        for node in self.nodes.values():
            if node.cfg.enabled:
                node.start()
        self.log.info(
            "supervisor_running",
            device=cfg.device,
            nodes=[n.name for n in cfg.nodes if n.enabled],
            listen=cfg.zenoh.listen,
            bus=f"{cfg.can.interface}:{cfg.can.channel}",
        )
        self.notifier.ready()

    def _start_zygote(self) -> Zygote | None:
        """Nodes fork from a pre-imported runtime (fast restarts, shared pages) unless
        EXOLINK_SPAWN=exec asks for a fresh interpreter per node (tests that hook its start)."""
        try:
            become_subreaper()
        except OSError as exc:
            self.log.warning("subreaper_unavailable", error=str(exc))
        if os.environ.get("EXOLINK_SPAWN") == "exec":
            return None
        try:
            zygote = Zygote()
        except OSError as exc:
            self.log.warning("zygote_unavailable", error=str(exc), fallback="exec")
            return None
        gc.freeze()  # this process' objects, shared with the zygote: no collector writes to them
        return zygote

    # --- events from other threads ----------------------------------------------------------

    def _on_exit(self, ex: Exit) -> None:
        """A spawn's exit, under its node's lock (NodeProcess._wait): nothing starts a
        successor while this runs, so the state set here is this spawn's own."""
        node = self.nodes[ex.node]
        what = ex.signal or f"exit code {ex.code}"
        if self.stopping:
            return
        if not ex.current:  # a restart replaced it already: its successor's state stands
            self.log.info("node_old_spawn_exited", node_name=ex.node, pid=ex.pid, how=what)
            return
        if ex.deliberate:  # a stop or restart asked it to go (and tripped, if critical)
            self.log.info("node_stopped", node_name=ex.node, pid=ex.pid, how=what)
            if node.state == "stopping":
                node.state = "stopped"
            node.due_at = 0.0
            return
        if node.cfg.critical:
            self.watchdog.trip("critical node exited", f"{ex.node}: {what}")
        self.log.warning("node_exited", node_name=ex.node, how=what, pid=ex.pid)
        if node.failed_by_policy(ex.code):
            if not node.schedule_restart(time.monotonic()):
                self.log.error(
                    "node_failed_permanently",
                    node_name=ex.node,
                    restarts=node.restarts,
                    window_s=node.cfg.restart.window_s,
                )
        else:
            node.state = "exited"
        node.due_at = 0.0
        self.wake.set()  # a restart may be due before the loop's next deadline

    def _on_line(self, name: str, line: str) -> None:
        relay(self.log, name, line)
        with contextlib.suppress(
            Exception
        ):  # a closed session at shutdown must not kill the reader thread
            self.session.put(self.msg.mgmt("log", name), line.encode())

    def _on_edge(self, edge: trigger.Edge) -> None:
        self.trigger_count += 1
        self.last_trigger_ns = edge.stamp_ns
        t = self.cfg.trigger
        rising = "rising" if edge.rising else "falling"
        payload = cdr.trigger_event(
            edge.stamp_ns, rising, t.chip, t.line, self.trigger_count, edge.source
        )
        self.pub_trigger.put(payload, edge.stamp_ns)
        self.log.info(
            "trigger",
            count=self.trigger_count,
            rising=edge.rising,
            source=edge.source,
            stamp_ns=edge.stamp_ns,
        )

    def described(self, node: NodeProcess) -> replies.NodeInfo:
        """A node as the API shows it: its own description and the requests it refused."""
        info = node.describe()
        if refused := self.node_api.get(node.name):
            info.api_refused = refused
        return info

    def _check_bus(self) -> None:
        if self.cfg.can.interface != "socketcan":
            return
        if self.link is None:
            self.link = canlink.LinkMonitor(self.cfg.can.channel)
        try:
            self.health = self.link.health()
        except canlink.CanLinkError as exc:
            self.health = canlink.LinkHealth("down")
            self.log.error("can_link_missing", error=str(exc))
        h = self.health
        if h.state == "bus-off" or (
            h.state == "error-passive" and self.cfg.watchdog.trip_on_bus_error_passive
        ):
            self.watchdog.trip(
                f"can {h.state}", f"{self.cfg.can.channel} tx errors {h.txerr}, rx errors {h.rxerr}"
            )

    def arm_blockers(self) -> list[str]:
        out = self.node_blockers()
        silent = self.watchdog.silent_for()
        limit = self.cfg.watchdog.silence_ms / 1000
        behind = self.watchdog.behind_s()
        if behind > limit:  # the bus may stream: the watchdog cannot see it in time
            out.append(
                f"the watchdog reads the bus {behind:.1f} s late (CPU saturated): it cannot "
                f"judge {self.device.pulse} silence"
            )
        elif silent is None or silent > limit:
            out.append(
                f"no {self.device.pulse} on the bus"
                if silent is None
                else f"no {self.device.pulse} for {silent:.1f} s"
            )
        if self.health is not None and self.health.bad:
            out.append(f"CAN bus is {self.health.state}")
        if self.update.installing:
            out.append("an update is being installed: the board reboots when it is in")
        return out

    def _mark_healthy(self) -> None:
        """The first armable state of this boot (every critical node beating, the bus seen):
        the root agent may now mark the booted slot good (exolink.board.update_agent). Until
        then a new slot is on trial and U-Boot falls back to the old one when its attempts run
        out."""
        if self._healthy_marked or self.arm_blockers():
            return
        self._healthy_marked = True
        try:
            self.update.mark_healthy()
        except OSError as exc:
            self.log.error("update_healthy_mark_failed", error=str(exc))

    def run(self) -> int:
        """The periodic checks, each when it is due: the loop sleeps until the nearest deadline
        (a heartbeat's, a restart's, a trip's repeat, ...), never longer than MAX_SLEEP_S, and
        another thread that moves a deadline closer wakes it. A 100 Hz tick cost the supervisor
        its largest share of one A8 core with nothing due."""
        next_state = time.monotonic()
        ping = self.notifier.ping_interval_s
        next_ping = next_stray = next_full = time.monotonic()
        while not self.stop_event.is_set():
            now = time.monotonic()
            self.watchdog.check()
            self._check_nodes(now)
            if now >= next_stray:
                next_stray = now + STRAY_SWEEP_S
                full = now >= next_full
                if full:
                    next_full = now + STRAY_FULL_SWEEP_S
                self._kill_strays(leader_only=not full)
            if now >= next_state:
                next_state = now + STATE_PERIOD_S
                self._publish_watchdog(self.watchdog.snapshot())
                self._publish_diagnostics()
                self.memory.check(now)
                self._mark_healthy()
            if ping and now >= next_ping:  # only a loop that runs keeps systemd's watchdog quiet
                next_ping = now + ping
                self.notifier.ping()
            if (took := time.monotonic() - now) > SLOW_LOOP_S:
                self.log.warning("supervisor_loop_slow", took_s=round(took, 3))
            due = min(
                self._next_due(now),
                next_state,
                next_ping if ping else next_state,
            )
            timers = {
                n.channel.timer: n
                for n in self.nodes.values()
                if n.channel is not None and n.state == "running"
            }
            _, ready = self.wake.wait_any(max(0.001, due - time.monotonic()), list(timers))
            for fd in ready:
                self._timer_ran_out(timers[fd], fd)
        return 0

    def _own_pids(self) -> set[int]:
        """The processes the supervisor watches: each node's current spawn and the ones being
        stopped, and the zygote."""
        pids = set()
        if self.zygote is not None:
            pids.add(self.zygote.proc.pid)
        for node in self.nodes.values():
            with node.lock:  # a spawn in progress holds it: its pid is known once it is free
                pids |= node.stopping_pids
                if node.proc is not None:
                    pids.add(node.proc.pid)
        return pids

    def _kill_strays(self, leader_only: bool = False) -> None:
        for pid, name in kill_strays(self._own_pids, leader_only):
            self.log.error(
                "stray_node_killed",
                pid=pid,
                process=name,
                why="a node process no node counts as its own: it ran unwatched",
            )

    def _link_loop(self) -> None:
        """The CAN link's state and error counters, off the safety loop: woken by the driver's
        error frame at a state change (a bus-off trips at once) and every HEALTH_PERIOD_S for
        the link's up/down (sysfs). A bus-off link also silences the H2, which the watchdog
        trips on within its silence limit anyway."""
        while not self.stop_event.is_set():
            link = self.link
            if link is None:
                self.stop_event.wait(HEALTH_PERIOD_S)
            else:
                link.wait(HEALTH_PERIOD_S)
            if not self.stop_event.is_set():
                self._check_bus()

    # --- shutdown ---------------------------------------------------------------------------

    def shutdown(self) -> None:
        """Safe action first, then the nodes, then the rest."""
        self.stopping = True
        self.notifier.stopping()
        if hasattr(self, "watchdog"):
            self.watchdog.trip("supervisor shutdown")
        threads = [threading.Thread(target=n.stop) for n in self.nodes.values()]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if (zygote := getattr(self, "zygote", None)) is not None:
            zygote.close()
        for src in (getattr(self, "trigger_src", None), getattr(self, "trigger_out", None)):
            if src is not None:
                src.close()
        if hasattr(self, "watchdog"):
            self.watchdog.close()
        if self.held is not None:
            self.held.close()
        for d in self._decls:
            with contextlib.suppress(Exception):
                d.undeclare()
        if hasattr(self, "ros2"):
            with contextlib.suppress(Exception):
                self.ros2.close()
        if hasattr(self, "msg"):
            self.msg.close()
        if hasattr(self, "session"):
            self.session.close()
        if hasattr(self, "bus"):
            self.bus.shutdown()
        if (link := getattr(self, "_link_thread", None)) is not None:
            link.join(2)
        if self.link is not None:
            self.link.close()
        shutil.rmtree(self._workdir, ignore_errors=True)
        self.log.info("supervisor_stopped")


def state_dir(cfg: ApplianceConfig, workdir: Path) -> str:
    """The config's state directory, else one in the supervisor's working directory."""
    return cfg.state_dir or str(workdir / "state")


def _config_data(cfg: ApplianceConfig, workdir: Path) -> dict[str, Any]:
    """The config the nodes read: the file's, with a state directory (the operator's limits)
    in the supervisor's working directory when the file names none."""
    data: dict[str, Any] = msgspec.to_builtins(cfg)
    data.pop("source", None)
    data["state_dir"] = state_dir(cfg, workdir)
    return data


def run(cfg: ApplianceConfig) -> int:
    """Blocking entry point of ``exolink up``."""
    sup = Supervisor(cfg)

    stop_on_signals(sup.stop_event, sup.log)
    try:
        sup.start()
        with profiled(SUPERVISOR):  # its loop, when EXOLINK_PROFILE_DIR says so
            return sup.run()
    finally:
        sup.shutdown()
