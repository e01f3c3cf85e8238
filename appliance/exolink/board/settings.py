"""The card's settings (``exolink-settings.yaml`` on the boot partition): their schema, and the
checks it cannot say, every error naming the file, line and key. What applying them does to the
board is exolink.board.setup's."""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path
from typing import Annotated, Literal

import msgspec

from exolink.config import ConfigError, DeviceName
from exolink.typed_yaml import decode_yaml

SETTINGS_FILE = "exolink-settings.yaml"


Country = Annotated[str, msgspec.Meta(pattern=r"^[A-Z]{2}$")]
Host = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9.:-]{1,253}$")]


class _Strict(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    pass


class Ethernet(_Strict, frozen=True):
    address: str = "dhcp"  # "dhcp" or CIDR, e.g. 192.168.10.2/24
    gateway: str = ""
    dns: list[Host] = msgspec.field(default_factory=list)


class Wifi(_Strict, frozen=True):
    country: Country = "DE"
    ssid: Annotated[str, msgspec.Meta(max_length=32)] = ""
    password: str = ""


Role = Literal["observer", "operator", "admin"]
Password = Annotated[str, msgspec.Meta(pattern=r"^[^:\s]{12,128}$")]


class ZenohAuth(_Strict, frozen=True):
    # Roles that get a laptop login file on the card; [] = no logins at all (open port).
    logins: list[Role] = msgspec.field(default_factory=lambda: ["operator", "observer"])
    passwords: dict[Role, Password] = msgspec.field(default_factory=dict)  # else made up
    tls: bool = False  # laptops connect with TLS (a CA made on the board) on TLS_PORT


class Ssh(_Strict, frozen=True):
    authorized_keys: list[str] = msgspec.field(default_factory=list)
    password: str = ""


class BoardSettings(_Strict, frozen=True):
    device: DeviceName
    ethernet: Ethernet = msgspec.field(default_factory=Ethernet)
    wifi: Wifi = msgspec.field(default_factory=Wifi)
    time_servers: list[Host] = msgspec.field(default_factory=lambda: ["pool.ntp.org"])
    zenoh: ZenohAuth = msgspec.field(default_factory=ZenohAuth)
    ssh: Ssh = msgspec.field(default_factory=Ssh)
    simulate: bool = False


def load_settings(path: Path) -> BoardSettings:
    """Parse and check the card's settings; every error names the file, line and key."""
    try:
        text = path.read_text(encoding="utf-8-sig")  # Windows editors add a BOM
    except FileNotFoundError:
        raise ConfigError(f"{path}: settings file not found") from None
    settings, _ = decode_yaml(text, str(path), BoardSettings)
    _check(settings, str(path))
    return settings


def _check(s: BoardSettings, source: str) -> None:
    """What the schema cannot say: addresses that parse, a Wi-Fi password WPA accepts."""
    eth = s.ethernet
    if eth.address != "dhcp":
        try:
            ipaddress.ip_interface(eth.address)
        except ValueError:
            raise ConfigError(
                f"{source}: ethernet.address: expected 'dhcp' or an address with prefix "
                f"like 192.168.10.2/24, got {eth.address!r}"
            ) from None
        if "/" not in eth.address:
            raise ConfigError(f"{source}: ethernet.address: {eth.address!r} needs a /prefix")
    if eth.gateway:
        try:
            ipaddress.ip_address(eth.gateway)
        except ValueError:
            raise ConfigError(
                f"{source}: ethernet.gateway: not an IP address: {eth.gateway!r}"
            ) from None
    if s.wifi.ssid and not 8 <= len(s.wifi.password) <= 63:
        raise ConfigError(f"{source}: wifi.password: WPA2 needs 8 to 63 characters")
    for i, key in enumerate(s.ssh.authorized_keys):
        if not re.match(r"^(ssh-|ecdsa-|sk-)\S+ \S+", key):
            raise ConfigError(
                f"{source}: ssh.authorized_keys[{i}]: not an OpenSSH public key line "
                "(expected 'ssh-ed25519 AAAA... comment')"
            )
