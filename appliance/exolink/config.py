"""The appliance configuration: one YAML file, typed and validated before anything starts.

Every error names the file, the line, the path inside the document (``nodes[2].params.speed``)
and what was expected, so a lab engineer can fix the card's config without reading code.
"""

from __future__ import annotations

import os
from collections.abc import Collection
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import yaml

from exolink.entrypoints import PluginError, node_params_type
from exolink.limits.joints import Limits, LimitsConfig
from exolink.liveness import Pace
from exolink.typed_yaml import ConfigError, decode_yaml, error_at, line_of, prefixed

Port = Annotated[int, msgspec.Meta(ge=1, le=65535)]
NodeName = Annotated[str, msgspec.Meta(pattern=r"^[a-z][a-z0-9_]{0,39}$")]
DeviceName = Annotated[str, msgspec.Meta(pattern=r"^[a-zA-Z0-9][a-zA-Z0-9_-]{0,39}$")]
PositiveMs = Annotated[int, msgspec.Meta(ge=1, le=600_000)]
DEFAULT_SILENCE_MS = 100
BoardId = Annotated[int, msgspec.Meta(ge=0, le=9)]

SIM_MULTICAST_GROUP = "239.74.163.2"
# The simulated bus is python-can's interface ``exolink_sim`` (exolink.canbus.simbus). Its datagrams are
# python-can's udp_multicast ones, and configs may name it ``udp_multicast``: the same bus.
SIM_INTERFACE = "exolink_sim"
INTERFACE_ALIASES = {"udp_multicast": SIM_INTERFACE}
# Node params that were joint limits: refused with a pointer to the `limits:` section.
MOVED_TO_LIMITS = ("min_angles", "max_angles", "torque_cap", "stiffness_cap", "max_step_deg")


class _Strict(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    pass


class CanConfig(_Strict, frozen=True):
    interface: Literal["socketcan", "virtual", "exolink_sim", "udp_multicast"] = "socketcan"
    channel: str = "can0"
    bitrate: Annotated[int, msgspec.Meta(ge=10_000, le=1_000_000)] = 1_000_000
    restart_ms: Annotated[int, msgspec.Meta(ge=0, le=10_000)] = 100
    # Bring the interface up through netlink (needs CAP_NET_ADMIN); off for vcan/udp.
    bring_up: bool = True
    # Check that the DCAN1 device-tree overlay is active before using can0.
    require_overlay: bool = False

    @property
    def bus_interface(self) -> str:
        """The python-can interface this opens (``INTERFACE_ALIASES`` resolved)."""
        return INTERFACE_ALIASES.get(self.interface, self.interface)

    @property
    def simulated(self) -> bool:
        """The simulated bus (exolink.canbus.simbus), by either of its names."""
        return self.bus_interface == SIM_INTERFACE


class TriggerOutput(_Strict, frozen=True):
    line: Annotated[int, msgspec.Meta(ge=0, le=511)]
    chip: str = "/dev/gpiochip0"
    pulse_ms: Annotated[int, msgspec.Meta(ge=1, le=10_000)] = 10


class TriggerConfig(_Strict, frozen=True):
    source: Literal["gpio", "simulated", "none"] = "gpio"
    chip: str = "/dev/gpiochip0"
    line: Annotated[int, msgspec.Meta(ge=0, le=511)] = 7
    edge: Literal["rising", "falling", "both"] = "rising"
    debounce_ms: Annotated[int, msgspec.Meta(ge=0, le=1000)] = 5
    # Simulated source only: seconds between generated edges (0 = only on `exolink trigger fire`).
    sim_period_s: Annotated[float, msgspec.Meta(ge=0.0, le=3600.0)] = 0.0
    output: TriggerOutput | None = None


class ZenohConfig(_Strict, frozen=True):
    domain_id: Annotated[int, msgspec.Meta(ge=0, le=232)] = 0
    namespace: Annotated[str, msgspec.Meta(pattern=r"^[a-z0-9_]+(/[a-z0-9_]+)*$")] = "h2"
    listen: list[str] = msgspec.field(default_factory=lambda: ["tcp/0.0.0.0:7447"])
    connect: list[str] = msgspec.field(default_factory=list)
    multicast_scouting: bool = False
    # The ROS 2 distro whose rmw_zenoh laptops run: Humble's has no type hashes in its keys
    # (TypeHashNotSupported) and a 24-byte GID; Jazzy, Kilted and Rolling agree (exolink.wire.rosgraph).
    ros_distro: Literal["jazzy", "kilted", "rolling", "humble"] = "jazzy"
    # Path to a Zenoh JSON5 file with credentials / TLS, merged over the settings above.
    config_file: str | None = None
    # Zenoh's worker threads per appliance process (messaging.zenoh_runtime): 1 hands all of
    # Zenoh's runtimes (rx, tx, accept, net) to one thread, so a sample is not passed between
    # threads on a single core; unset keeps Zenoh's own (about five). ZENOH_RUNTIME wins. The
    # supervisor's router transmits on one thread more (messaging.router_runtime): with one,
    # a message larger than a link's transmit queue (~128 KB) stalled it 5 s and was lost, and
    # with two app threads too.
    threads: Annotated[int, msgspec.Meta(ge=1, le=4)] | None = None


class WatchdogConfig(_Strict, frozen=True):
    heartbeat_deadline_ms: PositiveMs = 500
    # A (re)started node must send its first heartbeat within this. Only availability rides on
    # it, not safety: arming needs every critical node's heartbeat, and a restart already tripped.
    start_grace_ms: PositiveMs = 20_000
    # The device's pulse (exolink.hardware: the H2's joint angles) silent this long trips the
    # watchdog (``silence_ms``). ``h2_silence_ms`` is its name from before other devices: still
    # read, never both.
    pulse_silence_ms: PositiveMs | None = None
    h2_silence_ms: PositiveMs | None = None
    safe_action: Literal["disable", "stop"] = "disable"
    maccepa_boards: list[BoardId] = msgspec.field(default_factory=list)
    trip_on_operator_lost: bool = True
    operator_lost_ms: PositiveMs = 2000
    trip_on_bus_error_passive: bool = True

    def __post_init__(self) -> None:
        if self.pulse_silence_ms is not None and self.h2_silence_ms is not None:
            raise ValueError(
                "pulse_silence_ms and h2_silence_ms are one setting (h2_silence_ms is its old "
                "name): give pulse_silence_ms only"
            )

    @property
    def silence_ms(self) -> int:
        """How long the device's pulse may be silent (default 100 ms: ten H2 periods)."""
        return self.pulse_silence_ms or self.h2_silence_ms or DEFAULT_SILENCE_MS


class Priority(_Strict, frozen=True):
    nice: Annotated[int, msgspec.Meta(ge=-20, le=19)] | None = None
    fifo: Annotated[int, msgspec.Meta(ge=1, le=99)] | None = None
    cpus: list[Annotated[int, msgspec.Meta(ge=0, le=255)]] | None = None


class RestartPolicy(_Strict, frozen=True):
    policy: Literal["always", "on-failure", "never"] = "always"
    backoff_initial_ms: PositiveMs = 200
    backoff_max_ms: PositiveMs = 10_000
    max_restarts: Annotated[int, msgspec.Meta(ge=0, le=1000)] = 5
    window_s: Annotated[float, msgspec.Meta(gt=0, le=86400)] = 60.0


class ClockConfig(_Strict, frozen=True):
    # Take the wall clock from an operator's laptop when no time server disciplines it (a
    # BeagleBone has no battery-backed clock: exolink.board.clock). False on a simulator, whose clock is
    # its host's.
    from_laptop: bool = False


class NodeConfig(_Strict, frozen=True, kw_only=True):
    name: NodeName
    plugin: Annotated[str, msgspec.Meta(pattern=r"^[a-z][a-z0-9_]*$")]
    critical: bool = False
    enabled: bool = True
    restart: RestartPolicy = RestartPolicy()
    priority: Priority = Priority()
    # This node's liveness deadline (default: watchdog.heartbeat_deadline_ms). Motion nodes beat
    # every cycle and get a short one: a hung set-point loop is caught within it.
    heartbeat_deadline_ms: PositiveMs | None = None
    # While the node says its motion runs on a lease the kernel ends by itself (exolink.liveness:
    # the controller manager's timer), it is judged by this one instead (default: its own). A
    # hang then ends the motion at the lease's end; the node checks its lease fits at start.
    # Never shorter than its own (the longer of the two).
    leased_deadline_ms: PositiveMs | None = None
    # A node found late while the kernel had kept it waiting for the CPU (starved, not hung:
    # exolink.supervisor.starving) is judged again until this much silence (default: never;
    # never shorter than its own deadlines). Killing a starved node costs a whole re-import on
    # a core that is already full. Not for a motion node (one with a lease): starved, its
    # motion must end.
    starved_deadline_ms: PositiveMs | None = None
    params: dict[str, Any] = msgspec.field(default_factory=dict)


class ApplianceConfig(_Strict, frozen=True, kw_only=True):
    device: DeviceName
    # The hardware the supervisor guards: an ``exolink.hardware`` entry point (exolink.hardware).
    hardware: str = "h2"
    can: CanConfig = CanConfig()
    zenoh: ZenohConfig = ZenohConfig()
    trigger: TriggerConfig = TriggerConfig()
    watchdog: WatchdogConfig = WatchdogConfig()
    # The lab's joint limits: every motion obeys them, whoever asks (exolink.limits.joints).
    limits: LimitsConfig = LimitsConfig()
    clock: ClockConfig = ClockConfig()
    # Where the appliance keeps what an operator set at run time (stricter joint limits), so it
    # survives a node's restart and a reboot; unset: the supervisor's own working directory
    # (kept while it runs: `make sim`).
    state_dir: str | None = None
    nodes: list[NodeConfig] = msgspec.field(default_factory=list)
    # Where this config came from; set by the loader, not by the file.
    source: str = "<memory>"

    def deadline_s(self, node: NodeConfig, pace: Pace = Pace.OWN) -> float:
        """The node's liveness deadline by the pace its last beat said (exolink.liveness): its
        own, else the watchdog's; idle (nothing to drive) never shorter than the watchdog's;
        leased, its ``leased_deadline_ms`` if set, never shorter than its own (a node whose own
        deadline was raised, say for a slow machine, is not judged tighter on a lease)."""
        own = node.heartbeat_deadline_ms or self.watchdog.heartbeat_deadline_ms
        if pace == Pace.IDLE:
            return max(own, self.watchdog.heartbeat_deadline_ms) / 1000
        if pace == Pace.LEASED:
            return max(own, node.leased_deadline_ms or 0) / 1000
        return own / 1000

    def starved_deadline_s(self, node: NodeConfig) -> float | None:
        """How long a starved node may stay silent (None: it is judged as any late node)."""
        if node.starved_deadline_ms is None:
            return None
        return max(node.starved_deadline_ms / 1000, *self.deadlines_s(node))

    def deadlines_s(self, node: NodeConfig) -> tuple[float, ...]:
        """Its deadlines by ``Pace`` (own, idle, leased): what its beats set its timer by."""
        return tuple(self.deadline_s(node, pace) for pace in Pace)

    def joint_limits(self) -> Limits:
        """The configured limits, checked (parse has refused a config whose are not)."""
        return Limits.configured(self.limits)

    def node(self, name: str) -> NodeConfig:
        for node in self.nodes:
            if node.name == name:
                return node
        known = ", ".join(n.name for n in self.nodes) or "none"
        raise ConfigError(f"{self.source}: no node named {name!r} (configured: {known})")


def parse(
    text: str, source: str = "<memory>", check: Collection[str] | None = None
) -> ApplianceConfig:
    """Parse and validate a config document, and each node's params against its plugin.

    ``check`` names the nodes whose params are validated (None: all). Validating a node imports
    its plugin, so a node process checks only itself and does not load every other node's
    dependencies; the supervisor checks all of them in a throwaway child (``check_all_apart``).
    """
    cfg, root = decode_yaml(text, source, ApplianceConfig)
    try:
        cfg.joint_limits()
    except ValueError as exc:
        path = str(exc).split(":", 1)[0]
        raise ConfigError(f"{source}:{line_of(root, path)}: {exc}") from None
    _check_nodes(cfg, root, check)
    return cfg


def _check_nodes(
    cfg: ApplianceConfig, root: yaml.Node | None, check: Collection[str] | None = None
) -> None:
    seen: set[str] = set()
    for i, node in enumerate(cfg.nodes):
        if node.name in seen:
            line = line_of(root, f"nodes[{i}].name")
            raise ConfigError(f"{cfg.source}:{line}: nodes[{i}].name: duplicate node {node.name!r}")
        seen.add(node.name)
        if node.starved_deadline_ms is not None and node.leased_deadline_ms is not None:
            line = line_of(root, f"nodes[{i}].starved_deadline_ms")
            raise ConfigError(
                f"{cfg.source}:{line}: nodes[{i}].starved_deadline_ms: node {node.name!r} has a "
                "leased_deadline_ms (it moves the joints): a motion node is judged by its own "
                "deadlines, starved or hung"
            )
        for key in node.params:
            if key in MOVED_TO_LIMITS:
                line = line_of(root, f"nodes[{i}].params.{key}")
                raise ConfigError(
                    f"{cfg.source}:{line}: nodes[{i}].params.{key}: joint limits and caps live "
                    "in the top-level `limits:` section (one place for every node: "
                    "limits.max_step_deg, limits.joints.<joint>.min/max/torque/stiffness)"
                )
        if check is not None and node.name not in check:
            continue
        try:
            params = node_params_type(node.plugin)
        except PluginError as exc:
            line = line_of(root, f"nodes[{i}].plugin")
            raise ConfigError(f"{cfg.source}:{line}: nodes[{i}].plugin: {exc}") from None
        try:
            msgspec.convert(node.params, params)
        except msgspec.ValidationError as exc:
            err = error_at(cfg.source, root, prefixed(exc, f"nodes[{i}].params"))
            raise err from None


def load(path: str | Path, check: Collection[str] | None = None) -> ApplianceConfig:
    """Load the appliance config; any problem is a ConfigError naming file, line and path.
    ``check``: as in ``parse``."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror}") from None
    return parse(text, str(p), check)


def check_all_apart(path: str | Path) -> None:
    """Every node's params validated in a forked child that imports every plugin and exits, so
    the supervisor refuses a bad config before it starts anything without keeping numpy, mcap
    and every third-party plugin's imports in its own memory for the life of the board.
    Call before any thread is started (fork)."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: report and leave without running the parent's cleanup
        os.close(r)
        code = 0
        try:
            load(path)
        except ConfigError as exc:
            os.write(w, str(exc).encode())
            code = 3
        except BaseException as exc:  # anything else (a plugin failing to import) also refuses
            os.write(w, f"{path}: cannot validate node params: {exc}".encode())
            code = 3
        os._exit(code)
    os.close(w)
    with os.fdopen(r, "rb") as f:
        message = f.read().decode(errors="replace")
    _, status = os.waitpid(pid, 0)
    if status != 0:
        raise ConfigError(message or f"{path}: params check died (wait status {status})")


def node_params(cfg: ApplianceConfig, name: str) -> Any:
    """The typed params of one configured node (already validated by parse)."""
    node = cfg.node(name)
    return msgspec.convert(node.params, node_params_type(node.plugin))


def bundled(name: str) -> Path:
    """Path of a config shipped in the package (``sim`` or ``board``)."""
    return Path(__file__).with_name("configs") / f"{name}.yaml"
