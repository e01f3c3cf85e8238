"""The safety path against hostile clients, across real processes on simulated hardware: an
e-stop from one client reaches the bus (disable frames seen by an independent listener) while
other clients stop reading, flood queries or send large ones; large requests cross the router;
junk is refused cleanly and leaves the logs and the supervisor's memory bounded.

The hostile clients are real processes with real Zenoh sessions (SIGSTOP makes one stop
reading). The bounds here are generous (2 s against the 5-15 s these cases took before);
benchmarks/bench_netsafety.py measures the latencies themselves."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest
import structlog
import yaml
from test_roles import board_logins

from benchmarks.harness import Appliance, motion_nodes, wait_for
from exolink import messaging, roles
from exolink.config import NodeConfig, bundled
from exolink.protocol import h2
from exolink.supervisor import processes

NODES = motion_nodes()  # as shipped
BOUND_S = 2.0  # an e-stop's way to the bus took 5-15 s beside these clients before

# A client that queues ``count`` status queries, says so, and then waits to be SIGSTOPped.
STALL = """
import sys, time
from exolink import messaging
session = messaging.open_client_session(sys.argv[1], handshake_s=20)
for _ in range(int(sys.argv[3])):
    session.get(sys.argv[2], lambda _r: None, payload=b"{}", timeout=60)
print("sent", flush=True)
time.sleep(3600)
"""
# A client that keeps 1000 queries in flight (status, logs, control in turn) until killed.
FLOOD = """
import json, sys, threading, zenoh
from exolink import messaging
session = messaging.open_client_session(sys.argv[1], handshake_s=20)
bodies = [("status", {}), ("logs", {"node": "simulator", "lines": 500}),
          ("control", {"node": "none", "action": "restart"})]
slots = threading.Semaphore(1000)
print("flooding", flush=True)
n = 0
while True:
    slots.acquire()
    path, body = bodies[n % 3]
    session.get(f"{sys.argv[2]}/{path}/admin", zenoh.handlers.Callback(lambda _r: None,
                slots.release), payload=json.dumps(body).encode(), timeout=5)
    n += 1
"""


@pytest.fixture
def app(write_config, spawn):  # type: ignore[no-untyped-def]
    """The whole sim appliance (every node: status replies of their real size)."""
    return Appliance(write_config(), spawn)


@contextmanager
def hostile(code: str, *args: str, count: int = 1) -> Iterator[list[subprocess.Popen[str]]]:
    """``count`` client processes running ``code``, each having said its first line."""
    procs = [
        subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, text=True)
        for _ in range(count)
    ]
    try:
        for p in procs:
            assert p.stdout is not None and p.stdout.readline(), "hostile client did not start"
        yield procs
    finally:
        for p in procs:
            p.send_signal(signal.SIGCONT)
            p.kill()
            p.wait()


def estop_to_bus_s(session: Any, mbus: Any) -> float:
    """Seconds from an e-stop query's send (on a session opened before any abuse) to the first
    disable frame on the bus."""
    while mbus.recv(timeout=0) is not None:
        pass
    t0 = time.time()
    session.get("exolink/sim/watchdog/admin", lambda _r: None, payload=b'{"action": "estop"}')
    end = time.monotonic() + 30
    while time.monotonic() < end:
        m = mbus.recv(timeout=0.5)
        f = h2.decode(m) if m is not None else None
        if isinstance(f, h2.JointControl) and f.mode == 4 and m.timestamp >= t0:
            return float(m.timestamp - t0)
    return float("inf")


@pytest.fixture
def laptop(app) -> Iterator[Any]:  # type: ignore[no-untyped-def]
    """A client session opened before any abuse starts (the e-stop's)."""
    session = messaging.open_client_session(app.at)
    yield session
    session.close()


def rss_mb(app: Appliance) -> float:
    """The supervisor's resident size, as /proc says."""
    with open(f"/proc/{app.proc.p.pid}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_an_estop_reaches_the_bus_while_clients_stop_reading(app, laptop, mbus) -> None:  # type: ignore[no-untyped-def]
    """Three clients queue 3000 status queries each and stop reading: the router drops what
    they do not read instead of waiting 5 s on each (12 s before); the watchdog's word still
    reaches the nodes; the supervisor's memory comes back."""
    start_mb = rss_mb(app)
    status = messaging.mgmt_key("sim", "status", roles.OBSERVER)
    with hostile(STALL, app.at, status, "3000", count=3) as stalled:
        for p in stalled:
            p.send_signal(signal.SIGSTOP)
        stopped = time.monotonic()
        time.sleep(0.3)  # their replies fill what they no longer read
        assert estop_to_bus_s(laptop, mbus) < BOUND_S
        time.sleep(max(0.0, stopped + 4 - time.monotonic()))  # past the nodes' 3 s staleness
        word = app.cli("controllers", "list", "--json")
        assert word.returncode == 0, word.stderr
        # the manager's view of the watchdog was never older than its 3 s staleness
        assert json.loads(word.stdout)["watchdog_word"]["max_gap_s"] < 3.0
    wait_for(lambda: rss_mb(app) < start_mb + 16, timeout=30, step=1)


def test_an_estop_reaches_the_bus_during_a_query_flood(app, laptop, mbus) -> None:  # type: ignore[no-untyped-def]
    """Three clients keep 1000 queries each in flight (5-14 s before); the flood's excess is
    refused by rate, counted, and an observer is still answered."""
    with hostile(FLOOD, app.at, messaging.mgmt_key("sim"), count=3):
        time.sleep(1)
        assert estop_to_bus_s(laptop, mbus) < BOUND_S
        reply = messaging.request(laptop, "exolink/sim/status", {}, 5, roles.OBSERVER)
        assert reply["ok"] and reply["api"]["rate"] > 0, reply.get("api")


def test_large_queries_cross_the_router_and_oversized_ones_are_refused(app, laptop, mbus) -> None:  # type: ignore[no-untyped-def]
    """A query to a node larger than the router's transmit queue (2 x 64 KB) was lost and
    held every client 5 s; now an e-stop beside one goes at once, and each size up to the
    login's limit is answered. Over it: a refusal that says the limit, not the request."""
    s = messaging.open_client_session(app.at)
    try:
        big = json.dumps({"action": "x" * 100_000}).encode()
        s.get("exolink/sim/controllers/admin", lambda _r: None, payload=big)
        assert estop_to_bus_s(laptop, mbus) < BOUND_S
        for size in (100_000, 1_000_000):
            body = {"action": "list", "pad": "x" * size}
            reply = messaging.request(s, "exolink/sim/controllers", body, 10, roles.ADMIN)
            assert reply["ok"], reply  # the manager's whole answer
        over = json.dumps({"action": "list", "pad": "x" * 3_000_000}).encode()
        (r,) = list(s.get("exolink/sim/controllers/admin", payload=over, timeout=10))
        error = json.loads(r.ok.payload.to_bytes())["error"]
        assert error == f"request of {len(over)} bytes refused: the admin login may send 2097152"
        small = json.dumps({"action": "list", "pad": "x" * 5000}).encode()
        (r,) = list(s.get("exolink/sim/controllers/observer", payload=small, timeout=10))
        assert "the observer login may send 4096" in json.loads(r.ok.payload.to_bytes())["error"]
        with pytest.raises(messaging.RequestTooLarge, match="not sent"):
            messaging.request(s, "exolink/sim/status", {"pad": "x" * 5000}, 5, roles.OBSERVER)
    finally:
        s.close()

    def manager_refused() -> dict[str, int]:
        (n,) = [n for n in app.status()["nodes"] if n["name"] == "controller_manager"]
        return n.get("api_refused", {})  # type: ignore[no-any-return]

    wait_for(lambda: manager_refused().get("too_large") == 2, timeout=10)  # in exolink status


def test_a_pattern_of_10000_rows_loads_and_starts_end_to_end(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """exolink pattern load of a 10,000-row CSV (160 KB) and start: the player hands every
    row to the manager as JSON. An 8000-row one was "appliance unreachable" before."""
    rows = ["r_hip,r_knee,r_ankle,l_hip,l_knee,l_ankle"]
    rows += [f"{i % 40 - 20},{i % 50 + 5},0,{20 - i % 40},{55 - i % 50},0" for i in range(10_000)]
    csv = tmp_path / "long.csv"
    csv.write_text("\n".join(rows) + "\n")
    nodes = [
        n
        for n in yaml.safe_load(bundled("sim").read_text())["nodes"]
        if n["name"] not in ("recorder", "timing_monitor", "maccepa_bridge")
    ]
    app = Appliance(write_config(nodes=nodes), spawn)
    r = app.cli("pattern", "load", str(csv))
    assert r.returncode == 0 and "0/10000" in r.stdout, (r.stdout, r.stderr)
    app.arm_and_hold()
    # its saw-tooth jumps 39 deg from its last row to its first: only speed 1 keeps that
    # inside the step limit (the manager checks the whole sequence at the speed it runs)
    r = app.cli("pattern", "start", "--detach")
    assert r.returncode == 5 and "choose a lower speed" in r.stderr, r.stderr
    assert app.cli("pattern", "speed", "1").returncode == 0
    r = app.cli("pattern", "start", "--detach")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: "running" in app.cli("pattern", "status").stdout, timeout=10)
    assert app.cli("pattern", "stop").returncode == 0


def test_the_estop_names_the_login_zenoh_proved(write_config, spawn, tmp_path) -> None:  # type: ignore[no-untyped-def]
    """On a board with logins: the e-stop's detail and the command log say ``observer``, never
    the laptop's $USER (text the client chose)."""
    board_file, logins = board_logins(tmp_path)
    cfg = write_config(nodes=NODES[:2], zenoh={"config_file": str(board_file)})
    app = Appliance(cfg, spawn, login=logins[roles.ADMIN])
    env = {**os.environ, "USER": "mallory"}
    r = subprocess.run(
        [*app_cli(app), "estop", "--zenoh-config", str(logins[roles.OBSERVER])],
        capture_output=True,
        text=True,
        env=env,
        timeout=30,
    )
    assert r.returncode == 0 and "operator e-stop: by observer" in r.stdout, (r.stdout, r.stderr)
    wd = app.status()["watchdog"]
    assert (wd["reason"], wd["detail"]) == ("operator e-stop", "by observer")
    assert "mallory" not in app.proc.output()


def app_cli(app: Appliance) -> list[str]:
    return [sys.executable, "-m", "exolink.cli.main", "--at", app.at, "--timeout", "10"]


def test_junk_is_refused_cleanly_and_the_log_stays_small(app) -> None:  # type: ignore[no-untyped-def]
    """A JSON list raised AttributeError after the reply (4461 tracebacks in a flood); a 1 MB
    action was echoed into the error and the command log (21 MB for 20 of them)."""
    s = messaging.open_client_session(app.at)
    try:

        def ask(login: str, payload: bytes) -> dict[str, Any]:
            (r,) = list(s.get(f"exolink/sim/watchdog/{login}", payload=payload, timeout=10))
            return json.loads(r.ok.payload.to_bytes())  # type: ignore[no-any-return]

        assert ask("admin", b"[1, 2]")["error"] == "request must be a JSON object, not a list"
        time.sleep(0.5)
        before = app.proc.log.stat().st_size
        action = json.dumps({"action": "z" * 1_000_000}).encode()
        for login in ["admin"] * 10 + ["observer"] * 10:
            reply = ask(login, action)
            assert not reply["ok"] and len(reply["error"]) < 400, reply["error"][:400]
        time.sleep(0.5)
        assert app.proc.log.stat().st_size - before < 20_000
    finally:
        s.close()
    assert "Traceback" not in app.proc.output()


def test_a_nodes_output_is_kept_in_bounded_lines_at_a_bounded_rate() -> None:
    """A node's 1 MB line and a burst of 5000 lines: what the supervisor keeps and relays is
    cut (LOG_LINE_BYTES) and rate-limited, with the dropped lines counted."""
    relayed: list[str] = []
    node = processes.NodeProcess(
        NodeConfig(name="noisy", plugin="h2_reader"),
        "",
        lambda _e: None,
        lambda _n, line: relayed.append(line),
    )
    code = "print('x' * 1_000_000, flush=True)\nfor i in range(5000): print(i)\nprint('last')"
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    t0 = time.monotonic()
    node._read(proc)  # type: ignore[arg-type]
    took = time.monotonic() - t0
    proc.wait()
    assert max(len(line) for line in relayed) < 5000  # 4 KiB and the note that it was cut
    assert relayed[0].endswith("(line cut at 4096 bytes)")
    assert len(relayed) < 500 + 100 * took + 10  # the burst, then 100 a second (5002 before)
    assert any(line.endswith("dropped (over 100 a second)") for line in relayed)
    assert list(node.logs) == relayed[-processes.LOG_LINES :]


def test_unreadable_samples_are_counted_in_bounded_kinds() -> None:
    """Each error text an attacker makes (and the node names in keys) was a key of its own."""
    from exolink.config import parse
    from exolink.supervisor import core, telemetry

    sup = core.Supervisor(parse(bundled("sim").read_text(), "sim.yaml"))
    with structlog.testing.capture_logs():
        for i in range(1000):
            sup._bad_sample("pattern_state", ValueError(f"garbled {i} " + "y" * 10_000))
    assert len(sup.bad_samples) == telemetry.BAD_SAMPLE_KINDS + 1
    assert sup.bad_samples[telemetry.BAD_SAMPLE_OTHER] == 1000 - telemetry.BAD_SAMPLE_KINDS
    assert max(len(k) for k in sup.bad_samples) < telemetry.BAD_SAMPLE_CHARS + 30


def test_a_logins_rate_is_a_token_bucket() -> None:
    """A burst passes, then one request per 1/rate; each login has its own bucket."""
    adm = messaging.Admission(rate=10.0, burst=5)
    assert [adm.allow("observer") for _ in range(6)] == [True] * 5 + [False]
    assert adm.allow("operator")
    time.sleep(0.15)
    assert adm.allow("observer") and not adm.allow("observer")


def test_handlers_get_the_caller_when_they_take_one() -> None:
    def plain(_req: dict[str, Any]) -> None: ...
    def with_caller(_req: dict[str, Any], _caller: messaging.Caller) -> None: ...

    assert not messaging.takes_caller(plain) and messaging.takes_caller(with_caller)
    assert not messaging.takes_caller(lambda _r: None)


def test_the_command_log_keeps_a_bounded_summary() -> None:
    request = {f"k{i}": "v" * 1000 for i in range(100)} | {"content": "c" * 10_000}
    text = json.dumps(messaging.rpc._summary(request))
    assert len(text) < 6000 and "81 more fields" in text
    assert messaging.clip("a" * 1000, 10) == "aaaaaaaaaa... (1000 chars)"


def test_the_router_config_bounds_messages_and_never_blocks() -> None:
    cfg = messaging.session_config(bundled_zenoh(), mode="router")
    data, requests = json.loads(cfg.get_json("qos/network"))
    assert data["messages"] == ["put", "delete"] and requests["messages"] == ["query"]
    for rule in (data, requests):  # nothing a client sends may block the router
        assert rule["flows"] == ["ingress"] and rule["overwrite"]["congestion_control"] == "drop"
    assert requests["overwrite"]["priority"] == "interactive_high"  # ahead of the data
    size = json.loads(cfg.get_json("transport/link/rx/max_message_size"))
    assert size == messaging.MAX_MESSAGE_BYTES > max(roles.MAX_REQUEST_BYTES.values())


def bundled_zenoh() -> Any:
    from exolink.config import parse

    return parse(bundled("sim").read_text(), "sim.yaml").zenoh
