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


def _sockets(pid: int) -> set[int]:
    """The inodes of a process's sockets."""
    fds = Path(f"/proc/{pid}/fd")
    links = (os.readlink(fds / fd) for fd in os.listdir(fds))
    return {int(x[8:-1]) for x in links if x.startswith("socket:[")}


def _tcp_remote_ports(pid: int) -> dict[int, int]:
    """socket inode -> remote port, of the TCP sockets in the process's network namespace."""
    out: dict[int, int] = {}
    for name in ("tcp", "tcp6"):
        for line in Path(f"/proc/{pid}/net/{name}").read_text().splitlines()[1:]:
            f = line.split()
            out[int(f[9])] = int(f[2].rsplit(":", 1)[1], 16)
    return out


def _unix_paths(pid: int) -> dict[int, str]:
    """socket inode -> path, of the unix sockets bound to or accepted on a path."""
    rows = (ln.split() for ln in Path(f"/proc/{pid}/net/unix").read_text().splitlines()[1:])
    return {int(f[6]): f[7] for f in rows if len(f) > 7}


def test_node_link_unix_or_tcp(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    at = messaging.node_link(ZenohConfig(), tmp_path, env)
    assert at == f"unixsock-stream/{tmp_path}/router.sock" == env["EXOLINK_NODE_LINK"]
    assert messaging.node_link(ZenohConfig(node_link="tcp"), tmp_path, env) is None and env == {}


def test_nodes_reach_the_router_on_a_unix_socket_in_the_supervisors_own_directory(
    write_config, spawn
) -> None:  # type: ignore[no-untyped-def]
    """Each node's session is on the node link: no TCP connection of a node to the router's
    port, one accepted unix connection per node on the router's socket, in a directory only
    the appliance's user may enter."""
    app = Appliance(write_config(), spawn)
    port = int(app.at.rsplit(":", 1)[1])
    sup = app.proc.p.pid
    pids = [n["pid"] for n in app.call("status")["nodes"] if n.get("pid")]
    assert pids
    tcp = _tcp_remote_ports(sup)
    for pid in pids:
        assert [i for i in _sockets(pid) if tcp.get(i) == port] == [], pid
    paths = _unix_paths(sup)
    on_link = [paths[i] for i in _sockets(sup) if paths.get(i, "").endswith("/router.sock")]
    assert len(on_link) >= len(pids) + 1, on_link  # the listener and an accepted one per node
    assert Path(on_link[0]).parent.stat().st_mode & 0o077 == 0


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
