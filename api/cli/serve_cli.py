"""``serve``: the HTTP service and the web page on a port, over a data directory it locks."""

from __future__ import annotations

import argparse
from typing import Any

from slamreplay.api.cli.cli_parser import EXIT_OK, CliError, eprint


def _auth_text(settings: Any) -> str:
    """What the server asks of its clients: people's tokens, the shared token, or nothing (api/service/auth.py)."""
    from slamreplay.api.service.store import Store

    users = Store(settings.db_path).users()
    if users:
        active = sum(u.active for u in users)
        ignored = "; SLAMREPLAY_TOKEN is not used" if settings.token else ""
        return f"people: {active} active of {len(users)}, each with their own token and role{ignored}"
    if settings.token:
        return "single user: one shared bearer token required"
    return "single user: no token (set SLAMREPLAY_TOKEN, or add people with `slamreplay users add`)"


def cmd_serve(args: argparse.Namespace) -> int:
    """Take the data directory's lock, then the port, and only then announce and build the app: a second
    server on a directory or a port in use exits 2 on one line without touching the first one's jobs."""
    from pydantic import ValidationError

    from slamreplay.api.cli.listen import ListenError, listen, url_host
    from slamreplay.api.service.datalock import DataDirInUseError, DataDirLock
    from slamreplay.api.service.settings import Settings
    from slamreplay.api.service.siteguard import LOOPBACK_HOSTS, served_hosts

    try:
        settings = Settings.from_env(data_dir=args.data_dir, workers=args.workers, executor=args.executor,
                                     ray_address=args.ray_address, storage_url=args.storage_url,
                                     job_memory_mib=args.job_memory_mib, job_timeout_s=args.job_timeout_s,
                                     allowed_hosts=tuple(args.allowed_host) or None)
    except ValidationError as err:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}" for e in err.errors())
        raise CliError(f"invalid setting (from SLAMREPLAY_* or the options): {problems}") from None
    try:
        settings.make_dirs()
    except OSError as err:
        raise CliError(f"--data-dir {settings.data_dir}: cannot create it: {err.strerror or err}") from None
    settings = settings.model_copy(update={"allowed_hosts": served_hosts(settings.allowed_hosts, args.host)})
    lock = DataDirLock(settings.data_dir)
    try:
        lock.acquire()
        sock = listen(args.host, args.port)
    except (DataDirInUseError, ListenError) as err:
        lock.release()
        raise CliError(str(err)) from None
    except OSError as err:  # the lock file: a read-only data directory
        raise CliError(f"--data-dir {settings.data_dir}: cannot lock it: {err.strerror or err}") from None
    base = f"http://{url_host(args.host)}:{sock.getsockname()[1]}"
    lock.set_address(base)
    auth = _auth_text(settings)
    names = [h for h in settings.allowed_hosts if h not in LOOPBACK_HOSTS]
    hosts = "" if args.host == "127.0.0.1" else (
        f"; host names served: loopback, {', '.join(names)}" if names else
        "; host names served: loopback only (clients elsewhere need --allowed-host NAME)")
    eprint(f"slamreplay serve: {base} over {settings.data_dir.resolve()} "
            f"({settings.workers} {settings.executor} worker(s), {auth}{hosts})")
    import uvicorn  # the service's stack, imported once the directory and the port are ours (a refusal is quick)

    from slamreplay.api.app import create_app
    from slamreplay.api.service.timeouts import server_config

    try:
        app = create_app(settings, lock=lock)
    except ImportError as err:  # --executor ray without the extra: the message has the install command
        raise CliError(str(err)) from None
    config = server_config(app, args.host, args.port, args.log_level, settings.header_timeout_s)  # service/timeouts.py
    uvicorn.Server(config).run(sockets=[sock])
    lock.release()
    return EXIT_OK


def add_serve_parser(sub: Any) -> None:
    """``serve``."""
    srv = sub.add_parser("serve", help="run the HTTP service: upload recordings, run jobs, fetch runs and diffs",
                         description="Serve the HTTP API (OpenAPI docs at /docs). Settings come from SLAMREPLAY_* "
                                     "environment variables (SLAMREPLAY_TOKEN, SLAMREPLAY_MAX_UPLOAD_BYTES ...); "
                                     "these options win over them.")
    srv.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)")
    srv.add_argument("--port", type=int, default=8000, help="port (default: 8000)")
    srv.add_argument("--data-dir", default=None,
                     help="holds recordings/ and runs/ (default: SLAMREPLAY_DATA_DIR, else the current directory)")
    srv.add_argument("--workers", type=int, default=None,
                     help="jobs running at once, each in its own process (default: SLAMREPLAY_WORKERS, else 2)")
    srv.add_argument("--executor", choices=["local", "ray"], default=None,
                     help="where jobs run: local worker processes, or Ray tasks (the ray extra) "
                          "(default: SLAMREPLAY_EXECUTOR, else local)")
    srv.add_argument("--ray-address", default=None, metavar="ADDR",
                     help="Ray cluster to join, e.g. ray://head:10001 or auto (default: SLAMREPLAY_RAY_ADDRESS, "
                          "else a local Ray instance)")
    srv.add_argument("--storage-url", default=None, metavar="URL",
                     help="where workers read recordings and write runs, e.g. s3://bucket/slam or a shared "
                          "file:// path (default: SLAMREPLAY_STORAGE_URL, else the data directory)")
    srv.add_argument("--job-memory-mib", type=int, default=None, metavar="MIB",
                     help="memory limit of each job's process (default: SLAMREPLAY_JOB_MEMORY_MIB, else none)")
    srv.add_argument("--job-timeout-s", type=float, default=None, metavar="S",
                     help="wall-time limit of each job (default: SLAMREPLAY_JOB_TIMEOUT_S, else none)")
    srv.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                     help="a host name clients may reach the server by, besides 127.0.0.1, localhost, ::1 and --host "
                          "(repeatable; *.example.org for subdomains, * for any; default: "
                          "SLAMREPLAY_ALLOWED_HOSTS, comma-separated); requests naming another host are refused")
    srv.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"],
                     help="uvicorn log level (default: info)")
    srv.set_defaults(func=cmd_serve)
