"""Config validation: every error names the file, the line, the path and what was expected."""

from __future__ import annotations

from pathlib import Path

import pytest

from exolink.config import ConfigError, bundled, load, node_params, parse

GOOD = """\
device: exo-01
can:
  interface: socketcan
  channel: can0
nodes:
  - name: simulator
    plugin: simulator
    params:
      maccepa_boards: [0, 1]
"""


def test_bundled_configs_load() -> None:
    for name in ("sim", "board"):
        cfg = load(bundled(name))
        assert cfg.device
        assert cfg.nodes


def test_shipped_configs_leave_motion_to_the_controller_manager() -> None:
    """One writer of motion: in both shipped configs the manager runs; no other node serves a
    motion command (the h2 sender is gone, the player and the MACCEPA bridge write nothing)."""
    for name in ("sim", "board"):
        cfg = load(bundled(name))
        running = {n.name: n for n in cfg.nodes if n.enabled}
        assert "controller_manager" in running, name
        assert "h2_sender" not in {n.plugin for n in cfg.nodes}, name
        assert cfg.joint_limits().torque_cap == (20, 20, 10, 20, 20, 10), name


def test_limits_have_one_home_and_contradictions_are_refused() -> None:
    """Joint limits live in the top-level `limits:` section only: a node's old limit params
    are refused naming where they go, and limits outside the mechanical ranges (the tester's
    +-180) or min above max are refused naming file, line and path."""
    base = "device: x\nnodes:\n  - {name: cm, plugin: controller_manager, params: {min_angles: [0,0,0,0,0,0]}}\n"
    with pytest.raises(
        ConfigError, match=r"a\.yaml:3: nodes\[0\]\.params\.min_angles: joint limits"
    ):
        parse(base, "a.yaml")
    wide = "device: x\nlimits:\n  joints:\n    r_knee: {min: -180, max: 180}\n"
    with pytest.raises(
        ConfigError, match=r"a\.yaml:4: limits\.joints\.r_knee\.min: -180 deg is outside"
    ):
        parse(wide, "a.yaml")
    crossed = "device: x\nlimits:\n  joints:\n    l_hip: {min: 50, max: 10}\n"
    with pytest.raises(ConfigError, match=r"limits\.joints\.l_hip: min 50 must be below max 10"):
        parse(crossed, "a.yaml")
    cap = "device: x\nlimits:\n  joints:\n    l_hip: {torque: 200}\n"
    with pytest.raises(
        ConfigError, match=r"a\.yaml:4: limits\.joints\.l_hip\.torque: Expected `int` <= 127"
    ):
        parse(cap, "a.yaml")
    unknown = "device: x\nlimits:\n  joints:\n    l_elbow: {max: 10}\n"
    with pytest.raises(ConfigError, match=r"a\.yaml:4: limits\.joints\.l_elbow: unknown key"):
        parse(unknown, "a.yaml")
    lim = parse("device: x\n", "a.yaml").joint_limits()  # no section: safe defaults
    assert lim.torque_cap == (20, 20, 10, 20, 20, 10) and lim.torque_step == (2,) * 6


def test_good_config_and_typed_params() -> None:
    cfg = parse(GOOD, "a.yaml")
    assert cfg.can.bitrate == 1_000_000
    assert node_params(cfg, "simulator").maccepa_boards == [0, 1]


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml: config file not found"):
        load(tmp_path / "nope.yaml")


def test_bad_yaml_syntax_names_line() -> None:
    with pytest.raises(ConfigError) as e:
        parse("device: x\ncan:\n  interface: [socketcan\n", "a.yaml")
    assert str(e.value).startswith("a.yaml:4: invalid YAML: expected ',' or ']'")
    assert "flow sequence at line 3" in str(e.value)


def test_wrong_type_names_path_and_line() -> None:
    text = GOOD.replace("channel: can0", "channel: can0\n  bitrate: fast")
    with pytest.raises(ConfigError) as e:
        parse(text, "a.yaml")
    assert str(e.value) == "a.yaml:5: can.bitrate: Expected `int`, got `str`"


def test_unknown_key_is_an_error() -> None:
    text = GOOD.replace("  channel: can0", "  channel: can0\n  bitrat: 5")
    with pytest.raises(ConfigError) as e:
        parse(text, "a.yaml")
    assert "can.bitrat" in str(e.value) and "unknown key 'bitrat'" in str(e.value)


def test_out_of_range_value() -> None:
    text = GOOD.replace("channel: can0", "channel: can0\n  bitrate: 2000000")
    with pytest.raises(ConfigError) as e:
        parse(text, "a.yaml")
    assert str(e.value) == "a.yaml:5: can.bitrate: Expected `int` <= 1000000"


def test_node_params_validated_against_plugin() -> None:
    text = GOOD.replace("maccepa_boards: [0, 1]", "maccepa_boards: [0, 12]")
    with pytest.raises(ConfigError) as e:
        parse(text, "a.yaml")
    assert str(e.value) == "a.yaml:9: nodes[0].params.maccepa_boards[1]: Expected `int` <= 9"


def test_unknown_node_param() -> None:
    text = GOOD.replace("maccepa_boards: [0, 1]", "speed: 3")
    with pytest.raises(ConfigError) as e:
        parse(text, "a.yaml")
    assert "nodes[0].params.speed: unknown key 'speed'" in str(e.value)


def test_unknown_plugin_lists_available() -> None:
    with pytest.raises(
        ConfigError, match=r"a\.yaml:7: nodes\[0\]\.plugin: unknown node plugin 'warp'"
    ):
        parse(GOOD.replace("plugin: simulator", "plugin: warp"), "a.yaml")


def test_duplicate_node_names() -> None:
    text = GOOD + "  - name: simulator\n    plugin: simulator\n"
    with pytest.raises(ConfigError, match=r"nodes\[1\]\.name: duplicate node 'simulator'"):
        parse(text, "a.yaml")


def test_a_leased_deadline_is_never_the_stricter_one() -> None:
    """A lease loosens the watchdog's judgment of a motion node (exolink.liveness), never
    tightens it: a node whose own deadline was raised above its leased one (a slow machine's
    config) is judged by its own on a lease too. Deadlines by pace: own, idle, leased."""
    text = GOOD + (
        "  - name: controller_manager\n    plugin: controller_manager\n"
        "    heartbeat_deadline_ms: 50\n    leased_deadline_ms: 100\n"
    )
    cfg = parse(text, "a.yaml")
    assert cfg.deadlines_s(cfg.node("controller_manager")) == (0.05, 0.5, 0.1)
    cfg = parse(text.replace("deadline_ms: 50", "deadline_ms: 300"), "a.yaml")
    assert cfg.deadlines_s(cfg.node("controller_manager")) == (0.3, 0.5, 0.3)
    cfg = parse(text.replace("    leased_deadline_ms: 100\n", ""), "a.yaml")
    assert cfg.deadlines_s(cfg.node("controller_manager")) == (0.05, 0.5, 0.05)


def test_missing_required_key() -> None:
    with pytest.raises(ConfigError, match=r"Object missing required field `device`"):
        parse("can: {}\n", "a.yaml")


def test_top_level_not_a_mapping() -> None:
    with pytest.raises(ConfigError, match="expected a mapping"):
        parse("- a\n- b\n", "a.yaml")


def test_duplicate_keys_are_errors_with_both_lines() -> None:
    text = bundled("sim").read_text() + "watchdog:\n  pulse_silence_ms: 5000\n"
    with pytest.raises(ConfigError, match=r":\d+: duplicate key 'watchdog' \(first at line \d+\)"):
        parse(text, "appliance.yaml")


def test_the_pulse_silence_keeps_its_old_h2_name_but_not_both() -> None:
    """``watchdog.pulse_silence_ms`` was ``h2_silence_ms`` before other devices: a lab's config
    with the old name still loads, as the same setting; one with both names is refused by name."""
    sim = bundled("sim").read_text()
    new = parse(sim.replace("pulse_silence_ms: 100", "pulse_silence_ms: 250"), "a.yaml")
    old = parse(sim.replace("pulse_silence_ms: 100", "h2_silence_ms: 250"), "a.yaml")
    assert new.watchdog.silence_ms == old.watchdog.silence_ms == 250
    assert parse(sim.replace("  pulse_silence_ms: 100\n", ""), "a.yaml").watchdog.silence_ms == 100
    both = sim.replace("pulse_silence_ms: 100", "pulse_silence_ms: 100\n  h2_silence_ms: 100")
    with pytest.raises(ConfigError, match="pulse_silence_ms and h2_silence_ms are one setting"):
        parse(both, "a.yaml")
