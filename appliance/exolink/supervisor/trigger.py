"""The experiment trigger: libgpiod v2 edge events (or a simulated source), and a trigger output.

An edge defines the experiment's time zero [thesis 4.3.2.2]: it is published with the kernel's
event timestamp (REALTIME clock, so it lines up with CAN frame stamps) and recorded; nothing is
reset, tools show time since the last trigger from it. The output line lets this board trigger
another one and an EMG recorder, as the thesis' second BeagleBone did.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta

from exolink.config import TriggerConfig
from exolink.errors import TriggerError


@dataclass(frozen=True)
class Edge:
    stamp_ns: int
    rising: bool
    source: str  # gpio | simulated


OnEdge = Callable[[Edge], None]


class GpioTrigger:
    """Edge detection with kernel debounce on one line; a thread blocks in wait_edge_events."""

    def __init__(self, cfg: TriggerConfig, on_edge: OnEdge) -> None:
        import gpiod  # lazy: libgpiod: a board trigger only (a laptop has no GPIO)
        from gpiod.line import Clock
        from gpiod.line import Edge as GEdge

        edge = {"rising": GEdge.RISING, "falling": GEdge.FALLING, "both": GEdge.BOTH}[cfg.edge]
        settings = gpiod.LineSettings(
            edge_detection=edge,
            debounce_period=timedelta(milliseconds=cfg.debounce_ms),
            event_clock=Clock.REALTIME,
        )
        try:
            self.req = gpiod.request_lines(
                cfg.chip, consumer="exolink-trigger", config={cfg.line: settings}
            )
        except FileNotFoundError:
            raise TriggerError(
                f"no GPIO chip {cfg.chip}: check trigger.chip (gpiodetect lists chips)"
            ) from None
        except PermissionError:
            raise TriggerError(
                f"not permitted to open {cfg.chip}: run as root or in the gpio group"
            ) from None
        except OSError as exc:
            raise TriggerError(
                f"cannot request {cfg.chip} line {cfg.line}: {exc.strerror or exc}"
            ) from None
        self.on_edge = on_edge
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True, name="trigger")
        self.thread.start()

    def _loop(self) -> None:
        from gpiod import EdgeEvent  # lazy: libgpiod: a board trigger only

        rising = EdgeEvent.Type.RISING_EDGE
        while not self.stop.is_set():
            if not self.req.wait_edge_events(timedelta(milliseconds=200)):
                continue
            for ev in self.req.read_edge_events():
                self.on_edge(Edge(ev.timestamp_ns, ev.event_type == rising, "gpio"))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(1)
        self.req.release()


class SimulatedTrigger:
    """Rising edges on a period (or only when fired) for the simulated appliance and tests."""

    def __init__(self, cfg: TriggerConfig, on_edge: OnEdge) -> None:
        self.on_edge = on_edge
        self.period = cfg.sim_period_s
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True, name="sim-trigger")
        self.thread.start()

    def _loop(self) -> None:
        while not self.stop.wait(self.period or 3600):
            if self.period:
                self.fire()

    def fire(self) -> None:
        self.on_edge(Edge(time.time_ns(), True, "simulated"))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(1)


class TriggerOutput:
    """Drives the configured output line high for pulse_ms."""

    def __init__(self, chip: str, line: int, pulse_ms: int) -> None:
        import gpiod  # lazy: libgpiod: a board trigger only
        from gpiod.line import Direction, Value

        self.line, self.pulse_s = line, pulse_ms / 1000
        self._active, self._inactive = Value.ACTIVE, Value.INACTIVE
        try:
            self.req = gpiod.request_lines(
                chip,
                consumer="exolink-trigger-out",
                config={
                    line: gpiod.LineSettings(
                        direction=Direction.OUTPUT, output_value=Value.INACTIVE
                    )
                },
            )
        except OSError as exc:
            raise TriggerError(f"cannot drive {chip} line {line}: {exc.strerror or exc}") from None
        self.lock = threading.Lock()

    def fire(self) -> int:
        with self.lock:
            t = time.time_ns()
            self.req.set_value(self.line, self._active)
            time.sleep(self.pulse_s)
            self.req.set_value(self.line, self._inactive)
            return t

    def close(self) -> None:
        self.req.release()


def open_source(cfg: TriggerConfig, on_edge: OnEdge) -> GpioTrigger | SimulatedTrigger | None:
    if cfg.source == "none":
        return None
    if cfg.source == "simulated":
        return SimulatedTrigger(cfg, on_edge)
    return GpioTrigger(cfg, on_edge)


def open_output(cfg: TriggerConfig) -> TriggerOutput | None:
    if cfg.output is None:
        return None
    return TriggerOutput(cfg.output.chip, cfg.output.line, cfg.output.pulse_ms)
