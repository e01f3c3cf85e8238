"""One bench run: the guest (the card under qemu) or native (the same load on this host)."""

from __future__ import annotations

import base64
import contextlib
import hashlib
import itertools
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import structlog
import yaml

from benchmarks.board import card as cardlib
from benchmarks.board import kernelwork, profile, scenario, setpoints
from benchmarks.board import ladder as ladderlib
from benchmarks.board import timeline as timelinelib
from benchmarks.board.guest import MAIN, CoreSampler, Guest, ran_pct
from benchmarks.harness import free_port
from exolink import messaging
from exolink.config import bundled
from exolink.protocol import h2

log = structlog.get_logger("bench-board")

PROBE = Path(__file__).with_name("probe.py")
GUEST_PROBE = "/run/exolink-probe.py"
TIMELINE = Path(__file__).with_name("timeline.py")
GUEST_TIMELINE = "/run/exolink-timeline.py"
UNITS = Path(__file__).with_name("units.py")
ESTOP = Path(__file__).parents[1] / "estop.py"
GUEST_ESTOP, GUEST_LOGIN = "/run/exolink-estop.py", "/run/exolink-estop-login.json5"
ESTOP_TRIALS = 20
UNITS_SECONDS = 10.0
DEVICE = "exo-01"
SETTLE_S = 10.0
UNCAPPED_PCT = 200  # a quota of the guest's 2 CPUs: no limit
LOG_PATTERNS = (
    r"loop_stalled|node_hung_killed|node_exited|watchdog_trip|tripped|Watchdog timeout|Failed with"
)


def stalls(log: str) -> int:
    """Loop stalls in a log: each logged one plus those it says went unlogged (the runtime logs
    at most one per node per 10 s)."""
    hidden = sum(int(n) for n in re.findall(r'"stalls_not_logged": (\d+)', log))
    return log.count("loop_stalled") + hidden


def _connect(at: str, zenoh_config: str | None, timeout: float, alive: Any) -> scenario.Laptop:
    deadline = time.monotonic() + timeout
    while True:
        try:
            return scenario.Laptop(at, zenoh_config, DEVICE)
        except messaging.Unreachable:
            if time.monotonic() > deadline or not alive():
                raise
            time.sleep(3)


def _run_load(
    laptop: scenario.Laptop,
    probe_cmd: list[str],
    seconds: float,
    profiler: list[str] | None = None,
    jit: Callable[[], dict[str, Any]] | None = None,
    fetch: str | None = None,
    work: Path | None = None,
    core_cpu: Callable[[], float | None] | None = None,
    cap: Callable[[], dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """Arm, the pattern held, settle, then the window measured by the probe and the laptop
    (and ``fetch``, a recording on the card, fetched into ``work`` from the window's start).
    ``cap``: the service's quota set once the probe is ready, SETTLE_S before the arm.

    The probe starts and calibrates before the arm and waits (``--go``): on the proxy its
    interpreter's start and calibration take seconds of CPU 1, where the simulated H2 streams,
    and the runs that did that at the window's start tripped the watchdog on H2 silence there.
    A pattern that is not running when the window would start (refused arm, or a trip while
    settling) is recorded and tried once more, so the window carries the load if it can."""
    probe = subprocess.Popen(
        [*probe_cmd, "--go"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        return _load_window(laptop, probe, seconds, profiler, jit, fetch, work, core_cpu, cap)
    finally:
        if probe.poll() is None:
            probe.kill()


def _load_window(
    laptop: scenario.Laptop,
    probe: subprocess.Popen[str],
    seconds: float,
    profiler: list[str] | None,
    jit: Callable[[], dict[str, Any]] | None,
    fetch: str | None = None,
    work: Path | None = None,
    core_cpu: Callable[[], float | None] | None = None,
    cap: Callable[[], dict[str, Any]] | None = None,
) -> dict[str, Any]:
    assert probe.stdin is not None and probe.stdout is not None
    out: dict[str, Any] = {}
    for line in probe.stdout:
        if line.startswith("PROBE_READY"):
            break
    else:
        out["window"] = {"error": f"the probe ended before it was ready (rc {probe.wait()})"}
        return out
    # Read before the load and after it, not at the window's edges: the monitor's `info jit`
    # walks every translated block holding QEMU's global lock, a stall of the whole guest
    # (the watchdog tripped on H2 silence at a window's start when it was read there).
    log.info("probe ready: reading qemu's jit counters")
    jit0 = jit() if jit is not None else {}
    log.info("jit read")
    if cap is not None:
        # After that read, not before: it held the vCPU 0.8 s (H67: the host ran it 0-3 %,
        # never waiting for a core), the cgroup that was running was charged the stall, and
        # under the cap that debt held every node at zero CPU with CPU 0 idle (0 usage, 37 of
        # 37 periods throttled): hung-kills before the arm in M65, C66, E66, M66, G67, H67.
        # A bench artifact the cap tripled, not the load's.
        time.sleep(SETTLE_S / 2)
        out["cpu_quota_set"] = cap()
        time.sleep(SETTLE_S)
    log.info("arming")
    out["operator"] = laptop.arm_and_start_pattern()
    log.info("pattern started", armed=out["operator"].get("armed"))
    time.sleep(SETTLE_S)
    if not _pattern_running(laptop):
        out["first_attempt"] = {
            **out["operator"],
            "held_pattern_cli": laptop.stop_pattern(),
            "status": _safe_status(laptop),
        }
        log.warning("pattern not running before the window: arming once more")
        out["operator"] = laptop.arm_and_start_pattern()
        time.sleep(SETTLE_S)
    out["pattern_running_at_start"] = _pattern_running(laptop)
    log.info("measuring", seconds=seconds)
    probe.stdin.write("go\n")
    probe.stdin.flush()
    prof = _start_profiler(profiler)
    fetching = None
    if fetch is not None and work is not None:
        fetching = (laptop.fetch(fetch, work / "fetched"), time.monotonic())
    cpu0 = (core_cpu() if core_cpu else None, time.monotonic())
    try:
        out["window"] = scenario.measure(laptop, probe, seconds)
        cpu1 = (core_cpu() if core_cpu else None, time.monotonic())
        if cpu0[0] is not None and cpu1[0] is not None:  # the host's CPU for the board's vCPU
            out["host_core_pct"] = round(100 * (cpu1[0] - cpu0[0]) / (cpu1[1] - cpu0[1]), 1)
    finally:
        _end_profiler(prof, out)
        if fetching is not None:
            out["fetch"] = _fetched(*fetching, work / "fetched" / fetch)  # type: ignore[operator]
    log.info("window over: stopping the pattern")
    out["held_pattern_cli"] = laptop.stop_pattern()
    log.info("pattern stopped: disarming")
    # The trial is over: disarmed, as an operator ends one.
    disarm = laptop.cli("disarm")
    out["disarmed"] = disarm.returncode == 0 or (disarm.stdout + disarm.stderr).strip()
    # The monitor's `info jit` stalls the whole guest (QEMU's global lock): armed, that was a
    # trip on the H2's silence after a clean stop (F65); disarmed, still a hung-kill of the h2
    # reader 4 s after it (C67: the host ran the vCPU 15 % of 0.6 s the guest called 58 %
    # busy). So the second read comes once the service is stopped (run_guest).
    out["qemu_jit_before"] = jit0
    out["derived"] = scenario.derived(out["window"])
    return out


def _stage_recording(guest: Guest, work: Path, mb: int, result: dict[str, Any]) -> str:
    """A closed recording of ``mb`` MiB, as the recorder writes them, put in its directory on
    the card (before the load: the copy over ssh costs the guest CPU). Its name."""
    from benchmarks.bench_recorder import joint_states, write

    name = f"bench_fetch_{mb}mib.mcap"
    local = work / name
    if not local.exists():
        write(local, joint_states(), mb * 2**20 // 180, "none")
    remote = f"/var/lib/exolink/recordings/{name}"
    t = time.monotonic()
    guest.upload(local, remote)
    guest.ssh(f"chown exolink:exolink {remote} && chmod 0640 {remote}")
    result["fetch_staged"] = {
        "name": name,
        "bytes": local.stat().st_size,
        "sha256": _sha256(local),
        "upload_s": round(time.monotonic() - t, 1),
    }
    return name


def _fetched(proc: subprocess.Popen[str], t0: float, path: Path) -> dict[str, Any]:
    """The laptop's fetch, waited for after the window: its exit, time and the file's sha256."""
    try:
        output, _ = proc.communicate(timeout=600)
    except subprocess.TimeoutExpired:
        proc.kill()
        output, _ = proc.communicate()
    out: dict[str, Any] = {
        "rc": proc.returncode,
        "seconds": round(time.monotonic() - t0, 1),
        "output": output.strip()[-600:],
    }
    if path.exists():
        out["bytes"], out["sha256"] = path.stat().st_size, _sha256(path)
    return out


def _jit_window(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """TCG's code-buffer flushes from the arm to the pattern's stop, the window among them
    (each stalls the whole guest: a trip then is the emulator's, see guest.py)."""
    out = {"before": before, "after": after}
    if "flushes" in before and "flushes" in after:
        out["flushes_under_load"] = after["flushes"] - before["flushes"]
    return out


def _start_profiler(cmd: list[str] | None) -> subprocess.Popen[str] | None:
    if cmd is None:
        return None
    log.info("profiling the window", cmd=" ".join(cmd[-1:]))
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _end_profiler(prof: subprocess.Popen[str] | None, out: dict[str, Any]) -> None:
    if prof is None:
        return
    try:
        text, _ = prof.communicate(timeout=600)  # it writes only when done sampling
    except subprocess.TimeoutExpired:
        prof.kill()
        text, _ = prof.communicate()
    out["profiler_rc"] = prof.returncode
    out["profiler_output"] = text[-2000:]


def _pattern_running(laptop: scenario.Laptop) -> bool:
    try:
        return bool(laptop.call("pattern", body={"action": "status"}).get("state") == "running")
    except messaging.Unreachable:
        return False


def _safe_status(laptop: scenario.Laptop) -> dict[str, Any]:
    try:
        st = laptop.call("status", timeout=15)
    except messaging.Unreachable as exc:
        return {"error": str(exc)}
    return {"watchdog": st.get("watchdog"), "bus": st.get("bus")}


def run_guest(
    repo: Path,
    image: Path,
    work: Path,
    seconds: float,
    start_grace_ms: int,
    boot_timeout: float,
    timings: str,
    journal_console: bool = False,
    py_spy: Path | None = None,
    ladder: tuple[str, ...] | None = None,
    env: tuple[str, ...] = (),
    without: tuple[str, ...] = (),
    cprofile: tuple[str, ...] = (),
    cpu_quota: int | None = None,
    estop: bool = False,
    fetch_mb: int = 0,
    cap_after_start: bool = False,
    timeline: bool = False,
    own_core: bool = False,
    kernel_work: bool = False,
) -> dict[str, Any]:
    """``ladder``: the nodes to step through (empty: every one; None: the nominal load
    instead); ``env``: KEY=VALUE for the appliance's service on the guest; ``cprofile``: these
    nodes' loops under cProfile (exolink.runtime.profiled), fetched when the service stops;
    ``cpu_quota``: the service capped at this % of a CPU (cardlib.prepare); ``estop``: after the
    window, e-stop -> first disable frame in the guest, beside hostile clients on this host;
    ``fetch_mb``: a closed recording of this size on the card, fetched by the laptop's
    ``exolink record fetch`` from the window's start; ``cap_after_start``: the quota set once
    every node beats and SETTLE_S more (``_cap_now``), so the start is not under it, the arm
    and the gait's start are;
    ``timeline``: CPU per thread every 0.25 s from then to the end (timeline.py);
    ``own_core``: the board's vCPU on a host core of its own at nice -20 (guest.py);
    ``kernel_work``: the guest's workqueue items traced from then to the end (kernelwork.py)."""
    if cprofile:
        env = (
            *env,
            f"EXOLINK_PROFILE_DIR={GUEST_CPROFILE}",
            f"EXOLINK_PROFILE_NODES={','.join(cprofile)}",
        )
    result: dict[str, Any] = {"kind": "guest", "image": str(image), "notes": [], "env": env}
    wheel = cardlib.build_wheel(repo, work / "wheel")
    result["wheel"] = {"file": wheel.name, "sha256": _sha256(wheel)}
    key = work / "ssh_key"
    for old in (key, key.with_suffix(".pub")):
        old.unlink(missing_ok=True)
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(key)], check=True)
    password = secrets.token_urlsafe(12)
    card, cfg = cardlib.prepare(
        image,
        work,
        wheel,
        key.with_suffix(".pub").read_text().strip(),
        password,
        start_grace_ms,
        timings,
        (py_spy,) if py_spy else (),
        env,
        without,
        # Set later (_cap_now): from boot, a quota no larger than the guest's two CPUs, so
        # systemd enables the cgroup's cpu controller and its cpu.max is there to write.
        UNCAPPED_PCT if cpu_quota and cap_after_start else cpu_quota,
    )
    result["config"] = cfg
    result["cpu_quota_pct"] = cpu_quota
    laptop_cfg = work / "exolink-operator.json5"
    admin = ladder is not None
    user, pw = ("admin", cardlib.admin_password(password)) if admin else ("operator", password)
    login = {"transport": {"auth": {"usrpwd": {"user": user, "password": pw}}}}
    laptop_cfg.write_text(json.dumps(login) + "\n")
    guest = Guest(card, work, key, journal_console, own_core=own_core)
    result["qemu_command"] = " ".join(guest.cmd)
    console = guest.start()
    result["host_core"] = guest.core
    sampler = guest.core_sampler()
    laptop = None
    try:
        try:
            laptop = _connect(guest.at, str(laptop_cfg), boot_timeout, guest.alive)
        except messaging.Unreachable as exc:
            # What the guest itself shows (CPU, PSS, restarts, journal) is still measured.
            result["laptop_error"] = f"the laptop never connected ({boot_timeout:g} s): {exc}"
            log.error("laptop cannot connect: measuring the guest without it", error=str(exc))
        boot_s = time.monotonic() - guest.t0
        result["boot"] = {
            "bench_prep_done_s": console.first(r"exolink-bench: ready"),
            "supervisor_started_s": console.first(r"Started exolink\.service"),
        }
        if laptop is not None:
            status, ok = laptop.wait_beating(boot_timeout, scenario.enabled_nodes(cfg))
            boot_s = time.monotonic() - guest.t0
            if status is None:
                result["laptop_error"] = f"the supervisor never answered within {boot_timeout:g} s"
            else:
                if not ok:
                    result["notes"].append(_not_beating(status, boot_timeout))
                result["boot"] |= {
                    "all_nodes_beating_s": round(boot_s, 1) if ok else None,
                    "resolution_s": 2.0,
                    "node_start_s": {n["name"]: n["start_s"] for n in status["nodes"]},
                }
        installed = guest.ssh("cat /run/exolink-bench-installed; nproc; uname -r")
        result["boot"]["supervisor_restarts_by_systemd"] = _nrestarts(guest)
        result["installed"] = installed.stdout.strip() or installed.stderr.strip()
        if result["wheel"]["sha256"] not in result["installed"]:
            result["notes"].append("the checkout's wheel is NOT what the guest installed")
        log.info("nodes", laptop=laptop is not None, boot_s=round(boot_s, 1))
        if cpu_quota:
            result["simulator_cgroup"] = _simulator_out_of_the_quota(guest)
        if timeline:
            guest.upload(TIMELINE, GUEST_TIMELINE)
            guest.ssh(
                f"nohup taskset -c 1 python3 {GUEST_TIMELINE} --out {GUEST_TIMELINE}l "
                ">/dev/null 2>&1 &"
            )
        if kernel_work:
            armed = guest.ssh(kernelwork.arm_command())
            if armed.returncode != 0:
                result["notes"].append(f"kernel work not traced: {armed.stderr.strip()[-200:]}")
        fetch = _stage_recording(guest, work, fetch_mb, result) if fetch_mb else None
        time.sleep(SETTLE_S)
        loaded = laptop is not None and "laptop_error" not in result and ladder is None
        if cpu_quota and cap_after_start and not loaded:
            # Once the nodes' first seconds are over: set as the last node beat, the cap caught
            # the pattern player and the manager still settling (B63: 1.1 and 0.4 s stalls, two
            # hung-kills before any load), which is the start's budget, not the load's.
            result["cpu_quota_set"] = _cap_now(guest, cpu_quota)

        guest.upload(PROBE, GUEST_PROBE)
        log.info("probe uploaded")

        def guest_probe(secs: float, nodes: list[str]) -> list[str]:
            return guest.ssh_cmd(
                f"taskset -c 1 python3 {GUEST_PROBE} --unit exolink.service --seconds {secs:g} "
                f"--frames {h2.JOINT_CONTROL} "
                f"--channel vcan0 --nodes {','.join(nodes)}"
            )

        probe_cmd = guest_probe(seconds, sorted(scenario.enabled_nodes(cfg)))
        result["supervisor_restarts_by_systemd_before_load"] = _nrestarts(guest)
        profiler = None
        if py_spy is not None:  # on CPU 1 with the simulator: CPU 0 is what is measured
            profiler = guest.ssh_cmd(
                "taskset -c 1 /opt/exolink/bin/py-spy record --nonblocking --subprocesses "
                f"--threads -r {PROFILE_RATE} -d {seconds:g} -f raw -o {GUEST_PROFILE} "
                "-p $(systemctl show -p MainPID --value exolink.service)"
            )
        if ladder is not None and laptop is not None and "laptop_error" not in result:

            def probe(nodes: list[str], secs: float) -> dict[str, Any]:
                return dict(_probe_only(guest_probe(secs, nodes), secs)["probe"])

            result["ladder"] = ladderlib.run(laptop, cfg, probe, seconds, ladder)
            result["logs"] = _guest_logs(guest, result)
            return result
        if loaded:
            assert laptop is not None
            cap = partial(_cap_now, guest, cpu_quota) if cpu_quota and cap_after_start else None
            result |= _run_load(
                laptop, probe_cmd, seconds, profiler, guest.jit, fetch, work, guest.core_cpu_s, cap
            )
            result["setpoints"] = _setpoints(result, cfg, work)
        else:  # no load from the laptop: the guest's own figures, said to be without it
            result["window"] = _probe_only(probe_cmd, seconds, profiler, result)
        if estop and laptop is not None:
            result["estop"] = _estop_cases(guest, laptop_cfg, cfg["device"])
        result["supervisor_restarts_by_systemd_at_end"] = _nrestarts(guest)
        if cpu_quota:  # how often and how long the quota held the service back
            stat = guest.ssh("cat /sys/fs/cgroup/system.slice/exolink.service/cpu.stat")
            result["cpu_stat_at_end"] = dict(
                line.split(" ", 1) for line in stat.stdout.splitlines() if " " in line
            )
        result["supervisor_threads_at_end"] = _supervisor_threads(guest)
        result["guest_clock_ahead_s"] = guest.clock_ahead_s()  # the journal's against the host's
        if timeline:
            ahead = result["guest_clock_ahead_s"]
            result["timeline"] = _fetch_timeline(
                guest, work, sampler if ahead is not None else None, ahead or 0.0
            )
        result["logs"] = _guest_logs(guest, result)
        if kernel_work:
            result["kernel_work"] = _fetch_kernel_work(guest, work)
        if py_spy is not None:
            result["profile"] = _fetch_profile(guest, work, result, seconds)
        result["units"] = _guest_units(guest)  # stops the service: the profiles are written
        if "qemu_jit_before" in result:  # the service stopped: the read's stall hurts nothing
            result["qemu_jit"] = _jit_window(result.pop("qemu_jit_before"), guest.jit())
        if cprofile:
            result["cprofile"] = _fetch_cprofiles(guest, work, cprofile)
        return result
    except Exception as exc:  # a table with what was measured beats a traceback without one
        log.exception("guest run failed")
        result["error"] = f"{type(exc).__name__}: {exc}"
        return result
    finally:
        if laptop is not None:
            laptop.close()
        if sampler is not None:
            result["vcpu0"] = sampler.stop()
        guest.stop()
        result["console_log"] = str(work / "console.log")


def _estop_cases(guest: Guest, login: Path, device: str) -> dict[str, Any]:
    """benchmarks/estop.py's four cases on the proxy: the e-stop sent and its disable frame read
    in the guest (one clock; on CPU 1 with the simulator, as a laptop's work is not the board's),
    the hostile clients on this host through the forwarded port, as laptops would be: stalled
    (3 that queued 3000 status queries each, then SIGSTOPped for the whole case) and flood (3
    that keep 1000 queries in flight)."""
    guest.upload(ESTOP, GUEST_ESTOP)
    guest.upload(login, GUEST_LOGIN)
    out: dict[str, Any] = {"trials": ESTOP_TRIALS}
    for case in ("idle", "big_query", "stalled", "flood"):
        hostile = _hostile_clients(case, guest.at, str(login), device)
        try:
            r = guest.ssh(
                f"taskset -c 1 /opt/exolink/bin/python {GUEST_ESTOP} measure "
                f"--at tcp/127.0.0.1:7447 --device {device} --zenoh-config {GUEST_LOGIN} "
                f"--bus socketcan:vcan0 --case {'big_query' if case == 'big_query' else 'idle'} "
                f"--trials {ESTOP_TRIALS}",
                timeout=900,
            )
            last = r.stdout.strip().splitlines()[-1:] or [""]
            try:
                out[case] = json.loads(last[0])
            except ValueError:
                out[case] = {"error": (r.stderr or r.stdout)[-400:]}
        finally:
            for p in hostile:
                p.send_signal(signal.SIGCONT)
                p.kill()
                p.wait()
    return out


def _hostile_clients(case: str, at: str, login: str, device: str) -> list[subprocess.Popen[str]]:
    if case not in ("stalled", "flood"):
        return []
    mode = "stall" if case == "stalled" else "flood"
    cmd = [
        sys.executable,
        str(ESTOP),
        mode,
        "--at",
        at,
        "--device",
        device,
        "--zenoh-config",
        login,
    ]
    procs = [
        subprocess.Popen(cmd, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True)
        for _ in range(3)
    ]
    for p in procs:  # "sent" / "flooding": its queries are on their way
        assert p.stdout is not None
        p.stdout.readline()
        if mode == "stall":
            p.send_signal(signal.SIGSTOP)
    time.sleep(1.0)
    return procs


def _cap_now(guest: Guest, pct: int) -> dict[str, Any]:
    """The service's quota set at run time, with the cgroup's counters then: the figures at
    the end minus these are the load's alone."""
    # The cgroup's file, as CPUQuota= and CPUQuotaPeriodSec=10ms write it: `systemctl
    # set-property` reloads systemd's units first, which stalled the whole guest ~1.5 s under
    # TCG (the timeline's samples stopped) and hung-killed the h2 reader at the cap (C63).
    guest.ssh(f"echo '{pct * 100} 10000' > /sys/fs/cgroup/system.slice/exolink.service/cpu.max")
    log.info("capped", pct=pct)
    r = guest.ssh(
        "cat /sys/fs/cgroup/system.slice/exolink.service/cpu.max "
        "/sys/fs/cgroup/system.slice/exolink.service/cpu.stat"
    )
    lines = r.stdout.splitlines()
    stat = dict(line.split(" ", 1) for line in lines[1:] if " " in line)
    return {"cpu_max": lines[0] if lines else r.stderr.strip(), "cpu_stat": stat}


def _simulator_out_of_the_quota(guest: Guest) -> str:
    """The simulator (the hardware's stand-in on CPU 1, a node of the service) moved to a
    cgroup of its own, so the service's quota measures the appliance alone."""
    r = guest.ssh(
        "mkdir -p /sys/fs/cgroup/exolink-sim && "
        "for p in $(pgrep -x exo-simulator); do echo $p > /sys/fs/cgroup/exolink-sim/cgroup.procs; "
        "done; cat /sys/fs/cgroup/exolink-sim/cgroup.procs; "
        "cat /sys/fs/cgroup/system.slice/exolink.service/cpu.max"
    )
    return (r.stdout or r.stderr).strip()


def _units(stdout: str, stderr: str) -> dict[str, Any]:
    for line in stdout.splitlines():
        if line.startswith("UNITS_RESULT "):
            return dict(json.loads(line.split(" ", 1)[1]))
    return {"error": (stderr or stdout)[-500:]}


def _guest_units(guest: Guest) -> dict[str, Any]:
    """The guest's unit costs (units.py) on CPU 0, after the window, the appliance stopped."""
    log.info("unit costs in the guest")
    guest.ssh("systemctl stop exolink.service", timeout=300)
    guest.upload(UNITS, "/run/exolink-units.py")
    r = guest.ssh(
        f"/opt/exolink/bin/python /run/exolink-units.py --seconds {UNITS_SECONDS:g}", timeout=900
    )
    return _units(r.stdout, r.stderr)


def native_units() -> dict[str, Any]:
    """The same unit costs on this host's CPU 0 (after the native run)."""
    log.info("unit costs natively")
    cmd = [sys.executable, str(UNITS), "--seconds", f"{UNITS_SECONDS:g}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    return _units(r.stdout, r.stderr)


PROFILE_RATE = 10  # 50 Hz over 8 processes fell minutes behind on the emulated CPU 1
GUEST_PROFILE = "/run/exolink-profile.txt"


def _fetch_profile(
    guest: Guest, work: Path, result: dict[str, Any], seconds: float
) -> dict[str, Any]:
    """The window's py-spy stacks, saved beside the console log, summarized per process."""
    r = guest.ssh(f"cat {GUEST_PROFILE}")
    raw = work / "profile-guest.txt"
    raw.write_text(r.stdout)
    names = _pid_names(result)
    summary = profile.summarize(r.stdout, names)
    text = profile.render(summary, PROFILE_RATE * seconds)
    (work / "profile-guest-top.txt").write_text(text + "\n")
    return {"raw": str(raw), "rate_hz": PROFILE_RATE, "summary": summary}


def _fetch_timeline(
    guest: Guest, work: Path, vcpu: CoreSampler | None = None, ahead_s: float = 0.0
) -> dict[str, Any]:
    """The sampler stopped, its lines saved beside the console log and summarized there as
    ``timeline-top.txt`` (one line per interval: wall clock, the cgroup's use and throttled
    periods, CPU 0's idle, with ``vcpu`` the share the host ran the board's vCPU, the busiest
    threads), to read beside the journal's trips. ``ahead_s``: the guest's clock against the
    host's."""
    guest.ssh(f"pkill -f {GUEST_TIMELINE}")
    r = guest.ssh(f"cat {GUEST_TIMELINE}l", timeout=300)
    raw = work / "timeline.jsonl"
    raw.write_text(r.stdout)
    rows = timelinelib.summarize(r.stdout.splitlines(), top=8)
    if vcpu is not None:
        points = vcpu.points()
        for a, b in itertools.pairwise(rows):
            t0, t1 = a["wall"] - ahead_s, b["wall"] - ahead_s
            b["host_ran"] = ran_pct(points, t0, t1)
            b["qemu_main"] = ran_pct(points, t0, t1, column=MAIN)
    text = "\n".join(
        f"{time.strftime('%H:%M:%S', time.gmtime(row['wall']))}.{int(row['wall'] % 1 * 100):02d}"
        f" cpu {row['cpu_pct']:5.1f} usage {row.get('usage_pct', '-')}"
        f" thr {row.get('throttled', '-')} cpu0 {row.get('cpu0', '-')}"
        f" host ran {row.get('host_ran', '-')} qemu main {row.get('qemu_main', '-')} | "
        + ", ".join(f"{k} {s}" for k, s in row["top"])
        for row in rows
    )
    (work / "timeline-top.txt").write_text(text + "\n")
    return {"raw": str(raw), "text": str(work / "timeline-top.txt"), "intervals": len(rows)}


def _setpoints(result: dict[str, Any], cfg: dict[str, Any], work: Path) -> dict[str, Any]:
    """The probe's joint-control frames of the window, saved beside the console log
    (``frames-70.bin``, struct can_frame each) and checked against the config's limits."""
    frames = result.get("window", {}).get("probe", {}).pop("frames", None)
    if not frames:
        return {"error": "the probe kept no frames"}
    raw = base64.b64decode(frames["b64"])
    (work / f"frames-{frames['id']}.bin").write_bytes(raw)
    manager = [n for n in cfg.get("nodes", []) if n.get("plugin") == "controller_manager"]
    slot_ms = int((manager[0].get("params") or {}).get("slot_ms", 20)) if manager else 20
    return setpoints.steps(raw, cfg.get("limits"), slot_ms)


def _fetch_kernel_work(guest: Guest, work: Path) -> dict[str, Any]:
    """The workqueue trace stopped and saved beside the console log (``workqueue-trace.txt``),
    summarized for the whole run and for 2 s from each of the manager's ``timer_left`` (the
    pattern's stop, where J68's kworker held CPU 0), with those journal lines."""
    r = guest.ssh(kernelwork.stop_command(), timeout=300)
    (work / "workqueue-trace.txt").write_text(r.stdout)
    done = kernelwork.items(r.stdout)
    left = guest.ssh(
        "journalctl -b --no-pager -o short-monotonic -u exolink "
        "| grep -E 'timer_left|timer_lease_lapsed|watchdog_trip|node_hung_killed' | tail -20"
    ).stdout.splitlines()
    edges = []
    for line in left:
        t = _monotonic_s(line)
        if t is not None and "timer_left" in line:
            edges.append(
                {"t": t, **kernelwork.summarize([i for i in done if t <= i["t"] <= t + 2.0], 10)}
            )
    return {
        "raw": str(work / "workqueue-trace.txt"),
        **kernelwork.summarize(done),
        "journal": left,
        "after_timer_left": edges,
    }


GUEST_CPROFILE = "/var/lib/exolink/profile"  # the service may write there (ReadWritePaths)


def _fetch_cprofiles(guest: Guest, work: Path, nodes: tuple[str, ...]) -> dict[str, Any]:
    """Each node's cProfile (its loop's whole run: settle, window and stop), saved beside the
    console log as ``cprofile-<node>.prof``, its top functions in the JSON."""
    out: dict[str, Any] = {}
    for name in nodes:
        # the largest: a spawn restarted after the window writes its own, short, profile
        r = guest.ssh(f"base64 -w0 $(ls -S {GUEST_CPROFILE}/{name}-*.prof | head -1)")
        if r.returncode != 0 or not r.stdout.strip():
            out[name] = {"error": (r.stderr or "no profile written").strip()[-300:]}
            continue
        path = work / f"cprofile-{name}.prof"
        path.write_bytes(base64.b64decode(r.stdout.strip()))
        out[name] = {"file": str(path), **profile.top_pstats(path)}
    return out


def _pid_names(result: dict[str, Any]) -> dict[int, str]:
    names = {}
    probe = result.get("window", {}).get("probe", {})
    for name, pid in (probe.get("pids") or {}).items():
        names[int(pid)] = name
    st = result.get("window", {}).get("before", {}).get("status", {})
    if isinstance(st.get("pid"), int):
        names[st["pid"]] = "supervisor"
    if isinstance(st.get("zygote_pid"), int):
        names[st["zygote_pid"]] = "zygote"
    for n in st.get("nodes", []):
        if isinstance(n.get("pid"), int):
            names[n["pid"]] = n["name"]
    return names


def _supervisor_threads(guest: Guest) -> list[str]:
    """Each thread of the supervisor after the window: state, kernel wait channel, CPU time.
    When the laptop's queries go unanswered after the window (seen once this stop while its
    joint_states kept coming) this says whether the supervisor's threads are stuck, and where."""
    r = guest.ssh(
        "ps -L -o tid,stat,wchan:28,time,comm "
        "-p $(systemctl show -p MainPID --value exolink.service)"
    )
    return (r.stdout or r.stderr).splitlines()[:80]


def _nrestarts(guest: Guest) -> int | None:
    """systemd's count of supervisor restarts (its watchdog kills among them)."""
    r = guest.ssh("systemctl show -p NRestarts --value exolink.service")
    out = r.stdout.strip()
    return int(out) if out.isdigit() else None


def _probe_only(
    probe_cmd: list[str],
    seconds: float,
    profiler: list[str] | None = None,
    out: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One probe window and nothing else the laptop measures (it could not connect, or the
    ladder counts joint_states itself); the profiler's output, if any, goes into ``out``."""
    log.info("probe window", seconds=seconds)
    probe = subprocess.Popen(probe_cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True)
    prof = _start_profiler(profiler)
    try:
        return scenario.measure(None, probe, seconds)
    finally:
        if probe.poll() is None:
            probe.kill()
        _end_profiler(prof, out if out is not None else {})


def _monotonic_s(line: str) -> float | None:
    """The time of a `journalctl -o short-monotonic` line (None: not such a line)."""
    m = re.match(r"\[\s*(\d+\.\d+)\]", line)
    return float(m.group(1)) if m else None


def _guest_logs(guest: Guest, result: dict[str, Any]) -> dict[str, Any]:
    """Journal lines of interest, split into the whole boot and the measurement window."""
    r = guest.ssh(
        f"journalctl -b --no-pager -o short-monotonic -u exolink -u exolink-bench "
        f"| grep -E '{LOG_PATTERNS}' | tail -200"
    )
    probe = result.get("window", {}).get("probe", {})
    t0, t1 = probe.get("t0_monotonic"), probe.get("t1_monotonic")
    lines = r.stdout.splitlines()
    inside = []
    for line in lines:
        t = _monotonic_s(line)
        if t is not None and t0 is not None and t1 is not None and t0 <= t <= t1:
            inside.append(line)
    return {
        "boot_total": {p: sum(p in line for line in lines) for p in LOG_PATTERNS.split("|")},
        "window_counts": {p: sum(p in line for line in inside) for p in LOG_PATTERNS.split("|")},
        "window": inside[-50:],
        "window_loop_stalled": stalls("\n".join(inside)),
        "last_lines": lines[-30:],
    }


def _not_beating(status: dict[str, Any], timeout: float) -> str:
    bad = [
        f"{n['name']} {n['state']} (restarts {n['restarts']}, {n['last_exit'] or 'no exit'})"
        for n in status["nodes"]
        if n["enabled"] and not (n["state"] == "running" and n["heartbeat_age_s"] is not None)
    ]
    return f"not all enabled nodes beating after {timeout:g} s: {', '.join(bad)}; measured anyway"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_native(
    repo: Path,
    seconds: float,
    start_grace_ms: int,
    timings: str,
    ladder: tuple[str, ...] | None = None,
    without: tuple[str, ...] = (),
) -> dict[str, Any]:
    """The same config and load on this host: udp_multicast (no vcan module here), the
    supervisor under ``taskset -c 0``, the simulator node on CPU 1."""
    from benchmarks.harness import group

    result: dict[str, Any] = {"kind": "native", "notes": []}
    work = Path(tempfile.mkdtemp(prefix="exolink-bench-board-"))
    port = free_port()
    can = {
        "interface": "udp_multicast",
        "channel": group(),
        "bring_up": False,
        "require_overlay": False,
    }
    base = yaml.safe_load(bundled("board").read_text())
    cfg = scenario.bench_config(base, can, start_grace_ms, timings, without)
    cfg["zenoh"]["listen"] = [f"tcp/127.0.0.1:{port}"]
    for n in cfg["nodes"]:
        if n["plugin"] == "recorder":
            n["params"]["directory"] = str(work / "recordings")
    path = work / "appliance.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    result["config"] = cfg
    result["bus"] = f"udp_multicast {can['channel']} (this host has no vcan kernel module)"
    result["load1_before"] = round(os.getloadavg()[0], 2)
    up_log = work / "up.log"
    env = {**os.environ, "EXOLINK_LOG_JSON": "1", "PYTHONUNBUFFERED": "1"}
    exolink = [sys.executable, "-m", "exolink.cli.main"]
    t0 = time.monotonic()
    with open(up_log, "wb") as f:
        proc = subprocess.Popen(
            ["taskset", "-c", "0", *exolink, "up", "-c", str(path)],
            stdout=f,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=work,
        )
    laptop = None
    try:
        laptop = _connect(f"tcp/127.0.0.1:{port}", None, 60, lambda: proc.poll() is None)
        status, ok = laptop.wait_beating(120, scenario.enabled_nodes(cfg))
        if status is None:
            result["error"] = "the supervisor never answered within 120 s"
            return result
        if not ok:
            result["notes"].append(_not_beating(status, 120))
        result["boot"] = {
            "all_nodes_beating_s": round(time.monotonic() - t0, 1) if ok else None,
            "resolution_s": 2.0,
            "node_start_s": {n["name"]: n["start_s"] for n in status["nodes"]},
        }
        time.sleep(SETTLE_S)

        def native_probe(secs: float, nodes: list[str]) -> list[str]:
            return [
                *("taskset", "-c", "1", sys.executable, str(PROBE), "--pid", str(proc.pid)),
                *("--seconds", f"{secs:g}", "--nodes", ",".join(nodes)),
            ]

        probe_cmd = native_probe(seconds, sorted(scenario.enabled_nodes(cfg)))
        if ladder is not None:

            def probe(nodes: list[str], secs: float) -> dict[str, Any]:
                cmd = native_probe(secs, nodes)
                return dict(_probe_only(cmd, secs)["probe"])

            result["ladder"] = ladderlib.run(laptop, cfg, probe, seconds, ladder)
            return result
        size0 = up_log.stat().st_size
        result |= _run_load(laptop, probe_cmd, seconds)
        text = up_log.read_text(errors="replace")
        window = text.encode()[size0:].decode(errors="replace")
        result["logs"] = {
            "boot_total": {p: text.count(p) for p in LOG_PATTERNS.split("|")},
            "since_arm_loop_stalled": stalls(window),
            "since_arm": [ln for ln in window.splitlines() if re.search(LOG_PATTERNS, ln)][-50:],
        }
        result["up_log"] = str(up_log)
        return result
    finally:
        if laptop is not None:
            laptop.close()
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(20)
        if proc.poll() is None:
            proc.kill()
