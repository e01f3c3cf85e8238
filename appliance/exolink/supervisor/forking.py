"""Forking nodes from a zygote: the supervisor's end of ``exolink.zygote`` and the handle of a
node it forked (``Forked``, what the supervisor uses of Popen's interface). The supervisor is a
child subreaper, so a forked node (the zygote's child) is re-parented to it and reaped here."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import threading

from exolink.supervisor.osproc import plain_priority


class Forked:
    """A node forked by the zygote and re-parented to this process: the part of Popen's
    interface the supervisor uses. One thread reaps it; everyone else reads the result."""

    def __init__(self, pid: int, stdout_fd: int | None) -> None:
        self.pid = pid
        self.stdout = os.fdopen(stdout_fd, "rb") if stdout_fd is not None else None
        self.returncode: int | None = None
        self._done = threading.Event()
        threading.Thread(target=self._reap, daemon=True, name=f"reap-{pid}").start()

    def _reap(self) -> None:
        try:
            _, status = os.waitpid(self.pid, 0)
            self.returncode = os.waitstatus_to_exitcode(status)
        except ChildProcessError:  # not re-parented to us: nothing to wait with
            self.returncode = -signal.SIGKILL
        self._done.set()

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise subprocess.TimeoutExpired(f"node pid {self.pid}", timeout or 0)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


PR_SET_CHILD_SUBREAPER = 36


def become_subreaper() -> None:
    """Orphans of this process' descendants (a forked node, whatever a node left behind)
    become its children instead of init's, so none escapes the stray sweep (kill_strays)."""
    import ctypes  # lazy: prctl, once per process

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_CHILD_SUBREAPER)")


class Zygote:
    """The supervisor's end of ``exolink.zygote``: one request at a time, a node pid back.

    The zygote is a fork of the supervisor made before it opens anything or starts a thread
    (Supervisor.start calls this first): the runtime both import is then one set of pages
    shared by the supervisor, the zygote and every node, and no second interpreter imports it
    again (seconds on the A8)."""

    def __init__(self) -> None:
        become_subreaper()  # the zygote's forks come to us
        self._sock, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.proc = Forked(_fork_zygote(self._sock, theirs), None)
        plain_priority(self.proc.pid)  # its forks must not inherit the supervisor's nice
        self._lock = threading.Lock()
        self.broken = False
        self._sock.settimeout(ZYGOTE_READY_S)  # its gc.collect of the forked heap, then ready
        try:
            ready = json.loads(self._sock.recv(4096) or b"{}").get("ready")
        except (OSError, ValueError) as exc:
            self._retire()
            raise OSError(f"zygote not ready: {exc}") from None
        if not ready:
            self._retire()
            raise OSError("zygote exited before it was ready")
        self._sock.settimeout(ZYGOTE_TIMEOUT_S)

    def spawn(self, name: str, config: str, env: dict[str, str], live_fds: list[int]) -> Forked:
        """A forked node; any failure retires the zygote for good (a late reply must never be
        taken as the answer to a later request) and the caller starts the node by exec."""
        if self.broken:
            raise RuntimeError("zygote retired after an earlier failure")
        r, w = os.pipe2(os.O_CLOEXEC)
        try:
            req = json.dumps({"name": name, "config": config, "env": env}).encode()
            with self._lock:
                socket.send_fds(self._sock, [req], [w, *live_fds])
                reply = json.loads(self._sock.recv(4096) or b"{}")
        except (OSError, ValueError) as exc:
            os.close(r)
            self._retire()
            raise RuntimeError(f"zygote: {exc}") from None
        finally:
            os.close(w)
        if "pid" not in reply:
            os.close(r)
            self._retire()
            raise RuntimeError(f"zygote: {reply.get('error', 'no reply')}")
        return Forked(int(reply["pid"]), r)

    def _retire(self) -> None:
        """At once, from the supervisor's loop: no waiting on a zygote that misbehaves."""
        self.broken = True
        self._sock.close()
        self.proc.kill()

    def close(self) -> None:
        self.broken = True
        self._sock.close()  # the zygote sees EOF and exits
        try:
            self.proc.wait(3)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _fork_zygote(ours: socket.socket, theirs: socket.socket) -> int:
    from exolink import zygote  # heavy: preloads the node runtime; the forked child's only

    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            ours.close()
            zygote.own_process_group()
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, signal.SIG_DFL)
            zygote.set_comm("exo-zygote")
            zygote.serve(theirs.fileno())
            code = 0
        finally:
            os._exit(code)
    theirs.close()
    return pid


ZYGOTE_TIMEOUT_S = 2.0  # a fork takes milliseconds; the supervisor's loop waits on this
ZYGOTE_READY_S = 120.0
