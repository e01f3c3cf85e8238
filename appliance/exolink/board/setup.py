"""Board setup from the card: turns the one file users edit on the boot partition into /etc.

A lab engineer flashes a card on a laptop, edits ``exolink-settings.yaml`` on its FAT partition
(the only part every OS can write) and boots. ``exolink-setup.service`` runs this before the
network and the supervisor on every boot, so editing the file later and rebooting also works. It
renders files (pure, tested on the host against a scratch root) and then runs the few commands
that only make sense on the live board (hostname, passwords, SSH host keys, growing the data
partition), only when the root is ``/``.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import secrets
import socket
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from exolink import roles
from exolink.board.settings import BoardSettings
from exolink.config import ConfigError, parse

log = structlog.get_logger("exolink.board.setup")


def laptop_file(role: str) -> str:
    """The login file of a role on the card's drive (only for the roles the settings ask for)."""
    return f"exolink-{role}.json5"


FIRST_BOOT_DONE = "var/lib/exolink/first-boot.done"
LOGIN_USER = "exo"
SERVICE_GROUP = "exolink"
ZENOH_USERS = "etc/exolink/zenoh-users.txt"
TLS_DIR = "etc/exolink/tls"
TLS_PORT = 7448
# The supervisor's listen endpoints: with TLS, plain TCP stays on loopback for the nodes.
LISTEN_PLAIN = ["tcp/0.0.0.0:7447"]
LISTEN_TLS = ["tcp/127.0.0.1:7447", f"tls/0.0.0.0:{TLS_PORT}"]


@dataclass
class Plan:
    """What applying the settings does to the root and the boot partition."""

    files: dict[str, tuple[str, int]] = field(default_factory=dict)  # path -> (text, mode)
    remove: list[str] = field(default_factory=list)
    boot_files: dict[str, str] = field(default_factory=dict)  # written back to the boot partition
    boot_remove: list[str] = field(default_factory=list)
    first_boot: bool = False  # also regenerate SSH host keys and grow the data partition
    problems: list[str] = field(default_factory=list)  # applied anyway, logged as errors


def _network(s: BoardSettings) -> dict[str, str]:
    """systemd-networkd: DHCP or static on Ethernet, DHCP on Wi-Fi, mDNS (<device>.local) on both.

    Link-local addressing stays on, so a laptop on a direct cable reaches the board without DHCP.
    """
    eth = s.ethernet
    lines = ["[Match]", "Name=eth* en*", "", "[Network]"]
    if eth.address == "dhcp":
        lines.append("DHCP=yes")
    else:
        lines.append(f"Address={eth.address}")
        if eth.gateway:
            lines.append(f"Gateway={eth.gateway}")
    lines += [f"DNS={d}" for d in eth.dns]
    lines += ["LinkLocalAddressing=ipv4", "MulticastDNS=yes", ""]
    out = {"etc/systemd/network/10-exolink-ethernet.network": "\n".join(lines)}
    if s.simulate:  # the simulated CAN bus (udp multicast) stays on this board
        out["etc/systemd/network/05-exolink-sim-lo.network"] = (
            "[Match]\nName=lo\n\n[Route]\nDestination=224.0.0.0/4\n"
        )
    if s.wifi.ssid:
        out["etc/systemd/network/20-exolink-wifi.network"] = (
            "[Match]\nName=wl*\n\n[Network]\nDHCP=yes\nMulticastDNS=yes\n"
        )
    return out


def _wpa(s: BoardSettings) -> str:
    """The PSK is derived here (PBKDF2, as wpa_passphrase does): no quoting rules, no plain text."""
    psk = hashlib.pbkdf2_hmac("sha1", s.wifi.password.encode(), s.wifi.ssid.encode(), 4096, 32)
    return (
        "ctrl_interface=DIR=/run/wpa_supplicant GROUP=netdev\n"
        f"country={s.wifi.country}\n"
        "network={\n"
        f"    ssid={s.wifi.ssid.encode().hex()}\n"
        f"    psk={psk.hex()}\n"
        "}\n"
    )


def _zenoh_passwords(s: BoardSettings, root: Path) -> dict[str, str]:
    """Per login: the card's password, else the one made up on an earlier boot, else new."""
    earlier: dict[str, str] = {}
    users = root / ZENOH_USERS
    if users.exists():
        for line in users.read_text().splitlines():
            user, _, password = line.partition(":")
            if password:
                earlier[user] = password
    out = {}
    for user in (roles.APPLIANCE_USER, *roles.ROLES):
        given = s.zenoh.passwords.get(user) if user in roles.ROLES else None  # type: ignore[call-overload]
        out[user] = given or earlier.get(user) or secrets.token_urlsafe(12)
    return out


def _zenoh(s: BoardSettings, root: Path, plan: Plan) -> None:
    """One Zenoh login per role, and the appliance's own: the router checks the dictionary and
    enforces the roles (exolink.roles); laptop files only for the roles the settings ask for.

    No logins switches authentication and roles off (a closed lab network), which the log says.
    """
    for role in roles.ROLES:
        if role not in s.zenoh.logins:
            plan.boot_remove.append(laptop_file(role))
    if not s.zenoh.logins:
        plan.files["etc/exolink/zenoh.json5"] = ("{}\n", 0o640)
        plan.remove.append(ZENOH_USERS)
        log.warning("zenoh authentication is off", why="zenoh.logins is empty in the settings")
        return
    passwords = _zenoh_passwords(s, root)
    own = {"user": roles.APPLIANCE_USER, "password": passwords[roles.APPLIANCE_USER]}
    board: dict[str, Any] = {
        "transport": {"auth": {"usrpwd": {**own, "dictionary_file": "/" + ZENOH_USERS}}}
    }
    at = f"tcp/{s.device}.local:7447"
    ca = ""
    if s.zenoh.tls:
        ca = base64.b64encode(tls_files(root / TLS_DIR, s.device)["ca.pem"].read_bytes()).decode()
        board["transport"]["link"] = {
            "tls": {
                "listen_private_key": f"/{TLS_DIR}/server.key",
                "listen_certificate": f"/{TLS_DIR}/server.pem",
            }
        }
        at = f"tls/{s.device}.local:{TLS_PORT}"
    plan.files["etc/exolink/zenoh.json5"] = (json.dumps(board, indent=2) + "\n", 0o640)
    plan.files[ZENOH_USERS] = ("".join(f"{u}:{pw}\n" for u, pw in passwords.items()), 0o640)
    for role in s.zenoh.logins:
        laptop: dict[str, Any] = {
            "transport": {"auth": {"usrpwd": {"user": role, "password": passwords[role]}}}
        }
        if ca:  # the board's own CA, inline: the laptop verifies it talks to this board
            laptop["transport"]["link"] = {"tls": {"root_ca_certificate_base64": ca}}
        name = laptop_file(role)
        plan.boot_files[name] = (
            f"// Zenoh login of role {role} on {s.device}: on the laptop, "
            f"exolink --zenoh-config {name} --at {at} status\n"
            + json.dumps(laptop, indent=2)
            + "\n"
        )


def tls_files(tls_dir: Path, device: str) -> dict[str, Path]:
    """The board's CA and its server certificate (openssl), made once per device name.

    The CA key never leaves the board; laptops get ca.pem inside their login files and check
    that the server's certificate names ``<device>.local`` (or localhost through a tunnel).
    """
    files = {n: tls_dir / n for n in ("ca.key", "ca.pem", "server.key", "server.pem")}
    names = [f"DNS:{device}.local", f"DNS:{device}", "DNS:localhost", "IP:127.0.0.1"]
    marker = tls_dir / "names"
    have = all(f.exists() for f in (*files.values(), marker))
    if have and marker.read_text() == ",".join(names):
        return files
    tls_dir.mkdir(parents=True, exist_ok=True)
    os.chmod(tls_dir, 0o750)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]

    def openssl(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=tls_dir)

    ca_ext = ["-addext", "basicConstraints=critical,CA:TRUE"]
    ca_ext += ["-addext", "keyUsage=critical,keyCertSign,cRLSign"]
    openssl("req", "-x509", *ec, "-days", "3650", "-keyout", "ca.key", "-out", "ca.pem", *ca_ext,
            "-subj", f"/CN=exolink {device} CA")  # fmt: skip
    openssl(
        "req", *ec, "-keyout", "server.key", "-out", "server.csr", "-subj", f"/CN={device}.local"
    )
    (tls_dir / "server.ext").write_text(
        f"subjectAltName={','.join(names)}\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth\n"
    )
    openssl("x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
            "-CAcreateserial", "-out", "server.pem", "-days", "3650", "-extfile", "server.ext")  # fmt: skip
    for f in files.values():
        os.chmod(f, 0o640 if f.suffix == ".key" else 0o644)
    marker.write_text(",".join(names))
    return files


def _listen_in_config(text: str, endpoints: list[str]) -> str:
    """Set ``zenoh.listen`` when it is one of the two shipped values (a hand edit stays)."""
    for known in (LISTEN_PLAIN, LISTEN_TLS):
        line = f"  listen: {json.dumps(known)}"
        if line in text:
            return text.replace(line, f"  listen: {json.dumps(endpoints)}", 1)
    return text


def _device_in_config(text: str, device: str) -> str:
    """Replace the top-level ``device:`` value, keeping the file's comments and layout."""
    new, n = re.subn(r"(?m)^device:[ \t]*[^#\n]*?([ \t]*(#.*)?)$", rf"device: {device}\1", text)
    if n != 1:
        raise ConfigError("appliance.yaml: expected exactly one top-level 'device:' line")
    return new


def plan(s: BoardSettings, root: Path) -> Plan:
    p = Plan()
    p.files["etc/hostname"] = (f"{s.device}\n", 0o644)
    p.files["etc/hosts"] = (
        f"127.0.0.1\tlocalhost\n127.0.1.1\t{s.device}\n::1\tlocalhost ip6-localhost ip6-loopback\n",
        0o644,
    )
    for path, text in _network(s).items():
        p.files[path] = (text, 0o644)
    if not s.wifi.ssid:
        p.remove.append("etc/systemd/network/20-exolink-wifi.network")
    if not s.simulate:
        p.remove.append("etc/systemd/network/05-exolink-sim-lo.network")
    wpa = "etc/wpa_supplicant/wpa_supplicant-wlan0.conf"
    if s.wifi.ssid:
        p.files[wpa] = (_wpa(s), 0o600)
    else:
        p.remove.append(wpa)
    servers = " ".join(s.time_servers)
    p.files["etc/systemd/timesyncd.conf.d/exolink.conf"] = (f"[Time]\nNTP={servers}\n", 0o644)
    _zenoh(s, root, p)
    args = "--sim" if s.simulate else ""
    p.files["etc/default/exolink"] = (f"EXOLINK_UP_ARGS={args}\n", 0o644)
    appliance = root / "etc/exolink/appliance.yaml"
    if appliance.exists():
        # A broken appliance.yaml (a hand edit over ssh) is left as it is and does not hold back
        # the network and SSH settings: they are how the engineer reaches the board to fix it.
        # The supervisor refuses the file with its line (exit 3) and systemd leaves it stopped.
        try:
            text = _device_in_config(appliance.read_text(), s.device)
            listen = LISTEN_TLS if s.zenoh.tls and s.zenoh.logins else LISTEN_PLAIN
            text = _listen_in_config(text, listen)
            parse(text, str(appliance))
        except ConfigError as exc:
            p.problems.append(f"{exc} (left unchanged; device name applied on the next boot)")
        else:
            p.files["etc/exolink/appliance.yaml"] = (text, 0o640)
    home = f"home/{LOGIN_USER}/.ssh/authorized_keys"
    p.files[home] = ("".join(k.strip() + "\n" for k in s.ssh.authorized_keys), 0o600)
    p.first_boot = not (root / FIRST_BOOT_DONE).exists()
    return p


def _write(root: Path, rel: str, text: str, mode: int) -> None:
    """Atomic and on the card when it returns: the board is switched off by pulling its power.

    On vfat a rename writes the new directory entry with no size and no first cluster until the
    inode is written back, so the renamed file and its directory are synced again; without that a
    card pulled within ~30 s held no file, or an empty one (tests/kernel/test_fat_writes.py).
    """
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, mode)
    os.replace(tmp, path)
    for synced in (path, path.parent):
        fd = os.open(synced, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def apply(settings: BoardSettings, boot: Path, root: Path) -> Plan:
    """Render and write everything; on the live board (root ``/``) also run the commands."""
    p = plan(settings, root)
    for rel, (text, mode) in p.files.items():
        _write(root, rel, text, mode)
    for rel in p.remove:
        (root / rel).unlink(missing_ok=True)
    for name, text in p.boot_files.items():
        if not (boot / name).exists() or (boot / name).read_text() != text:
            _write(boot, name, text, 0o600)
    for name in p.boot_remove:
        (boot / name).unlink(missing_ok=True)
    if root == Path("/"):
        _run_live(settings, p)
    for problem in p.problems:
        log.error("appliance config not updated", problem=problem)
    log.info(
        "board settings applied",
        device=settings.device,
        wifi=bool(settings.wifi.ssid),
        ethernet=settings.ethernet.address,
        zenoh_logins=settings.zenoh.logins,
        simulate=settings.simulate,
        files=len(p.files),
    )
    return p


def _run_live(settings: BoardSettings, p: Plan) -> None:
    socket.sethostname(settings.device)
    _own("/etc/exolink/zenoh.json5", "/etc/exolink/zenoh-users.txt", "/etc/exolink/appliance.yaml")
    _own(*(str(f) for f in Path("/", TLS_DIR).glob("*")), "/" + TLS_DIR)
    home = Path(f"/home/{LOGIN_USER}/.ssh")
    subprocess.run(["chown", "-R", f"{LOGIN_USER}:{LOGIN_USER}", str(home)], check=True)
    if settings.ssh.password:  # on stdin, never in argv
        subprocess.run(
            ["chpasswd"], input=f"{LOGIN_USER}:{settings.ssh.password}\n", text=True, check=True
        )
    if p.first_boot:
        first_boot()


def _own(*paths: str) -> None:
    """Secrets readable by the supervisor's group, nobody else."""
    for path in paths:
        if os.path.exists(path):
            subprocess.run(["chown", f"root:{SERVICE_GROUP}", path], check=True)


def first_boot() -> None:
    """Once per card: new SSH host keys (no two boards share them), data partition grown to the
    card. The mark is on the data partition: an update's new root slot does not run this again
    (RAUC's post-install handler copies the keys into it)."""
    for key in Path("/etc/ssh").glob("ssh_host_*"):
        key.unlink()
    subprocess.run(["ssh-keygen", "-A"], check=True, capture_output=True)
    log.info("ssh host keys generated")
    _grow_data()
    _write(Path("/"), FIRST_BOOT_DONE, "", 0o644)


DATA_MOUNT = "/data"


def _grow_data() -> None:
    """The image is small; the card is not. The root slots (A/B) have a fixed size, the data
    partition after them (recordings, state) is the last: grow it and its ext4 online (MBR: no
    repart)."""
    src = subprocess.run(
        ["findmnt", "-no", "SOURCE", DATA_MOUNT], capture_output=True, text=True, check=False
    ).stdout.strip()
    m = re.match(r"^(/dev/(?:mmcblk\d+|[sv]d[a-z]))p?(\d+)$", src)
    if not m:
        log.warning("data partition not grown", why=f"unrecognised data device {src!r}")
        return
    disk, part = m.groups()
    r = subprocess.run(
        ["sfdisk", "--force", "--no-reread", "--no-tell-kernel", "-N", part, disk],
        input=", +\n",
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        log.warning("data partition not grown", why=r.stderr.strip()[-200:])
        return
    subprocess.run(["partx", "-u", disk], check=False, capture_output=True)
    r = subprocess.run(["resize2fs", src], capture_output=True, text=True)
    size = subprocess.run(["df", "-h", "--output=size", DATA_MOUNT], capture_output=True, text=True)
    log.info(
        "data filesystem grown",
        device=src,
        ok=r.returncode == 0,
        size=size.stdout.split()[-1] if size.stdout else "?",
    )
