"""The supervisor of one external program, run as ``python -I -S shepherd.py SPEC.json`` by
``slamreplay.replay.tools.containment`` (which documents the SPEC and the report it reads back).

It is the only process between slamreplay and the program, so every process below it is the program's: it
makes itself a child subreaper (Linux ``PR_SET_CHILD_SUBREAPER``), and a descendant that calls setsid or
double-forks is re-parented to it instead of to init. It starts the program in a session of its own under an
address-space limit, copies the program's stdout and stderr into files capped at ``cap`` bytes each (the rest is
counted, not kept; the last line of each stream is kept apart, for error messages) and reaps whatever ends.
When the program's main process exits, when its time limit passes or when it is told to stop (SIGUSR1 from
slamreplay; SIGTERM, which ``PR_SET_PDEATHSIG`` sends when slamreplay's thread that started it dies; SIGINT,
SIGHUP), it kills every process left below it with SIGKILL, reaps them all, reads what is still in the pipes for
at most ``DRAIN_S`` (it never waits for an end of file a process out of its reach could hold back) and writes its
report. When slamreplay's process has died, it also removes the run's scratch folder, which nobody else will.

Only the standard library, imported without ``site``: it starts in about 40 ms.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import resource
import select
import shutil
import signal
import subprocess
import sys
import time
from typing import Any

PR_SET_PDEATHSIG = 1  # linux/prctl.h
PR_SET_CHILD_SUBREAPER = 36
POLL_S = 0.05  # the loop looks at the clock and reaps at least this often
CHUNK = 1 << 16  # bytes read from a pipe at a time: the only output held in memory
TAIL = 4096  # bytes of each stream's end kept apart for its last line, whatever the cap dropped
DRAIN_S = 0.5  # output still in the pipes after the end is read for at most this long
KILL_S = 2.0  # the longest spent killing and reaping (a process in uninterruptible sleep dies late)
# A SIGTERM comes as soon as the thread that started us dies, which may be before the rest of its process: how long
# we wait for slamreplay's process to be gone (re-parented away from it) before we remove its scratch folder.
ORPHAN_WAIT_S = 5.0

_stop: list[str] = []  # the signals that asked us to stop


def _on_signal(signum: int, frame: Any) -> None:
    _stop.append(signal.Signals(signum).name)


def _prctl() -> Any:
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux: no subreaper, the process group is the fallback
        return None


class Capped:
    """One output stream into a file: the first ``cap`` bytes kept, the rest counted; its last ``TAIL`` bytes."""

    def __init__(self, path: str, cap: int, name: str) -> None:
        self.file = open(path, "wb")  # noqa: SIM115 (closed by close())
        self.cap, self.name, self.kept, self.dropped = cap, name, 0, 0
        self.tail = b""
        self.reading = True  # until the pipe's end of file

    def write(self, data: bytes) -> None:
        room = max(0, self.cap - self.kept)
        if room:
            try:
                self.file.write(data[:room])
                self.kept += min(room, len(data))
            except OSError:  # a full disk: the stream is counted from here on, not kept
                self.cap = self.kept
        self.dropped += len(data) - min(room, len(data))
        self.tail = (self.tail + data)[-TAIL:]

    def close(self) -> dict[str, Any]:
        """Close the file, with a line at its end saying how much was dropped; what the report says of it."""
        with contextlib.suppress(OSError):
            if self.dropped:
                self.file.write(f"\n[slamreplay: {self.dropped:,} more bytes on {self.name} were not kept: the "
                                f"file keeps the first {self.kept:,} bytes]\n".encode())
            self.file.close()
        lines = [line.strip() for line in self.tail.decode("utf-8", "replace").splitlines() if line.strip()]
        return {"kept": self.kept, "dropped": self.dropped, "last_line": lines[-1] if lines else ""}


def _descendants() -> dict[int, tuple[str, bool]]:
    """Every process below this one, pid -> (its name, whether it is a zombie), from the ppid links in /proc."""
    parents: dict[int, list[int]] = {}
    about: dict[int, tuple[str, bool]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                stat = f.read()
        except OSError:  # it ended while we looked
            continue
        close = stat.rfind(b")")  # the name may hold spaces and parentheses: it ends at the last ')'
        fields = stat[close + 2:].split()
        parents.setdefault(int(fields[1]), []).append(int(entry))
        about[int(entry)] = (stat[stat.find(b"(") + 1:close].decode("utf-8", "replace"), fields[0] == b"Z")
    found: dict[int, tuple[str, bool]] = {}
    todo = list(parents.get(os.getpid(), []))
    while todo:
        pid = todo.pop()
        found[pid] = about[pid]
        todo.extend(parents.get(pid, []))
    return found


def _reap(main: int, status: list[int]) -> bool:
    """Reap every child that has ended (the main one's exit status goes into ``status``); False once none is left."""
    while True:
        try:
            pid, wait_status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return False
        if pid == 0:
            return True
        if pid == main:
            status.append(os.waitstatus_to_exitcode(wait_status))


def _kill_all(main: int, status: list[int], subreaper: bool) -> dict[int, str]:
    """SIGKILL every process below this one until none is left (reaped); those killed but ``main``: pid -> name."""
    killed: dict[int, str] = {}
    deadline = time.monotonic() + KILL_S
    while True:
        if subreaper:  # each round catches what the last one's processes forked before they died
            for pid, (name, zombie) in _descendants().items():
                if not zombie:
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.kill(pid, signal.SIGKILL)
                    if pid != main:
                        killed.setdefault(pid, name)
        else:  # orphans went to init: the program's process group is what can still be reached
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(main, signal.SIGKILL)
        if not _reap(main, status) or time.monotonic() > deadline:
            return killed
        time.sleep(0.005)


def _pump(poller: select.poll, sinks: dict[int, Capped], timeout_s: float) -> None:
    """Copy what the pipes hold into their files, waiting at most ``timeout_s``; close a pipe at its end."""
    for fd, _ in poller.poll(max(0.0, timeout_s) * 1000):
        try:
            data = os.read(fd, CHUNK)
        except OSError:
            data = b""
        if data:
            sinks[fd].write(data)
        else:
            poller.unregister(fd)
            os.close(fd)
            sinks[fd].reading = False


def supervise(spec: dict[str, Any]) -> dict[str, Any]:
    """Run the program ``spec`` describes to its end, its limit or a stop; the report (see containment)."""
    prctl = _prctl()
    subreaper = prctl is not None and prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    if prctl is not None:
        prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    for sig in (signal.SIGUSR1, signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, _on_signal)
    if os.getppid() != spec["parent"]:  # slamreplay died before PR_SET_PDEATHSIG was set
        return {"start_error": "slamreplay's process ended before the program started"}
    limit = spec["memory_bytes"]

    def in_child() -> None:  # between fork and exec, in the program's process
        if limit is not None:
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        if prctl is not None:  # dies with us even if we are killed before we can kill it
            prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)

    pipes = {"stdout": os.pipe(), "stderr": os.pipe()}
    sinks = {r: Capped(spec[name], spec["cap"], name) for name, (r, _) in pipes.items()}
    start = time.monotonic()
    try:
        with open(spec["stdin"] or os.devnull, "rb") as stdin:
            proc = subprocess.Popen(spec["argv"], cwd=spec["cwd"], env=spec["env"], stdin=stdin,
                                    stdout=pipes["stdout"][1], stderr=pipes["stderr"][1], start_new_session=True,
                                    preexec_fn=in_child)
    except (OSError, subprocess.SubprocessError) as err:  # SubprocessError: in_child failed
        return {"start_error": getattr(err, "strerror", None) or str(err)}
    finally:
        for _, w in pipes.values():
            os.close(w)  # the program holds the write ends now: an end of file means every writer is gone
    poller = select.poll()
    for fd in sinks:
        poller.register(fd, select.POLLIN)
    status: list[int] = []
    timed_out = False
    while not status and not _stop:
        left = start + spec["timeout_s"] - time.monotonic()
        if left <= 0:
            timed_out = True
            break
        _pump(poller, sinks, min(POLL_S, left))
        _reap(proc.pid, status)
    wall_s = time.monotonic() - start
    killed = _kill_all(proc.pid, status, subreaper)
    end = time.monotonic() + DRAIN_S
    while any(s.reading for s in sinks.values()) and time.monotonic() < end:
        _pump(poller, sinks, end - time.monotonic())
    streams = {name: sinks[r].close() for name, (r, _) in pipes.items()}
    return {"status": status[0] if status else None, "timed_out": timed_out, "stopped": _stop[0] if _stop else None,
            "wall_s": wall_s, "killed": sorted(killed.items()), "subreaper": subreaper, **streams}


def main() -> None:
    with open(sys.argv[1]) as f:
        spec = json.load(f)
    report = supervise(spec)
    tmp = spec["report"] + ".tmp"
    with open(tmp, "w") as f:
        json.dump(report, f)
    os.replace(tmp, spec["report"])  # a report is read whole or not at all
    if report.get("stopped") in ("SIGTERM", "SIGHUP"):
        deadline = time.monotonic() + ORPHAN_WAIT_S
        while os.getppid() == spec["parent"] and time.monotonic() < deadline:
            time.sleep(0.01)
    if os.getppid() != spec["parent"] and spec.get("cleanup"):  # slamreplay died: nobody else removes its files
        shutil.rmtree(spec["cleanup"], ignore_errors=True)


if __name__ == "__main__":
    main()
