"""ros2/exolink_msgs is a colcon package whose definitions hash to the keys on the wire.

The package's msg/ and srv/ are links to the appliance's own files; this hashes what the package
holds, in a type store of its own (rosbags' Jazzy types plus the package), and compares with the
table the appliance's keys use and with the key a publisher or service puts on the wire."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from exolink import messaging
from exolink.wire import srvtypes

PKG = Path(__file__).resolve().parents[1] / "ros2" / "exolink_msgs"
TABLE = json.loads(messaging.TYPE_HASHES.read_text())
# What ROS 2 Jazzy advertises for std_srvs (rosidl-generated type hashes).
JAZZY_STD_SRVS = {
    "std_srvs/srv/Trigger": "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f",
    "std_srvs/srv/SetBool": "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a",
}


def _files(kind: str) -> list[Path]:
    return sorted((PKG / kind).glob(f"*.{kind}"))


def test_the_package_builds_every_definition_it_holds() -> None:
    cmake = (PKG / "CMakeLists.txt").read_text()
    listed = re.findall(r'"((?:msg|srv)/\w+\.(?:msg|srv))"', cmake)
    held = [f"{p.parent.name}/{p.name}" for p in _files("msg") + _files("srv")]
    assert sorted(listed) == sorted(held) and held
    xml = ET.parse(PKG / "package.xml").getroot()
    assert xml.findtext("name") == "exolink_msgs" and "project(exolink_msgs)" in cmake
    depends = {d.text for d in xml.findall("depend")}
    used = {
        m.split("/")[0]
        for p in _files("msg") + _files("srv")
        for m in re.findall(r"^\s*([a-z_]+/[A-Za-z]+)", p.read_text(), re.M)
    }
    assert used <= depends, used - depends
    assert f"DEPENDENCIES {' '.join(sorted(depends))}" in cmake
    groups = [g.text for g in xml.findall("member_of_group")]
    assert groups == ["rosidl_interface_packages"]


def test_message_hashes_are_the_ones_on_the_wire() -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for p in _files("msg"):
        types.update(get_types_from_msg(p.read_text(), f"exolink_msgs/msg/{p.stem}"))
    store.register(types)
    for name in types:
        h = str(store.hash_rihs01(name))
        assert TABLE[name] == h, name
        key = messaging.topic_key(0, "h2", "x", name)
        assert key.endswith(f"/exolink_msgs::msg::dds_::{name.rsplit('/', 1)[1]}_/{h}")


def test_service_hashes_are_the_ones_on_the_wire() -> None:
    defs = {
        f"exolink_msgs/srv/{p.stem}": tuple(p.read_text().split("\n---\n")) for p in _files("srv")
    } | srvtypes.STD_SRVS
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, (req, resp) in defs.items():
        store.register(srvtypes.service_fielddefs(name, req, resp))
    hashes = srvtypes.service_hashes(store, list(defs))
    for name, h in hashes.items():
        assert TABLE[name] == h, name
        pkg, _, short = name.split("/")
        assert messaging.topic_key(0, "h2", "s", name).endswith(f"/{pkg}::srv::dds_::{short}_/{h}")
    assert {k: hashes[k] for k in JAZZY_STD_SRVS} == JAZZY_STD_SRVS
    # And an independent RIHS01 implementation (zenoh-ros2-sdk's) agrees on our own services.
    sdk_utils = pytest.importorskip("zenoh_ros2_sdk.utils")
    for name, (req, resp) in defs.items():
        assert sdk_utils.compute_service_type_hash(name, req or "# empty\n", resp) == hashes[name]
