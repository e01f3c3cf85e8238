"""Board setup from the card's settings file, applied to a scratch root (the live-only commands:
hostname, chpasswd, SSH host keys, growing the partition, run only on the board and in the qemu
boot test of the image)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from benchmarks.harness import free_port
from exolink import messaging
from exolink.board import settings as boardsettings
from exolink.board import setup as boardsetup
from exolink.config import ConfigError, ZenohConfig, bundled, load

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "services/boot/exolink-settings.yaml"


@pytest.fixture
def card(tmp_path: Path) -> tuple[Path, Path]:
    """A boot partition with the shipped settings and a root with the image's appliance.yaml."""
    boot, root = tmp_path / "boot", tmp_path / "root"
    boot.mkdir()
    shutil.copy(SHIPPED, boot / boardsettings.SETTINGS_FILE)
    (root / "etc/exolink").mkdir(parents=True)
    text = bundled("board").read_text()
    (root / "etc/exolink/appliance.yaml").write_text(text)
    return boot, root


def edit(boot: Path, **changes: object) -> None:
    """Change keys the way a user would, in the shipped file's YAML."""
    path = boot / boardsettings.SETTINGS_FILE
    data = yaml.safe_load(path.read_text())
    for dotted, value in changes.items():
        *parents, leaf = dotted.split("__")
        node = data
        for p in parents:
            node = node[p]
        node[leaf] = value
    path.write_text(yaml.safe_dump(data))


def apply(boot: Path, root: Path) -> boardsetup.Plan:
    s = boardsettings.load_settings(boot / boardsettings.SETTINGS_FILE)
    return boardsetup.apply(s, boot, root)


def test_shipped_settings_make_a_dhcp_board_with_a_zenoh_login(card: tuple[Path, Path]) -> None:
    boot, root = card
    plan = apply(boot, root)
    assert plan.first_boot
    assert (root / "etc/hostname").read_text() == "exo-01\n"
    eth = (root / "etc/systemd/network/10-exolink-ethernet.network").read_text()
    assert "DHCP=yes" in eth and "MulticastDNS=yes" in eth
    assert not (root / "etc/systemd/network/20-exolink-wifi.network").exists()
    assert not (root / "etc/wpa_supplicant/wpa_supplicant-wlan0.conf").exists()
    assert "NTP=pool.ntp.org" in (root / "etc/systemd/timesyncd.conf.d/exolink.conf").read_text()
    assert (root / "etc/default/exolink").read_text() == "EXOLINK_UP_ARGS=\n"
    users = _users(root)
    assert set(users) == {"exolink", "observer", "operator", "admin"}
    assert all(len(pw) >= 16 for pw in users.values()) and len(set(users.values())) == 4
    for role in ("operator", "observer"):
        assert users[role] in (boot / boardsetup.laptop_file(role)).read_text()
    assert not (boot / boardsetup.laptop_file("admin")).exists()  # not asked for
    assert (root / "etc/exolink/zenoh-users.txt").stat().st_mode & 0o777 == 0o640
    board = (root / "etc/exolink/zenoh.json5").read_text()
    assert '"user": "exolink"' in board and users["exolink"] in board


def _users(root: Path) -> dict[str, str]:
    lines = (root / "etc/exolink/zenoh-users.txt").read_text().splitlines()
    return dict(line.split(":", 1) for line in lines)


def test_generated_zenoh_passwords_survive_later_boots(card: tuple[Path, Path]) -> None:
    boot, root = card
    apply(boot, root)
    first = _users(root)
    apply(boot, root)
    assert _users(root) == first
    edit(boot, zenoh__passwords={"operator": "chosen-by-the-lab"}, zenoh__logins=["admin"])
    apply(boot, root)
    assert _users(root) == {**first, "operator": "chosen-by-the-lab"}
    assert [f.name for f in boot.glob("exolink-*.json5")] == ["exolink-admin.json5"]


def test_short_zenoh_password_is_refused(card: tuple[Path, Path]) -> None:
    boot, _ = card
    edit(boot, zenoh__passwords={"operator": "short"})
    with pytest.raises(ConfigError, match=r"zenoh\.passwords"):
        boardsettings.load_settings(boot / boardsettings.SETTINGS_FILE)


def test_device_name_goes_into_appliance_yaml_keeping_comments(card: tuple[Path, Path]) -> None:
    boot, root = card
    edit(boot, device="exo-07")
    apply(boot, root)
    text = (root / "etc/exolink/appliance.yaml").read_text()
    assert "device: exo-07                 # names this board on Zenoh" in text
    assert load(root / "etc/exolink/appliance.yaml").device == "exo-07"
    assert "127.0.1.1\texo-07" in (root / "etc/hosts").read_text()


def test_broken_appliance_yaml_is_left_alone_and_the_board_stays_reachable(
    card: tuple[Path, Path],
) -> None:
    """A hand edit broke the config: the supervisor will refuse it (exit 3, unit stays stopped),
    but network and SSH settings must still apply, or nobody can log in to fix it."""
    boot, root = card
    path = root / "etc/exolink/appliance.yaml"
    broken = path.read_text().replace("heartbeat_deadline_ms: 500", "heartbeat_deadline_ms: -5")
    path.write_text(broken)
    edit(boot, device="exo-07")
    plan = apply(boot, root)
    assert path.read_text() == broken
    [problem] = plan.problems
    assert "watchdog.heartbeat_deadline_ms" in problem and "left unchanged" in problem
    assert (root / "etc/hostname").read_text() == "exo-07\n"
    assert (root / "etc/systemd/network/10-exolink-ethernet.network").exists()
    assert (root / "home/exo/.ssh/authorized_keys").exists()


def test_static_address_and_wifi(card: tuple[Path, Path]) -> None:
    boot, root = card
    edit(
        boot,
        ethernet__address="192.168.10.2/24",
        ethernet__gateway="192.168.10.1",
        ethernet__dns=["192.168.10.1"],
        wifi__ssid="IEEE",
        wifi__password="password",
    )
    apply(boot, root)
    eth = (root / "etc/systemd/network/10-exolink-ethernet.network").read_text()
    assert "Address=192.168.10.2/24\nGateway=192.168.10.1\nDNS=192.168.10.1" in eth
    assert "DHCP" not in eth
    wpa = (root / "etc/wpa_supplicant/wpa_supplicant-wlan0.conf").read_text()
    # IEEE 802.11i-2004 annex H.4 test vector: passphrase "password", SSID "IEEE".
    assert "psk=f42c6fc52df0ebef9ebb4b90b38a5f902e83fe1b135a70e23aed762e9710a12e" in wpa
    assert f"ssid={b'IEEE'.hex()}" in wpa and "password" not in wpa
    assert (root / "etc/wpa_supplicant/wpa_supplicant-wlan0.conf").stat().st_mode & 0o777 == 0o600
    assert (root / "etc/systemd/network/20-exolink-wifi.network").exists()
    # Turning Wi-Fi off again removes it.
    edit(boot, wifi__ssid="")
    apply(boot, root)
    assert not (root / "etc/wpa_supplicant/wpa_supplicant-wlan0.conf").exists()


def test_simulate_runs_the_supervisor_with_sim_and_keeps_the_bus_on_loopback(
    card: tuple[Path, Path],
) -> None:
    boot, root = card
    edit(boot, simulate=True)
    apply(boot, root)
    assert (root / "etc/default/exolink").read_text() == "EXOLINK_UP_ARGS=--sim\n"
    lo = (root / "etc/systemd/network/05-exolink-sim-lo.network").read_text()
    assert "Name=lo" in lo and "Destination=224.0.0.0/4" in lo


def test_ssh_keys_are_written_and_bad_keys_refused(card: tuple[Path, Path]) -> None:
    boot, root = card
    key = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIB0x lab@laptop"
    edit(boot, ssh__authorized_keys=[key])
    apply(boot, root)
    assert (root / "home/exo/.ssh/authorized_keys").read_text() == key + "\n"
    edit(boot, ssh__authorized_keys=["AAAAC3NzaC1lZDI1NTE5 missing type"])
    with pytest.raises(ConfigError, match=r"ssh.authorized_keys\[0\]: not an OpenSSH public key"):
        apply(boot, root)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"ethernet__address": "192.168.10.300/24"}, "ethernet.address: expected 'dhcp'"),
        ({"ethernet__address": "192.168.10.2"}, "needs a /prefix"),
        ({"ethernet__gateway": "router"}, "ethernet.gateway: not an IP address"),
        ({"wifi__ssid": "lab", "wifi__password": "short"}, "wifi.password: WPA2 needs 8 to 63"),
        ({"wifi__country": "germany"}, "wifi.country"),
        ({"device": "exo 01"}, "device"),
    ],
)
def test_bad_settings_name_the_key_and_change_nothing(
    card: tuple[Path, Path], changes: dict[str, object], message: str
) -> None:
    boot, root = card
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    edit(boot, **changes)
    with pytest.raises(ConfigError, match=message):
        apply(boot, root)
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before


def test_unknown_key_reports_file_and_line(card: tuple[Path, Path]) -> None:
    boot, _ = card
    path = boot / boardsettings.SETTINGS_FILE
    path.write_text(path.read_text() + "wify:\n  ssid: lab\n")
    n = len(path.read_text().splitlines()) - 1
    with pytest.raises(ConfigError, match=rf"exolink-settings.yaml:{n}: wify: unknown key"):
        boardsettings.load_settings(path)


def test_cli_applies_and_reports_errors_with_exit_code(card: tuple[Path, Path]) -> None:
    boot, root = card
    cmd = [sys.executable, "-m", "exolink.cli.main", "board-setup", "--boot", str(boot)]
    ok = subprocess.run([*cmd, "--root", str(root)], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert (root / "etc/hostname").exists()
    edit(boot, ethernet__address="nope")
    bad = subprocess.run([*cmd, "--root", str(root)], capture_output=True, text=True)
    assert bad.returncode == 3
    assert "ethernet.address" in bad.stderr and "Traceback" not in bad.stderr


def test_rendered_zenoh_login_admits_the_laptop_file_and_refuses_others(
    card: tuple[Path, Path], tmp_path: Path
) -> None:
    """Real Zenoh sessions: the board's rendered config as router, the card's laptop file as client."""
    boot, root = card
    apply(boot, root)
    board_cfg = root / "etc/exolink/zenoh.json5"
    text = board_cfg.read_text().replace(
        "/etc/exolink/zenoh-users.txt", str(root / "etc/exolink/zenoh-users.txt")
    )
    board_cfg.write_text(text)
    port = free_port()
    cfg = messaging.session_config(
        ZenohConfig(config_file=str(board_cfg)), listen=[f"tcp/127.0.0.1:{port}"], mode="router"
    )
    router = messaging.open_session(cfg, "router")
    try:
        at = f"tcp/127.0.0.1:{port}"
        laptop = messaging.open_client_session(at, str(boot / boardsetup.laptop_file("observer")))
        laptop.close()
        with pytest.raises(messaging.Unreachable):
            messaging.open_client_session(at)
        wrong = tmp_path / "wrong.json5"
        wrong.write_text('{transport: {auth: {usrpwd: {user: "observer", password: "guess"}}}}')
        with pytest.raises(messaging.Unreachable):
            messaging.open_client_session(at, str(wrong))
    finally:
        router.close()


def test_tls_login_needs_the_boards_ca(card: tuple[Path, Path], tmp_path: Path) -> None:
    """TLS with a CA made by openssl as on the board: the laptop file (CA inline) connects over
    tls/, the same login without the CA and plain TCP to the TLS port are refused."""
    boot, root = card
    edit(boot, zenoh__tls=True)
    apply(boot, root)
    appliance = (root / "etc/exolink/appliance.yaml").read_text()
    assert f"listen: {json.dumps(boardsetup.LISTEN_TLS)}" in appliance
    assert (root / boardsetup.TLS_DIR / "ca.key").stat().st_mode & 0o777 == 0o640
    board_cfg = root / "etc/exolink/zenoh.json5"
    board_cfg.write_text(board_cfg.read_text().replace("/etc/exolink/", f"{root}/etc/exolink/"))
    port = free_port()
    cfg = messaging.session_config(
        ZenohConfig(config_file=str(board_cfg)), listen=[f"tls/127.0.0.1:{port}"], mode="router"
    )
    router = messaging.open_session(cfg, "router")
    try:
        login = boot / boardsetup.laptop_file("operator")
        assert f"--at tls/exo-01.local:{boardsetup.TLS_PORT}" in login.read_text()
        messaging.open_client_session(f"tls/localhost:{port}", str(login)).close()
        data = json5_body(login)
        del data["transport"]["link"]
        no_ca = tmp_path / "no-ca.json5"
        no_ca.write_text(json.dumps(data))
        with pytest.raises(messaging.Unreachable):
            messaging.open_client_session(f"tls/localhost:{port}", str(no_ca))
        with pytest.raises(messaging.Unreachable):
            messaging.open_client_session(f"tcp/127.0.0.1:{port}", str(login))
    finally:
        router.close()


def json5_body(path: Path) -> dict:
    """A login file without its leading // comment line."""
    return json.loads(
        "\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("//"))
    )


def test_missing_laptop_file_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="Zenoh config file not found"):
        messaging.open_client_session("tcp/127.0.0.1:1", "/nonexistent/exolink-observer.json5")
