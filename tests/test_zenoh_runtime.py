"""``zenoh.threads``: every appliance process runs Zenoh on that many worker threads (the board
config: one, so a sample is not handed between threads on its single core), and the commands
whose handler queries another node from inside a queryable still answer."""

from __future__ import annotations

import os
from pathlib import Path

from benchmarks.harness import Appliance, wait_for
from exolink import messaging
from exolink.config import ZenohConfig


def _threads(pid: int) -> list[str]:
    task = Path(f"/proc/{pid}/task")
    return sorted((task / t / "comm").read_text().strip() for t in os.listdir(task))


def test_the_setting_goes_into_the_environment_unless_the_operator_set_one() -> None:
    env: dict[str, str] = {}
    assert messaging.zenoh_runtime(ZenohConfig(), env) is None and env == {}
    one = messaging.zenoh_runtime(ZenohConfig(threads=1), env)
    assert one == env["ZENOH_RUNTIME"]
    assert "app: (worker_threads: 1)" in one and one.count("handover: app") == 4
    own = {"ZENOH_RUNTIME": "(app: (worker_threads: 3))"}
    assert messaging.zenoh_runtime(ZenohConfig(threads=1), own) == "(app: (worker_threads: 3))"


def test_the_router_transmits_on_its_own_thread_while_it_opens() -> None:
    env: dict[str, str] = {}
    nodes = messaging.zenoh_runtime(ZenohConfig(threads=1), env)
    with messaging.router_runtime(ZenohConfig(threads=1), env) as router:
        assert router == env["ZENOH_RUNTIME"] and "tx: (worker_threads: 1)" in router
        assert "tx: (handover: app)" not in router
    assert env["ZENOH_RUNTIME"] == nodes  # the nodes spawned afterwards: one thread
    own = {"ZENOH_RUNTIME": "(app: (worker_threads: 3))"}
    with messaging.router_runtime(ZenohConfig(threads=1), own) as router:
        assert router == "(app: (worker_threads: 3))"  # an operator's own is left alone


def test_one_zenoh_thread_per_process_and_nested_commands_answer(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    env_before = os.environ.get("ZENOH_RUNTIME")
    app = Appliance(write_config(zenoh={"threads": 1}), spawn)
    assert os.environ.get("ZENOH_RUNTIME") == env_before  # set in the supervisor, not here
    sup = app.proc.p.pid
    manager = app.node("controller_manager")["pid"]
    for pid, tx in ((sup, ["tx-0"]), (manager, [])):  # the router transmits on a thread of its own
        names = _threads(pid)
        assert "app-0" in names and not [n for n in names if n.startswith("rx-")], names
        assert [n for n in names if n.startswith("tx-")] == tx, names
    app.arm_and_hold()
    # a command that waits for the manager's cycle (a switch) answers
    r = app.cli("send", "position", "l_ankle", "5")
    assert r.returncode == 0 and "held by controller operator.l_ankle.position" in r.stdout, r
    # the player asks the manager to load and activate the gait's trajectory controller
    assert app.cli("pattern", "start", "--detach").returncode == 0
    wait_for(lambda: "running" in app.cli("pattern", "status").stdout, timeout=10)
    # a query larger than the router's transmit queue (2 x 64 KB) to a node: it was lost and
    # stalled the router 5 s when the router's one thread also had to transmit it
    s = messaging.open_client_session(app.at)
    try:
        for size in (100_000, 1_000_000):
            body = {"action": "list", "pad": "x" * size}
            assert messaging.request(s, "exolink/sim/controllers", body, 10)["ok"]
    finally:
        s.close()
