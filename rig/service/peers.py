"""Who is at the other end of the control socket, and may they control the rig.

The daemon checks every connection's peer (SO_PEERCRED) against the socket's owner and group
before it reads a request, and records the user with the starts and stops they make.
"""

from __future__ import annotations

import pwd
import socket
import struct
from pathlib import Path


def peer_credentials(conn: socket.socket) -> tuple[int, int, int]:
    """(pid, uid, gid) of the process at the other end (Linux SO_PEERCRED)."""
    data = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return struct.unpack("3i", data)


def peer_groups(pid: int) -> set[int]:
    """The peer's supplementary groups, from /proc (empty if it cannot be read)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("Groups:"):
                return {int(g) for g in line.split()[1:]}
    except OSError:
        pass
    return set()


def peer_allowed(uid: int, gid: int, groups: set[int], owner_uid: int, group_gid: int | None) -> bool:
    """Root, the socket's owner, or a member of its group (primary or supplementary)."""
    if uid in (0, owner_uid):
        return True
    return group_gid is not None and (gid == group_gid or group_gid in groups)


def user_name(uid: int) -> str:
    """The user name of `uid` ("uid N" where it has none)."""
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"
