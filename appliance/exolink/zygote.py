"""Fork server for nodes: the runtime imported once, each node a fork of it.

A node started with ``python -m exolink.runtime`` spends ~200 ms on an x86 core (seconds on the
board's Cortex-A8) importing the same runtime every other node imports, and keeps a private copy
of it. The supervisor forks this process once, before it opens anything; it has imported the common runtime (Zenoh, python-can,
structlog, msgspec, never a node plugin; the device's protocol tables come with the supervisor,
which loaded its hardware before the fork), freezes it for the garbage
collector (gc.freeze: pages stay shared, not copied on the first collection) and then forks one
child per node on request. No Zenoh session or thread exists here before a fork: each node opens
its own afterwards. A node is forked through a short-lived intermediate, so it is re-parented to
the supervisor (a child subreaper), which waits for it exactly as for a process it spawned.

Protocol (SOCK_SEQPACKET from the supervisor): {ready} once imported; then per node a JSON
request {name, config, env} with three file descriptors, the node's stdout, its liveness pipe
and its deadline timer (and a leased node's broadcast-manager socket, exolink.canbus.held), and
the reply {pid} or {error}.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import json
import os
import signal
import socket
import struct
import sys
import traceback
from typing import Any, NoReturn

import exolink.canbus
import exolink.canbus.held
import exolink.errors
import exolink.liveness
import exolink.logs
import exolink.messaging
import exolink.plugins
import exolink.runtime
import exolink.wire.cdr

_PID = struct.Struct("=i")
MAX_REQUEST = 1 << 16


def serve(fd: int) -> None:
    """Until the supervisor closes its end."""
    gc.collect()
    gc.freeze()
    sock = socket.socket(fileno=fd)
    sock.send(b'{"ready": true}')  # imports done: the supervisor waits for this before any request
    while True:
        try:
            msg, fds, _flags, _addr = socket.recv_fds(sock, MAX_REQUEST, 4)
        except OSError:
            return
        if not msg:
            return
        try:
            reply: dict[str, Any] = {"pid": _spawn(json.loads(msg), fds, sock)}
        except Exception as exc:  # the supervisor falls back to exec: say why
            reply = {"error": f"{type(exc).__name__}: {exc}"}
        finally:
            for f in fds:
                os.close(f)
        sock.send(json.dumps(reply).encode())


def _spawn(req: dict[str, Any], fds: list[int], sock: socket.socket) -> int:
    if len(fds) not in (3, 4):
        raise ValueError(f"expected 3 or 4 file descriptors, got {len(fds)}")
    r, w = os.pipe()
    mid = os.fork()
    if mid == 0:  # intermediate: fork the node, report its pid, leave at once
        code = 1
        try:
            os.close(r)
            pid = os.fork()
            if pid == 0:
                os.close(w)
                _node(req, fds, sock)
            os.write(w, _PID.pack(pid))
            code = 0
        finally:
            os._exit(code)
    os.close(w)
    os.waitpid(mid, 0)
    with os.fdopen(r, "rb") as f:
        raw = f.read(_PID.size)
    if len(raw) != _PID.size:
        raise RuntimeError("the intermediate process did not report the node's pid")
    return int(_PID.unpack(raw)[0])


def _node(req: dict[str, Any], fds: list[int], sock: socket.socket) -> NoReturn:
    """In the node's process: become what ``python -m exolink.runtime NAME -c FILE`` would be."""
    code = 1
    try:
        sock.close()
        own_process_group()
        set_comm(f"exo-{req['name']}")
        out, live, timer, *held = fds
        os.dup2(out, 1)
        os.dup2(out, 2)
        os.close(out)
        for s in (signal.SIGTERM, signal.SIGINT, signal.SIGPIPE):
            signal.signal(s, signal.SIG_DFL if s != signal.SIGPIPE else signal.SIG_IGN)
        os.environ.clear()
        os.environ.update(req["env"])
        os.environ[exolink.liveness.ENV] = str(live)
        os.environ[exolink.liveness.TIMER_ENV] = str(timer)
        if held:  # a leased node's broadcast-manager socket, the supervisor's too
            os.environ[exolink.canbus.held.HELD_ENV] = str(held[0])
        args = [str(req["name"]), "-c", str(req["config"])]
        sys.argv = [exolink.runtime.__file__, *args]
        try:
            code = exolink.runtime.main(args)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        except BaseException:  # what the interpreter would print: os._exit below would not
            traceback.print_exc()
            code = 1
    finally:
        with contextlib.suppress(Exception):
            atexit._run_exitfuncs()
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def own_process_group() -> None:
    """A terminal's Ctrl-C reaches the supervisor's process group only (it stops the nodes in
    order), and stdin is /dev/null; but the process stays in the supervisor's session.

    Why not a session of its own (setsid): the kernel's autogroup (CONFIG_SCHED_AUTOGROUP, on in
    Debian's armmp kernel and most desktops) makes each session one scheduling group of equal
    weight, and nice then only orders threads inside a group. With a session per node, board.yaml's
    priorities do nothing: on a saturated core a nice 10 observer keeps its share while a
    nice -10 reader falls behind (measured: docs/performance.md)."""
    os.setpgid(0, 0)
    with contextlib.suppress(OSError):
        fd = os.open(os.devnull, os.O_RDONLY)
        if fd != 0:
            os.dup2(fd, 0)
            os.close(fd)


def set_comm(name: str) -> None:
    """What top and the journal show for the process (its cmdline stays the zygote's)."""
    import ctypes  # lazy: prctl, once per process

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).prctl(PR_SET_NAME, name.encode()[:15], 0, 0, 0)


PR_SET_NAME = 15
