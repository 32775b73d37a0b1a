"""Who is on the other end of a control-socket connection, and may it command the robot.

The kernel's peer credentials (SO_PEERCRED: pid, uid, gid; SO_PEERGROUPS: the supplementary groups),
read once per connection, against ``daemon.socket.allowed_users`` / ``allowed_groups``; ``status``
(``control_protocol.OPEN_COMMANDS``) is open to every peer. Used by ``control_socket.ControlServer``.
"""
from __future__ import annotations

import grp
import os
import pwd
import socket
import struct
from dataclasses import dataclass

SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)  # Linux >= 4.13


@dataclass(frozen=True)
class Peer:
    """The connected process as the kernel reports it: pid, uid, gid, supplementary groups."""

    pid: int
    uid: int
    gid: int
    groups: tuple[int, ...] = ()

    def __str__(self) -> str:
        return f"pid {self.pid} uid {self.uid} gid {self.gid}"


def peer_credentials(conn: socket.socket) -> Peer:
    pid, uid, gid = struct.unpack("3i", conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))
    try:  # Python caps getsockopt's buffer at 1024 bytes (a larger one raises OSError at once)
        raw = conn.getsockopt(socket.SOL_SOCKET, SO_PEERGROUPS, 1024)
        groups = struct.unpack(f"{len(raw) // 4}I", raw)
    except OSError:  # older kernel or more than 256 groups: the user database's list
        try:
            groups = tuple(os.getgrouplist(pwd.getpwuid(uid).pw_name, gid))
        except KeyError:
            groups = ()
    return Peer(pid=pid, uid=uid, gid=gid, groups=tuple(groups))


class Authorizer:
    """Who may send commands beyond ``OPEN_COMMANDS``: users and groups by name or numeric id.
    Names are looked up when a peer connects (a user added later is recognized); names that do
    not exist match nobody. Nobody is implied, root included."""

    def __init__(self, users=(), groups=()):
        self.users = tuple(users)
        self.groups = tuple(groups)

    def _ids(self, entries, lookup) -> set[int]:
        out = set()
        for e in entries:
            if isinstance(e, int):
                out.add(e)
            else:
                try:
                    out.add(lookup(e))
                except KeyError:
                    pass
        return out

    def allows(self, peer: Peer) -> bool:
        if peer.uid in self._ids(self.users, lambda n: pwd.getpwnam(n).pw_uid):
            return True
        gids = self._ids(self.groups, lambda n: grp.getgrnam(n).gr_gid)
        return bool(gids & ({peer.gid} | set(peer.groups)))

