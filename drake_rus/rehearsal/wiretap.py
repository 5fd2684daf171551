"""A passive tap on LCM's UDP multicast wire: every packet on one channel, with the kernel's
receive time.

Why: a DrakeLcm subscription keeps one pending message (drake-franka-driver's own keeps
100) and pumping it from Python holds the interpreter lock, so neither sees every command
with an exact arrival time while the simulation runs. This tap joins the multicast group on
its own socket (Linux delivers each datagram to every socket bound to the group's port),
reads in a thread (the socket call releases the interpreter lock) and stamps each packet
with the kernel's receive time (``SO_TIMESTAMPNS``), not with when Python got to it.

Only small LCM messages (``LC02`` packets, < 64 kB: commands and statuses) are decoded;
fragmented ones are counted and skipped.
"""

from __future__ import annotations

import socket
import struct
import threading
import time
import urllib.parse

__all__ = ["LcmUdpmTap", "parse_udpm_url", "decode_lcm_packet"]

_MAGIC_SHORT = 0x4C433032  # "LC02"
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)


def parse_udpm_url(url: str) -> tuple[str, int]:
    """(group, port) of an LCM ``udpm://GROUP:PORT?...`` URL; ValueError otherwise."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "udpm" or not parts.hostname or not parts.port:
        raise ValueError(f"not an LCM udpm:// URL with a group and a port: {url!r}")
    return parts.hostname, int(parts.port)


def decode_lcm_packet(data: bytes):
    """(channel, sequence number, payload) of a short LCM packet, or None (fragment or not
    LCM). The sequence number counts the sender's messages (all channels)."""
    if len(data) < 9:
        return None
    magic, seq = struct.unpack(">II", data[:8])
    if magic != _MAGIC_SHORT:
        return None
    end = data.find(b"\0", 8)
    if end < 0:
        return None
    return data[8:end].decode("utf-8", "replace"), seq, data[end + 1 :]


class LcmUdpmTap:
    """Records ``(receive time s, sender, sequence number, payload)`` of every packet on
    ``channel`` of the udpm ``url`` (``records``, appended from the tap thread;
    ``on_packet(t, sender, seq, payload)`` if given is called there too; ``sender`` is the
    sending socket's "address:port"). ``close()`` stops it (bounded: the socket times out
    every 0.1 s)."""

    def __init__(self, url: str, channel: str, on_packet=None):
        group, port = parse_udpm_url(url)
        self.channel = channel
        self.records: list[tuple[float, bytes]] = []
        self.fragments = 0
        self._on_packet = on_packet
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if hasattr(socket, "SO_REUSEPORT"):
            try:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            except OSError:
                pass
        s.bind(("", port))
        s.setsockopt(
            socket.IPPROTO_IP,
            socket.IP_ADD_MEMBERSHIP,
            struct.pack("4s4s", socket.inet_aton(group), socket.inet_aton("0.0.0.0")),
        )
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        s.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        s.settimeout(0.1)
        self._socket = s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="drake_rus_lcm_tap", daemon=True)
        self._thread.start()

    def _run(self):
        s = self._socket
        while not self._stop.is_set():
            try:
                data, ancillary, _flags, addr = s.recvmsg(65536, 64)
            except socket.timeout:
                continue
            except OSError:
                return
            t = None
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(value) >= 16:
                    sec, nsec = struct.unpack("qq", value[:16])
                    t = sec + nsec * 1e-9
            if t is None:
                t = time.time()
            packet = decode_lcm_packet(data)
            if packet is None:
                self.fragments += 1
                continue
            channel, seq, payload = packet
            if channel != self.channel:
                continue
            sender = f"{addr[0]}:{addr[1]}"
            self.records.append((t, sender, seq, payload))
            if self._on_packet is not None:
                self._on_packet(t, sender, seq, payload)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        try:
            self._socket.close()
        except OSError:
            pass
