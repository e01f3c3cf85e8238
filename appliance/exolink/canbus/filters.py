"""Content filters: frames of an id a reader reads but never needs, dropped before they cost it.

SocketCAN's receive filter matches ids only, and some ids carry two protocols or more traffic
than a reader uses: id 70 is the H2's joint control (6 bytes, the controller manager's four
set-points per cycle with the gait) and MACCEPA board 0's controller status (8 bytes). The
MACCEPA bridge read every set-point to skip it, the manager every board-0 status it does not
drive. On the board each frame queued to a socket costs its reader a dequeue, a copy and a
parse (more than the Python that skips it), so ``Drop`` rules name what to leave
out, by id, length and optionally one data byte's values.

On SocketCAN the rules become a classic BPF socket filter (``SO_ATTACH_FILTER``): the kernel
runs it as it queues a frame and drops a match there; no receive, no wake-up, and not counted
in the socket's drop counter (``sk_drops`` counts only a full queue, so ``dropped`` stays the
frames lost). On other buses (the simulated one, the virtual one) ``FrameReader`` applies the
same rules in Python, so a node behaves alike on both. Only standard data frames are judged:
an extended, remote or error frame never matches a rule (its id word carries a flag).
"""

from __future__ import annotations

import ctypes
import socket
import struct
from collections.abc import Iterable, Sequence
from typing import NamedTuple

SO_ATTACH_FILTER = 26  # asm-generic/socket.h; Python exports neither
STD_MASK = 0x7FF
MAX_RULES = 32
MAX_KEEP = 32  # a rule's jumps are 8-bit offsets: its instructions stay far below 256

# linux/filter.h: classic BPF opcodes used here
_LD_W_ABS, _LD_B_ABS = 0x20, 0x30
_JEQ_K, _RET_K = 0x15, 0x06
_KEEP, _DROP = 0xFFFFFFFF, 0
_INSN = struct.Struct("=HBBI")  # struct sock_filter: code, jt, jf, k
# struct can_frame: can_id (host order) at 0, len at 4, data at 8
_ID_AT, _LEN_AT, _DATA_AT = 0, 4, 8


class Drop(NamedTuple):
    """Frames of ``can_id`` that are ``dlc`` bytes long are not delivered, except (``byte``
    set) those whose data byte ``byte`` is one of ``keep``."""

    can_id: int
    dlc: int
    byte: int | None = None
    keep: frozenset[int] = frozenset()


def check(rules: Iterable[Drop]) -> tuple[Drop, ...]:
    """The rules, validated: a rule that cannot match a classic CAN frame is a caller's bug."""
    out = tuple(rules)
    if len(out) > MAX_RULES:
        raise ValueError(f"{len(out)} drop rules: at most {MAX_RULES}")
    seen: set[tuple[int, int]] = set()
    for r in out:
        if not 0 <= r.can_id <= STD_MASK:
            raise ValueError(f"drop rule {r}: can_id must be a standard 11-bit id")
        if not 0 <= r.dlc <= 8:
            raise ValueError(f"drop rule {r}: dlc must be 0..8")
        if r.byte is not None and not 0 <= r.byte < r.dlc:
            raise ValueError(f"drop rule {r}: byte must be inside the frame's {r.dlc} bytes")
        if r.byte is None and r.keep:
            raise ValueError(f"drop rule {r}: keep values need a byte")
        if any(not 0 <= v <= 0xFF for v in r.keep) or len(r.keep) > MAX_KEEP:
            raise ValueError(f"drop rule {r}: keep values are at most {MAX_KEEP} bytes (0..255)")
        if (r.can_id, r.dlc) in seen:
            raise ValueError(f"two drop rules for id {r.can_id} with {r.dlc} bytes")
        seen.add((r.can_id, r.dlc))
    return out


class Predicate:
    """The rules in Python, for buses without a kernel to run them: ``drops(id, data)``."""

    def __init__(self, rules: Sequence[Drop]) -> None:
        self._by = {(r.can_id, r.dlc): r for r in check(rules)}

    def __bool__(self) -> bool:
        return bool(self._by)

    def drops(self, can_id: int, data: bytes) -> bool:
        """For a standard data frame (the caller checks the flags, as the kernel's id word
        does)."""
        r = self._by.get((can_id, len(data)))
        if r is None:
            return False
        return r.byte is None or data[r.byte] not in r.keep


def _id_word(can_id: int) -> int:
    """The can_id as ``ld [0]`` sees it: BPF loads words in network order, the kernel stores
    can_id in host order."""
    return int.from_bytes(can_id.to_bytes(4, "little" if _LITTLE else "big"), "big")


_LITTLE = struct.pack("=I", 1)[0] == 1


def program(rules: Sequence[Drop]) -> list[tuple[int, int, int, int]]:
    """Classic BPF over a struct can_frame: for each rule, id and length equal and (if it has
    one) the byte not among ``keep`` -> drop; every other frame is kept."""
    insns: list[tuple[int, int, int, int]] = []
    for r in check(rules):
        keep = sorted(r.keep) if r.byte is not None else []
        # instructions after each test, to the end of this rule (the next rule's first)
        body = 4 + (1 + len(keep) if r.byte is not None else 0) + 1
        left = body
        insns.append((_LD_W_ABS, 0, 0, _ID_AT))
        left -= 1
        insns.append((_JEQ_K, 0, left - 1, _id_word(r.can_id)))
        left -= 1
        insns.append((_LD_B_ABS, 0, 0, _LEN_AT))
        left -= 1
        insns.append((_JEQ_K, 0, left - 1, r.dlc))
        left -= 1
        if r.byte is not None:
            insns.append((_LD_B_ABS, 0, 0, _DATA_AT + r.byte))
            left -= 1
            for v in keep:  # a kept value: on to the next rule
                insns.append((_JEQ_K, left - 1, 0, v))
                left -= 1
        insns.append((_RET_K, 0, 0, _DROP))
    insns.append((_RET_K, 0, 0, _KEEP))
    return insns


class _SockFprog(ctypes.Structure):
    _fields_ = (("len", ctypes.c_ushort), ("filter", ctypes.c_void_p))


def attach(sock: socket.socket, rules: Sequence[Drop]) -> None:
    """The rules as the socket's filter (the kernel copies the program: nothing to keep)."""
    insns = program(rules)
    code = ctypes.create_string_buffer(b"".join(_INSN.pack(*i) for i in insns))
    fprog = _SockFprog(len(insns), ctypes.addressof(code))
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, bytes(fprog))
