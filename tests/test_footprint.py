"""What each process loads: a node imports its own plugin and what that plugin uses, nothing
of the other nodes; the supervisor loads no plugin at all (their params are checked in a child
that exits). On one Cortex-A8 core every import is seconds of start time and megabytes kept."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from benchmarks.harness import Appliance, wait_for
from exolink.plugins import available

# Nodes whose every dependency is light: no rosbags (generic CDR) and hence no numpy.
LEAN = {
    "h2_reader",
    "pattern_player",
    "timing_monitor",
    "maccepa_bridge",
}  # exolink.wire.cdr, no typestore
HEAVY = ("numpy", "rosbags", "mcap", "zstandard")


def _dump_modules(tmp_path: Path, monkeypatch) -> Path:  # type: ignore[no-untyped-def]
    """A sitecustomize (real interpreter start, no mock) that writes each exolink process's
    sys.modules at exit to out/<first argument after the module>.json."""
    site, out = tmp_path / "site", tmp_path / "modules"
    site.mkdir()
    out.mkdir()
    (site / "sitecustomize.py").write_text(
        "import atexit, json, sys\n"
        "def _dump():\n"
        "    args = [a for a in sys.argv[1:] if not a.startswith('-')]\n"
        "    name = args[0] if args else 'unknown'\n"
        f"    with open({str(out)!r} + '/' + name + '.json', 'w') as f:\n"
        "        json.dump(sorted(sys.modules), f)\n"
        "atexit.register(_dump)\n"
    )
    monkeypatch.setenv("PYTHONPATH", str(site))
    return out


def test_each_node_imports_only_its_own_plugin(write_config, spawn, tmp_path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    out = _dump_modules(tmp_path, monkeypatch)
    nodes = yaml.safe_load(write_config().read_text())["nodes"]
    for n in nodes:  # the recorder records: it writes schemas, as on the board
        if n["plugin"] == "recorder":
            n["params"] |= {"autostart": True, "directory": str(tmp_path / "rec")}
    cfg = write_config(nodes=nodes)
    plugin_modules = {v.split(":")[0] for v in available().values()}
    names = [n["name"] for n in nodes]
    assert "recorder" in names
    app = Appliance(cfg, spawn)
    st = app.status()
    written = lambda: json.loads(app.cli("record", "status", "--json").stdout).get("written")  # noqa: E731
    wait_for(lambda: int(written() or 0) > 0, timeout=30)
    assert {n["name"] for n in st["nodes"]} == set(names)
    # Forked from the zygote, itself a fork of the supervisor (same cmdline, its own name),
    # and re-parented to the supervisor that waits for them.
    assert st["zygote_pid"]
    assert Path(f"/proc/{st['zygote_pid']}/comm").read_text().strip() == "exo-zygote"
    sup_cmdline = Path(f"/proc/{st['pid']}/cmdline").read_bytes()
    for n in st["nodes"]:
        stat = Path(f"/proc/{n['pid']}/stat").read_text()
        assert int(stat.rsplit(")", 1)[1].split()[1]) == st["pid"], n
        assert Path(f"/proc/{n['pid']}/comm").read_text().strip() == f"exo-{n['name']}"[:15]
        assert Path(f"/proc/{n['pid']}/cmdline").read_bytes() == sup_cmdline, n
    # No Zenoh shared-memory pool: Zenoh 1.x maps 16 MiB per session for messages over 3 KiB
    # (the status reply just asked for is one), 18 MB of the supervisor's PSS on x86.
    for pid in [st["pid"], *(n["pid"] for n in st["nodes"])]:
        shm = [ln for ln in Path(f"/proc/{pid}/maps").read_text().splitlines() if ".zenoh" in ln]
        assert not shm, (pid, shm[:2])
    app.proc.stop()
    wait_for(lambda: all((out / f"{n}.json").exists() for n in names), timeout=15)

    for name in names:
        loaded = set(json.loads((out / f"{name}.json").read_text()))
        own = {m for m in plugin_modules if m in loaded}
        assert len(own) == 1, f"{name} imported plugins {sorted(own)}"
        if name in LEAN:
            heavy = sorted(m for m in loaded if m.split(".")[0] in HEAVY)
            assert not heavy, f"{name} imported {heavy[:5]}"
    # The supervisor (`exolink up`, dumped as "up") validated every plugin's params, in a child.
    sup = set(json.loads((out / "up.json").read_text()))
    assert not (plugin_modules & sup), sorted(plugin_modules & sup)
    # The recorder writes every schema from messaging.MSGDEFS: mcap, zstandard, no typestore.
    rec = set(json.loads((out / "recorder.json").read_text()))
    assert "mcap.writer" in rec
    assert not {m for m in rec if m.split(".")[0] in ("rosbags", "numpy")}, "recorder: typestore"
    # Nor a typestore: its messages are exolink.wire.cdr's, its ROS 2 services load rosbags at their
    # first call (none here): numpy and rosbags were ~13 MB of its memory.
    heavy = sorted(m for m in sup if m.split(".")[0] in HEAVY)
    assert not heavy, f"the supervisor imported {heavy[:5]}"


def test_a_bad_param_of_any_node_still_starts_nothing(write_config, spawn) -> None:  # type: ignore[no-untyped-def]
    data = yaml.safe_load(write_config().read_text())
    data["nodes"][-1]["params"]["nosuch"] = 1  # the last node's: checked in the child
    path = write_config(nodes=data["nodes"])
    proc = spawn("up", "-c", str(path), name="up")
    assert proc.p.wait(30) == 3
    out = proc.output()
    assert "nosuch" in out and f"nodes[{len(data['nodes']) - 1}].params" in out, out
    assert "node_running" not in out
