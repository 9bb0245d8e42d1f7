"""A program under test, contained whatever it does (docs/external.md, "Limits"): every process it starts is
killed and reaped when its main process exits, at its time limit and when slamreplay stops (a cancel, Ctrl-C, a
killed worker); its output goes to size-capped files as it comes; it runs under an address-space limit.

The program runs below a small supervisor of its own (``shepherd.py``, a child subreaper), not directly below
slamreplay's process: every process below the supervisor is then the program's, whatever it did (setsid, a
double fork, a new process group), while slamreplay's process may have children of its own (a service worker's,
multiprocessing's) that nothing here may touch. slamreplay never reads the program's pipes itself, so it never
waits on a pipe a leftover holds, and its memory does not grow with the program's output.

- ``OUTPUT_CAP_BYTES`` (10 MiB) of each of stdout and stderr are kept; the rest is counted, and a line at the end
  of the file says how many bytes were dropped. The last line of each stream is kept apart (for error messages).
- ``DEFAULT_MEMORY_MIB`` (4096 MiB) of address space (``RLIMIT_AS``) unless the declaration sets ``memory_mib`` or
  the operator sets ``$SLAMREPLAY_EXTERNAL_MEMORY_MIB``. Address space, not resident memory: Python with numpy,
  scipy and mcap reserves about 280 MiB, with OpenCV 530 MiB, with rerun-sdk (pyarrow) 1.7 GiB while using 130
  MiB (measured on 2 cores; thread stacks and malloc arenas grow with the number of cores), so 4 GiB runs those
  and stops a runaway long before it takes the machine. Programs that reserve far more than they use (the JVM,
  CUDA, sanitizers) need a declared ``memory_mib``.
- The supervisor kills the program at ``timeout_s``; slamreplay gives it ``STOP_GRACE_S`` more to kill and report,
  then kills the supervisor and every process still marked with the run's token (``TOKEN_ENV``, in the program's
  environment), so ``run_contained`` returns within ``timeout_s`` + 10 s whatever happens (the program may stop
  or kill its supervisor: it is its parent).
- Elsewhere than Linux there is no subreaper: the program's process group is killed, and a process that left it
  may survive.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from slamreplay.replay.errors import ReplayError

OUTPUT_CAP_BYTES = 10 * 1024 * 1024  # per stream
DEFAULT_MEMORY_MIB = 4096
MEMORY_ENV = "SLAMREPLAY_EXTERNAL_MEMORY_MIB"
TOKEN_ENV = "SLAMREPLAY_PROGRAM_TOKEN"  # marks every process of one run, for the last-resort sweep
MAX_RESULT_BYTES = 256 * 1024 * 1024  # of a file the program writes (a TUM line is ~80 bytes: 3 million poses)
LINE_CHARS = 500  # of a line of the program's output copied into a log or an error
STOP_GRACE_S = 4.0  # past the limit (or a stop), how long the supervisor has to kill, reap and report
SHEPHERD = Path(__file__).with_name("shepherd.py")


@dataclass(frozen=True, slots=True)
class Contained:
    """How one contained run of a program ended.

    ``status`` is its exit status (negative: the signal that killed it), None when it never started
    (``start_error`` says why); ``killed`` the processes killed besides its main one, as (pid, name): those left
    behind at its exit, or alive at the limit; ``dropped`` the bytes of each stream past the cap.
    """

    status: int | None
    timed_out: bool
    wall_s: float
    killed: tuple[tuple[int, str], ...]
    stdout_path: Path
    stderr_path: Path
    dropped: Mapping[str, int]
    last_stderr_line: str
    start_error: str | None = None


def memory_limit_mib(declared: int | None) -> int:
    """The program's address-space limit: its declaration's ``memory_mib``, else ``$SLAMREPLAY_EXTERNAL_MEMORY_MIB``,
    else ``DEFAULT_MEMORY_MIB``; ReplayError when the variable is not a whole number of MiB >= 16."""
    if declared is not None:
        return declared
    text = os.environ.get(MEMORY_ENV, "").strip()
    if not text:
        return DEFAULT_MEMORY_MIB
    if not text.isdigit() or int(text) < 16:
        raise ReplayError(f"${MEMORY_ENV} must be a whole number of MiB >= 16 (the default address-space limit of "
                          f"external programs), got {text!r}")
    return int(text)


def run_contained(argv: Sequence[str], *, cwd: Path, env: Mapping[str, str], stdin: Path | None,
                  memory_mib: int | None, timeout_s: float, work: Path, scratch: Path | None = None) -> Contained:
    """Run ``argv`` contained (module docstring) and return how it ended; its output in ``work`` (created).

    Parameters
    ----------
    argv : the command line, its program resolved
    cwd, env : where it runs and its whole environment (``TOKEN_ENV`` is added)
    stdin : a file fed to its standard input, or None for /dev/null
    memory_mib, timeout_s : its address-space limit (MiB; None: none) and wall-time limit (s)
    work : a folder of slamreplay's for the capped ``program_stdout.txt`` and ``program_stderr.txt``
    scratch : the temporary folder holding ``work`` and the program's inputs, removed by the supervisor if
        slamreplay's process dies during the run (a cancelled job's worker); by default ``work``
    """
    work.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    spec = {"argv": list(argv), "cwd": str(cwd), "env": {**env, TOKEN_ENV: token}, "timeout_s": timeout_s,
            "stdin": str(stdin) if stdin else None, "memory_bytes": memory_mib and memory_mib * 1024 * 1024,
            "stdout": str(work / "program_stdout.txt"), "stderr": str(work / "program_stderr.txt"),
            "cap": OUTPUT_CAP_BYTES, "report": str(work / "report.json"), "parent": os.getpid(),
            "cleanup": str(scratch or work)}
    (work / "spec.json").write_text(json.dumps(spec))
    tic = time.monotonic()
    with open(work / "supervisor.log", "wb") as log:
        # -I -S: the standard library only, no site-packages, no PYTHON* variables: a fast start
        shepherd = subprocess.Popen([sys.executable, "-I", "-S", str(SHEPHERD), str(work / "spec.json")],
                                    stdin=subprocess.DEVNULL, stdout=log, stderr=log, close_fds=True)
    try:
        shepherd.wait(timeout_s + STOP_GRACE_S)
    except subprocess.TimeoutExpired:  # it ends at timeout_s itself: it is stuck, or the program stopped it
        shepherd.kill()
        shepherd.wait()
    finally:  # also when this thread is interrupted (Ctrl-C, a job's limit): the program goes first
        if not _stop(shepherd):
            sweep(token)
    wall_s = time.monotonic() - tic
    try:
        report = json.loads((work / "report.json").read_text())
    except (OSError, ValueError):  # it died (killed by someone, or a bug), or hung past the limit: say which
        said = (work / "supervisor.log").read_text(errors="replace").strip().splitlines()
        report = ({"status": -signal.SIGKILL, "timed_out": True, "wall_s": wall_s} if wall_s >= timeout_s else
                  {"start_error": f"its supervisor ended with status {shepherd.returncode} and no report"
                                  + (f": {said[-1][:300]}" if said else "")})
    # without a subreaper, or without a supervisor to the end, a process of the program may have escaped
    swept = sweep(token) if not report.get("subreaper") else ()
    killed = tuple((int(pid), str(name)) for pid, name in report.get("killed", [])) + swept
    status = report.get("status")
    why = report.get("start_error") or (None if status is not None else "it did not end when killed (a process in "
                                        "uninterruptible sleep?)")
    return Contained(status, bool(report.get("timed_out")), float(report.get("wall_s", wall_s)), killed,
                     work / "program_stdout.txt", work / "program_stderr.txt",
                     {s: int(report.get(s, {}).get("dropped", 0)) for s in ("stdout", "stderr")},
                     str(report.get("stderr", {}).get("last_line", "")), why)


def _stop(shepherd: subprocess.Popen[bytes]) -> bool:
    """Ask the supervisor to kill the program and report (SIGUSR1), and kill it if it does not end in time;
    whether it ended by itself (else the program's processes it held may be left: ``sweep``)."""
    if shepherd.poll() is not None:
        return True
    shepherd.send_signal(signal.SIGUSR1)
    try:
        shepherd.wait(STOP_GRACE_S)
        return True
    except subprocess.TimeoutExpired:
        shepherd.kill()
        shepherd.wait()
        return False


def sweep(token: str) -> tuple[tuple[int, str], ...]:
    """SIGKILL every process whose environment holds ``TOKEN_ENV=token`` (Linux; none elsewhere): a program's
    process that escaped its supervisor (killed by someone else, or no subreaper). Those killed, (pid, name)."""
    marker = f"{TOKEN_ENV}={token}".encode() + b"\0"
    killed: list[tuple[int, str]] = []
    with contextlib.suppress(OSError):
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                with open(f"/proc/{entry}/environ", "rb") as f:
                    if marker not in f.read():
                        continue
                name = Path(f"/proc/{entry}/comm").read_text().strip()
                os.kill(int(entry), signal.SIGKILL)
            except OSError:  # ended, or not ours to read
                continue
            killed.append((int(entry), name))
    return tuple(killed)


_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def printable(data: bytes | str) -> str:
    """One line of a program's output as it may be shown: UTF-8 (bad bytes replaced), control characters
    (terminal escape sequences among them) written as ``\\x1b``, at most ``LINE_CHARS`` characters."""
    text = data.decode("utf-8", "replace") if isinstance(data, bytes) else data
    text = _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", text.rstrip("\r\n"))
    return text if len(text) <= LINE_CHARS else text[:LINE_CHARS] + " ..."


def head_lines(data: bytes, n: int) -> tuple[list[str], int]:
    """The first ``n`` lines of ``data``, printable, and how many lines it holds (without a copy of all of it)."""
    lines: list[str] = []
    start = 0
    while len(lines) < n and start < len(data):
        end = data.find(b"\n", start, start + 4 * LINE_CHARS)  # a longer line is cut anyway
        stop = end if end >= 0 else min(len(data), start + 4 * LINE_CHARS)
        lines.append(printable(data[start:stop]))
        start = end + 1 if end >= 0 else data.find(b"\n", stop) + 1 or len(data)
    return lines, data.count(b"\n") + (0 if data.endswith(b"\n") or not data else 1)


def read_result(path: Path, inside: Path | None) -> tuple[bytes | None, str | None]:
    """A file the program wrote, or why it is not read: (data, None), (None, None) when there is no file, or
    (None, the reason, to follow the file's name). Only a regular file that is not a symbolic link is read, only
    inside the folder ``inside`` (the program's ``{out}``) when it was declared there, and at most
    ``MAX_RESULT_BYTES``: a program's output cannot make slamreplay read another file, a device or a pipe, or
    fill its memory."""
    if path.is_symlink():
        return None, f"is a symbolic link (to {os.readlink(path)}): slamreplay reads only a file written there"
    if inside is not None and path.exists() and not path.resolve().is_relative_to(inside.resolve()):
        return None, f"leads out of {inside} (through a symbolic link): slamreplay reads only a file written there"
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return None, None
    except OSError as err:
        return None, f"cannot be read: {err.strerror}"
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            return None, "is not a regular file"
        data = f.read(MAX_RESULT_BYTES + 1) if st.st_size <= MAX_RESULT_BYTES else b""
    if st.st_size > MAX_RESULT_BYTES or len(data) > MAX_RESULT_BYTES:
        return None, (f"is {max(st.st_size, len(data)):,} bytes, more than the {MAX_RESULT_BYTES >> 20} MiB "
                      f"slamreplay reads")
    return data, None
