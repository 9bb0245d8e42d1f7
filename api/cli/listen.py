"""The listening socket of ``slamreplay serve``, opened before the server announces itself.

uvicorn binds its own socket only once the app is built and logs a failure as a multi-line
error; binding here first turns a port in use into one line and exit 2, and handing the socket
to uvicorn (``Server.run(sockets=...)``) leaves no moment in which another process can take it.
"""

from __future__ import annotations

import errno
import socket


class ListenError(RuntimeError):
    """The address or port cannot be listened on; the message says why on one line."""


def url_host(host: str) -> str:
    """``host`` as it goes in a URL (IPv6 addresses in brackets)."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def listen(host: str, port: int) -> socket.socket:
    """A TCP socket bound to (``host``, ``port``) and listening, as uvicorn would open it.

    Raises
    ------
    ListenError
        The port is in use, the address is not one of this machine's, or binding is not allowed.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    # IPPROTO_TCP by number, as asyncio's own sockets: asyncio sets TCP_NODELAY on a connection only then, and
    # without it each answer waited about 40 ms for a delayed ACK (measured: GET /healthz 44 ms against 1 ms)
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn: restart while old connections linger
    try:
        sock.bind((host.strip("[]"), port))
        sock.listen(2048)  # at once: two sockets with SO_REUSEADDR may both bind a port until one listens
    except OSError as err:
        sock.close()
        if err.errno == errno.EADDRINUSE:
            msg = f"port {port} on {host} is in use (another server?): pass --port N"
        elif err.errno == errno.EADDRNOTAVAIL:
            msg = f"--host {host}: not an address of this machine (try 127.0.0.1, or 0.0.0.0 for every address)"
        elif err.errno == errno.EACCES:
            msg = f"port {port} on {host}: permission denied (ports below 1024 need privileges): pass --port N"
        elif isinstance(err, socket.gaierror):
            msg = f"--host {host}: unknown host name ({err.strerror})"
        else:
            msg = f"cannot listen on {host} port {port}: {err.strerror or err}"
        raise ListenError(msg) from err
    return sock
