"""``make bench-board``: the built SD card under qemu-system-arm as a (slow) board proxy.

``python -m benchmarks.board [--image IMG] [--seconds 60] [--out build/bench-board.json]``
boots a copy of the card running the checkout's exolink (its wheel is installed on the copy at
boot), puts the nominal load on it and measures 60 s; then the same on this host (native) for the
ratio. Prints a table; writes everything, including the exact qemu command line, as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import structlog

from benchmarks.board import card as cardlib
from benchmarks.board import ladder, runs, scenario

REPO = Path(__file__).resolve().parents[2]


def _ms(usec: Any) -> str | None:
    return None if usec is None else f"{int(usec) / 1000:.1f}"


def _cell(v: Any, fmt: str = "{}") -> str:
    return "n/a" if v is None else fmt.format(v)


def _procs(run: dict[str, Any]) -> dict[str, Any]:
    return dict(run.get("window", {}).get("probe", {}).get("processes", {}))


def table(result: dict[str, Any]) -> str:
    g, n = result.get("guest", {}), result.get("native", {})
    if "ladder" in g or "ladder" in n:
        return ladder_table(result)
    gp, np_ = _procs(g), _procs(n)
    lines = [
        f"exolink {result['checkout']['describe']} ({result['checkout']['commit'][:12]}), "
        f"{result['seconds']:g} s window, {result['timings']} watchdog timings, nominal load "
        "(H2 100 Hz + MACCEPA board 0 simulated on CPU 1, pattern speed 10 armed, recorder on, "
        "timing monitor on, 1 laptop subscriber)"
        + (f" WITHOUT {', '.join(result['without'])}" if result.get("without") else "")
        + (f", a PID on {result['pid_joint']}" if result.get("pid_joint") else "")
        + (
            f", manager cycles_per_update {result['cycles_per_update']}"
            if result.get("cycles_per_update")
            else ""
        ),
        "",
        f"{'process':16} {'cpus':>5} {'guest %cpu':>10} {'guest PSS':>10} "
        f"{'native %cpu':>11} {'native PSS':>10} {'ratio':>6}",
    ]
    for name in sorted(set(gp) | set(np_), key=lambda x: (x != "supervisor", x)):
        a, b = gp.get(name, {}), np_.get(name, {})
        ratio = (
            f"{a['cpu_pct'] / b['cpu_pct']:.0f}x"
            if a.get("cpu_pct") and b.get("cpu_pct")
            else "n/a"
        )
        cpus = ",".join(a.get("cpus_allowed") or b.get("cpus_allowed") or ["?"])
        lines.append(
            f"{name:16} {cpus:>5} {_cell(a.get('cpu_pct'), '{:.1f}'):>10} "
            f"{_cell(a.get('pss_mb'), '{:.1f} MB'):>10} {_cell(b.get('cpu_pct'), '{:.1f}'):>11} "
            f"{_cell(b.get('pss_mb'), '{:.1f} MB'):>10} {ratio:>6}"
            + (
                f"  ({a.get('error') or b.get('error')})"
                if a.get("error") or b.get("error")
                else ""
            )
        )
    lines.append("")

    def row(label: str, gv: Any, nv: Any) -> None:
        lines.append(f"{label:34} {_cell(gv):>22} {_cell(nv):>22}")

    row("", "guest (qemu TCG, vcan0)", "native (x86, udp_mcast)")

    def get(run: dict[str, Any], *path: str) -> Any:
        cur: Any = run
        for p in path:
            if not isinstance(cur, dict) or p not in cur:
                return None
            cur = cur[p]
        return cur

    def pair(*path: str) -> tuple[Any, Any]:
        return get(g, *path), get(n, *path)

    def idle(run: dict[str, Any], cpu: str) -> Any:
        return get(run, "window", "probe", "idle_pct", cpu)

    row("CPU 0 idle %", idle(g, "cpu0"), idle(n, "cpu0"))
    core = get(g, "host_core") or {}
    row(
        "  the board's vCPU on the host",
        f"CPU {core['host_cpu']}, nice {core['nice']}" if core.get("own") else "shared",
        "",
    )
    row("  host CPU it had in the window %", get(g, "host_core_pct"), "")
    vcpu = g.get("vcpu0") or {}
    if vcpu.get("worst"):  # the host's runqueue held the board's core (CoreSampler)
        row(
            "  vCPU 0 ran / waited on the host, run %",
            f"{vcpu['run_pct']} / {vcpu['waited_pct']}",
            "",
        )
        w = vcpu["worst"][-1]
        row("  its worst 0.5 s waited % (UTC)", f"{w['waited_pct']} ({w['at_utc']})", "")
        row("  guest clock ahead of the host (s)", get(g, "guest_clock_ahead_s"), "")
    row("calibration (CPU ms, fixed Python loop)", *pair("window", "probe", "calibration_ms"))
    # units.py on CPU 0 after the window: what the appliance's CPU is made of on each machine
    row("unit: Python loop (CPU ms)", *pair("units", "python_loop_ms"))
    row("unit: getppid() (CPU us per call)", *pair("units", "syscall_getppid_us"))
    row("unit: thread_time() (CPU us per call)", *pair("units", "syscall_thread_time_us"))
    row("unit: 100 Hz sleep-wake (CPU us)", *pair("units", "wake_us"))
    row("unit: beat's pipe write (CPU us)", *pair("units", "beat_us", "pipe_write"))
    row("unit: beat's timerfd re-arm (CPU us)", *pair("units", "beat_us", "timerfd_rearm"))
    row(
        "unit: CAN frame read (CPU us)",
        *pair("units", "can_receive_us", "read", "cpu_us_per_frame_sent"),
    )
    row(
        "unit: CAN frame kernel-dropped (us)",
        *pair("units", "can_receive_us", "kernel_dropped", "cpu_us_per_frame_sent"),
    )
    for key, label in (
        ("", "one by one"),
        ("_burst4", "in fours"),
        ("_burst4x5", "4 x 5 topics"),
        ("_burst4x5_channel", "4 x 5, sub drains"),
        ("_burst4x5_unix", "4 x 5, unix sockets"),
    ):
        hop = [_hop(v) for v in pair("units", f"zenoh_us_per_sample{key}")]
        row(f"unit: Zenoh sample {label} (us)", *hop)
    row("  (publisher/router/subscriber)", "", "")
    row("CPU 1 idle % (simulator's)", idle(g, "cpu1"), idle(n, "cpu1"))
    sums = []
    for procs in (gp, np_):
        v = [p["cpu_pct"] for k, p in procs.items() if k != "simulator" and "cpu_pct" in p]
        sums.append(round(sum(v), 1) if v else None)
    row("appliance %cpu on CPU 0 (sum)", *sums)
    row("joint_states rate on laptop (Hz)", *pair("window", "joint_states", "rate_hz"))
    row("  taken as", *pair("window", "joint_states", "taken_as"))
    row("joint_states min/s", *pair("window", "joint_states", "per_second_min"))
    row("joint_states max gap (ms)", *pair("window", "joint_states", "max_gap_ms"))
    row("joint_states seq missed", *pair("window", "joint_states", "seq_missed"))
    row("h2_reader missing frames", *pair("derived", "h2_reader_missing"))
    row("vcan0 rx/tx dropped", _vcan_drops(g), "n/a (no vcan)")
    row("pattern running at window start", *pair("pattern_running_at_start"))
    row("pattern frames sent", *pair("derived", "pattern_sent"))
    row("pattern state at end", *pair("derived", "pattern_state_end"))
    sp = g.get("setpoints") or {}
    if "motors" in sp:  # what the set-points said (benchmarks/board/setpoints.py)
        steps = "/".join(str(m["max_step"]) for m in sp["motors"].values())
        row(
            "set-point max step per motor (deg)",
            f"{steps} (limit {sp.get('step_limit_deg')})",
            "n/a",
        )
        row(
            "  steps over the limit, out of range",
            f"{sp.get('over_step_limit')}, {sp.get('out_of_range')}",
            "n/a",
        )
    row("pattern timing id70 motor1 mean dev ms", *pair("window", "timing", "mean_dev_ms"))
    row("pattern timing p99 dev ms", *pair("window", "timing", "p99_dev_ms"))
    row("pattern timing max dev ms", *pair("window", "timing", "max_dev_ms"))
    row("pattern timing mean period ms", *pair("window", "timing", "mean_period_ms"))
    row("pattern timing n", *pair("window", "timing", "n"))
    row("  timing monitor socket drops", *pair("window", "timing", "socket_dropped"))
    row("H2 angle frames (110) n in window", *pair("window", "angles", "n"))
    row("H2 angle frames max dev ms", *pair("window", "angles", "max_dev_ms"))
    row("manager cycles/s (before..after)", *pair("derived", "manager_cycles_per_s"))
    for node in ("h2_reader", "controller_manager"):
        lines.append(f"{node} loop CPU per iteration in window (us, thread CPU clock):")
        for run in (g, n):
            w = get(run, "derived", f"{node}_loop_cpu")
            if isinstance(w, dict):
                phases = " ".join(f"{k} {v:g}" for k, v in w["us_per_iteration"].items())
                lines.append(f"  {run['kind']:6} {w['iterations']} iterations: {phases}")
            walls = get(run, "derived", f"{node}_loop_wall_max_ms")
            if isinstance(walls, dict):
                longest = " ".join(f"{k} {v:g}" for k, v in walls.items())
                lines.append(f"  {run['kind']:6} longest wall per phase (ms): {longest}")
    row("watchdog trips in window", *pair("derived", "watchdog_trips_in_window"))
    row("watchdog state at end", *pair("derived", "watchdog_state_end"))
    row("watchdog reason", *pair("derived", "watchdog_reason_end"))
    row("read_lag_max_ms (since start)", *pair("derived", "read_lag_max_ms"))
    row("frames the watchdog read in window", *pair("derived", "watchdog_frames_read"))
    row("recorder written / dropped", _rec(g), _rec(n))
    row(
        "loop_stalled in window",
        *(get(g, "logs", "window_loop_stalled"), get(n, "logs", "since_arm_loop_stalled")),
    )
    row("node restarts in window", _restarts(g), _restarts(n))
    row("qemu code-buffer flushes (arm..stop)", get(g, "qemu_jit", "flushes_under_load"), "n/a")
    row("cold start to all beating (s)", *pair("boot", "all_nodes_beating_s"))
    row("supervisor restarts by systemd", get(g, "supervisor_restarts_by_systemd_at_end"), "n/a")
    row("  of them during the load", _load_restarts(g), "n/a")
    row(
        "  'Watchdog timeout' in window",
        get(g, "logs", "window_counts", "Watchdog timeout"),
        "n/a",
    )
    row("laptop session", _laptop(g), _laptop(n))
    if f := g.get("fetch"):
        staged = g.get("fetch_staged") or {}
        ok = f.get("rc") == 0 and f.get("sha256") == staged.get("sha256")
        row(
            "record fetch in window",
            f"{(f.get('bytes') or 0) / 2**20:.1f} MiB in "
            f"{f.get('seconds')} s, rc {f.get('rc')}, sha256 {'equal' if ok else 'DIFFERS'}",
            "n/a",
        )
    if g.get("cpu_quota_pct"):
        stat = g.get("cpu_stat_at_end") or {}
        when = "set once all beat" if g.get("cpu_quota_set") else "from boot"
        row(f"service CPU quota (10 ms period, {when})", f"{g['cpu_quota_pct']}%", "n/a")
        if before := (g.get("cpu_quota_set") or {}).get("cpu_stat"):
            for k in ("nr_periods", "nr_throttled", "throttled_usec"):
                if k in stat and k in before:
                    stat = {**stat, k: int(stat[k]) - int(before[k])}
        row(
            "  periods throttled / total",
            f"{stat.get('nr_throttled')}/{stat.get('nr_periods')}",
            "",
        )
        row("  throttled ms", _ms(stat.get("throttled_usec")), "")
    for case, r in (g.get("estop") or {}).items():
        if isinstance(r, dict) and "estop_to_first_disable_frame_ms" in r:
            e = r["estop_to_first_disable_frame_ms"]
            lost = r.get("no_frame_within_s", {}).get("trials")
            row(
                f"e-stop -> disable ms p50/p99 {case}",
                f"{e.get('p50')}/{e.get('p99')} ({lost} lost)",
                "",
            )
        elif isinstance(r, dict):
            row(f"e-stop {case}", r.get("error", "?")[-40:], "")
    for run in (g, n):
        if not run:
            continue
        cpu0 = idle(run, "cpu0")
        if isinstance(cpu0, int | float) and cpu0 < 5:
            lines.append(
                f"note ({run['kind']}): CPU 0 saturated ({cpu0}% idle): the %cpu column is the "
                "scheduler's split of a full CPU, not what each process would use"
            )
    if g.get("qemu_command"):
        lines += ["", "qemu: " + g["qemu_command"]]
    for run in (g, n):
        if not run:
            continue
        for note in run.get("notes", []):
            lines.append(f"note ({run['kind']}): {note}")
        if run.get("laptop_error"):
            lines.append(
                f"LAPTOP FAILED ({run['kind']}): {run['laptop_error']}; the figures above that "
                "need the laptop (joint_states, pattern, watchdog, recorder) are n/a"
            )
        if run.get("error"):
            lines.append(f"ERROR ({run['kind']}): {run['error']}")
    return "\n".join(lines)


def ladder_table(result: dict[str, Any]) -> str:
    lines = [
        f"exolink {result['checkout']['describe']} ({result['checkout']['commit'][:12]}), "
        f"{result['seconds']:g} s per step, {result['timings']} watchdog timings; base: "
        "supervisor + h2_reader on CPU 0, simulator (H2 100 Hz + MACCEPA board 0) on CPU 1, "
        "1 laptop subscriber. 'all enabled': node columns summed over every node but the "
        "simulator (h2_reader included)",
    ]
    for run in (result.get("guest", {}), result.get("native", {})):
        if not run:
            continue
        lines += ["", f"{run['kind']}:"]
        lines += ladder.table(run.get("ladder", {})) if "ladder" in run else []
        if run.get("qemu_command"):
            lines.append("qemu: " + run["qemu_command"])
        lines += [f"note: {note}" for note in run.get("notes", [])]
        for key in ("laptop_error", "error"):
            if run.get(key):
                lines.append(f"ERROR: {run[key]}")
    return "\n".join(lines)


def _hop(v: Any) -> Any:
    """units.py's per-sample CPU of the three processes of a Zenoh hop, as pub/router/sub."""
    if not isinstance(v, dict):
        return v
    return "/".join(str(v.get(k)) for k in ("publisher", "router", "subscriber"))


def _laptop(run: dict[str, Any]) -> str | None:
    if not run:
        return None
    if run.get("laptop_error"):
        return "FAILED (see note)"
    return "connected" if "operator" in run else None


def _load_restarts(run: dict[str, Any]) -> int | None:
    a = run.get("supervisor_restarts_by_systemd_before_load")
    b = run.get("supervisor_restarts_by_systemd_at_end")
    return b - a if isinstance(a, int) and isinstance(b, int) else None


def _vcan_drops(run: dict[str, Any]) -> str | None:
    d = run.get("window", {}).get("probe", {}).get("link_delta")
    if not d:
        return None
    return f"{d.get('rx_dropped')}/{d.get('tx_dropped')} of {d.get('rx_packets')} rx"


def _rec(run: dict[str, Any]) -> str | None:
    d = run.get("derived", {})
    if "recorder_written" not in d:
        return None
    return f"{d['recorder_written']} / {d.get('recorder_dropped')}"


def _restarts(run: dict[str, Any]) -> str | None:
    r = run.get("derived", {}).get("node_restarts_in_window")
    if r is None:
        return None
    bad = {k: v for k, v in r.items() if v}
    return json.dumps(bad) if bad else "0"


def main() -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.board", description=__doc__)
    p.add_argument("--image", help="raw image (default: newest build/image/exolink-bbb-*.img)")
    p.add_argument("--seconds", type=float, default=60.0, help="measurement window")
    p.add_argument("--out", default=str(REPO / "build/bench-board.json"))
    p.add_argument("--work", default=str(REPO / "build/bench-board"), help="card copy, logs")
    p.add_argument("--only", choices=["guest", "native"])
    p.add_argument(
        "--start-grace-ms",
        type=int,
        default=600_000,
        help="watchdog.start_grace_ms (the only timing changed from stock: imports under TCG)",
    )
    p.add_argument(
        "--timings",
        choices=["stock", "relaxed"],
        default="stock",
        help="watchdog timings: stock (board.yaml, systemd WatchdogSec 5 s) or relaxed "
        "(heartbeat deadline 5 s, WatchdogSec 60 s: for CPU shares when stock cannot settle)",
    )
    p.add_argument("--boot-timeout", type=float, default=900.0)
    p.add_argument(
        "--journal-console",
        action="store_true",
        help="forward the guest's journal to the serial console (debugging; costs guest CPU)",
    )
    p.add_argument(
        "--py-spy",
        metavar="WHEEL",
        help="an armv7 py-spy wheel (pip download py-spy --platform manylinux2014_armv7l "
        "--only-binary=:all:): installed on the card copy; the window is profiled "
        "(build/bench-board/profile-guest*.txt, 'profile' in the JSON). Under TCG it cannot "
        "keep up: at 10 Hz over every process it fell 11 min behind, was killed, and took CPU 1 "
        "from the simulator (H2 gaps): a run with it measures nothing else",
    )
    p.add_argument(
        "--ladder",
        nargs="?",
        const="",
        metavar="NODES",
        help="instead of the nominal load: each node's own cost, added one at a time to a base "
        "while CPU 0 has room (benchmarks/board/ladder.py); NODES: only these (comma-separated)",
    )
    p.add_argument(
        "--guest-env",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="environment of the appliance's service on the guest (experiments; in the JSON)",
    )
    p.add_argument(
        "--without",
        default="",
        metavar="NODES",
        help="leave these non-critical nodes off (comma-separated): what the rest of the "
        "nominal load needs when all of it saturates CPU 0 (in the JSON and the table's title)",
    )
    p.add_argument(
        "--cprofile",
        default="",
        metavar="NODES",
        help="these nodes' loops under cProfile in the guest (comma-separated; EXOLINK_PROFILE_DIR): "
        "deterministic, in-process, slower nodes; files beside the console log, top functions "
        "in the JSON",
    )
    p.add_argument(
        "--laptop-one-by-one",
        action="store_true",
        help="the laptop takes joint_states one message per sample, as a ROS 2 tool does, "
        "not as the bundles exolink's client takes (the board then puts each message for it)",
    )
    p.add_argument(
        "--cpu-quota",
        type=int,
        metavar="PCT",
        help="cap the appliance's service on the guest at PCT %% of one CPU (systemd CPUQuota, "
        "a 10 ms CPUQuotaPeriodSec): the board budget as a hard limit (e.g. 50)",
    )
    p.add_argument(
        "--cap-after-start",
        action="store_true",
        help="with --cpu-quota: set the quota once every node beats and 10 s more, not from boot (the "
        "budget of the running appliance; the cold start under the cap is another question)",
    )
    p.add_argument(
        "--timeline",
        action="store_true",
        help="CPU per thread of the appliance's cgroup every 0.25 s from the nodes' start "
        "(or the cap) to the end (benchmarks/board/timeline.py): who took the core when",
    )
    p.add_argument(
        "--kernel-work",
        action="store_true",
        help="trace the guest's workqueue items (function, CPU time) from the nodes' start to "
        "the end (benchmarks/board/kernelwork.py): which kernel work held CPU 0 when",
    )
    p.add_argument(
        "--pid",
        metavar="JOINT",
        default="",
        help="a PID controller active on JOINT beside the gait during the window (the "
        "manager's 100 Hz feedback loop; e.g. l_ankle, which the pattern does not drive)",
    )
    p.add_argument(
        "--cycles-per-update",
        type=int,
        metavar="N",
        help="the controller manager's cycles_per_update (board.yaml ships 2: a feedback "
        "controller every second H2 cycle; 1 runs --pid's loop at 100 Hz)",
    )
    p.add_argument(
        "--estop",
        action="store_true",
        help="after the window: e-stop -> first disable frame in the guest, idle and beside "
        "hostile clients on this host (benchmarks/estop.py's cases)",
    )
    p.add_argument(
        "--fetch-mb",
        type=int,
        default=0,
        metavar="MIB",
        help="a closed recording of MIB MiB put on the card before the load and fetched by "
        "the laptop's `exolink record fetch` from the window's start (its cost to the gait)",
    )
    p.add_argument(
        "--own-core",
        action="store_true",
        help="the board's vCPU on host CPU 0 at nice -20, the laptop and qemu's other threads "
        "there only while it idles (guest.py; by default it shares the host's cores)",
    )
    p.add_argument("--show", metavar="JSON", help="only print the table of an earlier run")
    args = p.parse_args()
    if args.show:
        print(table(json.loads(Path(args.show).read_text())))
        return 0
    structlog.configure(
        processors=[  # UTC to the millisecond: each bench action beside the guest's journal
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="%H:%M:%S.%f", utc=True),
            structlog.dev.ConsoleRenderer(colors=False),
        ],
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
    )
    scenario.ONE_BY_ONE = args.laptop_one_by_one
    scenario.PID_JOINT = args.pid
    scenario.MANAGER_CYCLES = args.cycles_per_update
    ladder_nodes = None if args.ladder is None else tuple(filter(None, args.ladder.split(",")))
    without = tuple(filter(None, args.without.split(",")))
    t0 = time.monotonic()
    result: dict[str, Any] = {
        "schema": 1,
        "without": list(without),
        "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "seconds": args.seconds,
        "timings": args.timings,
        "cpu_quota_pct": args.cpu_quota,
        "cap_after_start": args.cap_after_start,
        "pid_joint": args.pid or None,
        "cycles_per_update": args.cycles_per_update,
        "fetch_mb": args.fetch_mb or None,
        "laptop_joint_states": "one by one" if args.laptop_one_by_one else "bundles if bundled",
        "checkout": cardlib.checkout_info(REPO),
        "host": {
            "cpus": os.cpu_count(),
            "arch": platform.machine(),
            "python": platform.python_version(),
            "load1": round(os.getloadavg()[0], 2),
        },
    }
    if args.only != "native":
        image = cardlib.find_image(REPO, args.image)
        result["guest"] = _guarded(
            "guest",
            runs.run_guest,
            REPO,
            image,
            Path(args.work),
            args.seconds,
            args.start_grace_ms,
            args.boot_timeout,
            args.timings,
            args.journal_console,
            Path(args.py_spy) if args.py_spy else None,
            ladder_nodes,
            tuple(args.guest_env),
            without,
            tuple(filter(None, args.cprofile.split(","))),
            args.cpu_quota,
            args.estop,
            args.fetch_mb,
            args.cap_after_start,
            args.timeline,
            args.own_core,
            args.kernel_work,
        )
    if args.only != "guest":
        result["native"] = _guarded(
            "native",
            runs.run_native,
            REPO,
            args.seconds,
            args.start_grace_ms,
            args.timings,
            ladder_nodes,
            without,
        )
        if ladder_nodes is None:
            result["native"]["units"] = _guarded("units", runs.native_units)
    result["run_s"] = round(time.monotonic() - t0, 1)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    text = table(result)
    out.with_suffix(".txt").write_text(text + "\n")
    print(text)
    print(f"\nJSON: {out}  (run took {result['run_s']:.0f} s)")
    runs_ = (result.get("guest", {}), result.get("native", {}))
    return 0 if not any(r.get("error") or r.get("laptop_error") for r in runs_) else 1


def _guarded(kind: str, fn: Any, *args: Any) -> dict[str, Any]:
    """A run that raises still leaves a row in the table and the JSON."""
    try:
        return dict(fn(*args))
    except Exception as exc:
        structlog.get_logger("bench-board").exception("run failed", kind=kind)
        return {"kind": kind, "notes": [], "error": f"{type(exc).__name__}: {exc}"}


if __name__ == "__main__":
    sys.exit(main())
