"""The dashboard: CAN frame -> value drawn in a real browser (Debian's headless chromium),
updates per second reaching the page, the dashboard server's CPU at 100 Hz data (`exolink
dashboard` on the laptop, and the board's `dashboard` node inside the appliance), and (full run
only) the page's memory over 10 minutes.

Latency: each joint_states message carries the kernel receive time of its CAN frame (wall
clock); the page notes ``Date.now()`` minus that stamp when it draws the value (requestAnimation-
Frame after the update), so the figure includes h2_reader, Zenoh, the server's decimation tick
(up to one period: 40 ms at 25 frames/s), the WebSocket and the draw.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
import urllib.request
from typing import Any

import yaml

from benchmarks.harness import EXOLINK, Appliance, cpu_s, free_port, pct, pss_mb
from exolink.config import bundled

RATE_HZ = 25.0  # `exolink dashboard`'s default
BOARD_RATE_HZ = 10.0  # the board node's default (board.yaml)


def _dashboard(app: Appliance, port: int) -> subprocess.Popen[bytes]:
    log = (app.dir / "dashboard.log").open("wb")
    args = [
        "dashboard",
        "--at",
        app.at,
        "--port",
        str(port),
        "--no-browser",
        "--rate",
        str(RATE_HZ),
    ]
    proc = subprocess.Popen(
        [*EXOLINK, *args],
        stdout=log,
        stderr=subprocess.STDOUT,
        env={**os.environ, "EXOLINK_LOG_JSON": "1"},
    )
    end = time.monotonic() + 30
    while time.monotonic() < end:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=1):
                return proc
        except OSError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError(f"dashboard did not start; see {app.dir}/dashboard.log")


def _cpu_per_s(pid: int, seconds: float) -> float:
    c0, t0 = cpu_s(pid), time.monotonic()
    time.sleep(seconds)
    return round((cpu_s(pid) - c0) / (time.monotonic() - t0), 4)


def run(quick: bool) -> dict[str, Any]:
    exe = shutil.which("chromium")
    if exe is None:
        return {"skipped": "Debian's chromium is not installed (make browser)"}
    from playwright.sync_api import sync_playwright

    seconds = 10.0 if quick else 30.0
    soak_s = 0.0 if quick else float(os.environ.get("EXOLINK_BENCH_DASHBOARD_SOAK_S", 600))
    out: dict[str, Any] = {"rate_hz": RATE_HZ, "seconds": seconds}
    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=exe, args=["--no-sandbox", "--js-flags=--expose-gc"]
        )
        try:
            out |= _laptop(browser, seconds, soak_s)
            out["board_node"] = _board_node(browser, seconds)
        finally:
            browser.close()
    return out


STATS = "({f: exolinkStats.frames, d: exolinkStats.drawn, n: exolinkStats.lat.length})"


def _laptop(browser: Any, seconds: float, soak_s: float) -> dict[str, Any]:
    """`exolink dashboard` beside a sim appliance, one page open."""
    app = Appliance.sim()
    port = free_port()
    dash = None
    out: dict[str, Any] = {}
    try:
        dash = _dashboard(app, port)
        time.sleep(2)
        out["server_cpu_s_per_s_no_page"] = _cpu_per_s(dash.pid, min(seconds, 5))
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function("window.exolinkStats.drawn > 10", timeout=30_000)
        time.sleep(2)
        s0 = page.evaluate(STATS)
        c0, t0 = cpu_s(dash.pid), time.monotonic()
        time.sleep(seconds)
        wall = time.monotonic() - t0
        cpu = cpu_s(dash.pid) - c0
        s1 = page.evaluate(STATS)
        lat = page.evaluate(f"exolinkStats.lat.slice({s0['n']})")
        out |= {
            "latency_can_to_drawn_ms": pct(lat, digits=1),
            "frames_to_page_per_s": round((s1["f"] - s0["f"]) / wall, 1),
            "values_drawn_per_s": round((s1["d"] - s0["d"]) / wall, 1),
            "server_cpu_s_per_s": round(cpu / wall, 4),
            "server_pss_mb": pss_mb(dash.pid),
        }
        if soak_s:
            out["browser_memory"] = _soak(page, soak_s)
        page.close()
    finally:
        if dash is not None:
            dash.terminate()
            try:
                dash.wait(10)
            except subprocess.TimeoutExpired:
                dash.kill()
        app.close()
    return out


def _board_node(browser: Any, seconds: float) -> dict[str, Any]:
    """The `dashboard` node inside the appliance (as on the board, at its 10 frames/s)."""
    port = free_port()
    nodes = yaml.safe_load(bundled("sim").read_text())["nodes"]
    params = {"host": "127.0.0.1", "port": port, "rate_hz": BOARD_RATE_HZ}
    app = Appliance.sim(
        nodes=[*nodes, {"name": "dashboard", "plugin": "dashboard", "params": params}]
    )
    try:
        pid = app.node("dashboard")["pid"]
        time.sleep(3)  # past its start (imports, first queries)
        no_page = _cpu_per_s(pid, min(seconds, 5))
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{port}/")
        page.wait_for_function("window.exolinkStats.drawn > 5", timeout=30_000)
        s0, t0 = page.evaluate(STATS), time.monotonic()
        with_page = _cpu_per_s(pid, seconds)
        s1 = page.evaluate(STATS)
        lat = page.evaluate(f"exolinkStats.lat.slice({s0['n']})")
        page.close()
        return {
            "rate_hz": BOARD_RATE_HZ,
            "cpu_s_per_s_no_page": no_page,
            "cpu_s_per_s_one_page": with_page,
            "frames_to_page_per_s": round((s1["f"] - s0["f"]) / (time.monotonic() - t0), 1),
            "latency_can_to_drawn_ms": pct(lat, digits=1),
            "pss_mb": pss_mb(pid),
        }
    finally:
        app.close()


def _soak(page: Any, seconds: float) -> dict[str, Any]:
    """JS heap after a forced GC at the start and the end of a long live view: no growth."""
    heap = (
        "(() => { window.gc(); return {heap: performance.memory.usedJSHeapSize,"
        " nodes: document.getElementsByTagName('*').length}; })()"
    )
    first = page.evaluate(heap)
    time.sleep(seconds)
    last = page.evaluate(heap)
    return {
        "seconds": seconds,
        "js_heap_start_mb": round(first["heap"] / 2**20, 2),
        "js_heap_end_mb": round(last["heap"] / 2**20, 2),
        "dom_nodes_start": first["nodes"],
        "dom_nodes_end": last["nodes"],
    }
