"""`slamreplay snapshot`: render a run's layout in the real Rerun viewer, one PNG per tab.

The viewer is Rerun's own (the ``rerun`` executable that rerun-sdk installs) started headless
(``--headless``: an offscreen window driven through its gRPC control API), so what the PNGs show
is what a user sees. It needs a Vulkan driver; on a machine without a GPU Mesa's software
rasterizer does (Debian: ``mesa-vulkan-drivers``). Nothing is installed here: a missing driver
is a clear error naming the package.

For each tab of the run's blueprint the tab is made active, the time cursor is put at the end
(or the start, or a given step) and paused, and the viewer saves a screenshot. The blueprint
the run carries is left as it is: only the viewer's copy changes.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import glob
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slamreplay.recorder.files import atomic_write
from slamreplay.replay.engine.views import STEP
from slamreplay.replay.errors import ReplayError

VULKAN_ICD_DIRS = ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d")
INSTALL_HINT = ("on Debian/Ubuntu without a GPU, Mesa's Vulkan software rasterizer: "
                "sudo apt-get install mesa-vulkan-drivers libvulkan1 (make viewer-deps in a checkout)")
TOAST_S = 6.0  # the viewer's start-up notifications fade after about 5 s


@dataclass(frozen=True, slots=True)
class Shot:
    tab: str
    path: Path


def resolve_rrd(source: Path) -> Path:
    """The ``.rrd`` of a run directory, or the file itself; ReplayError otherwise."""
    if source.is_dir():
        source = source / "run.rrd"
        if not source.is_file():
            raise ReplayError(f"{source.parent} has no run.rrd: it is not a finished run directory")
    elif not source.is_file():
        raise ReplayError(f"{source}: no such file or directory")
    with open(source, "rb") as f:
        if f.read(4) not in (b"RRF2", b"RRF1", b"RRIS"):
            raise ReplayError(f"{source} is not a Rerun .rrd file")
    return source


def parse_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d{2,5})x(\d{2,5})", text.strip())
    if not match:
        raise ReplayError(f"--size expects WIDTHxHEIGHT in pixels, e.g. 1600x900, got {text!r}")
    w, h = int(match[1]), int(match[2])
    if not (320 <= w <= 7680 and 240 <= h <= 4320):
        raise ReplayError(f"--size {text}: width must be 320-7680 and height 240-4320 pixels")
    return w, h


def parse_at(text: str) -> str | int:
    if text in ("end", "start"):
        return text
    try:
        step = int(text)
    except ValueError:
        raise ReplayError(f"--at expects end, start or a step number, got {text!r}") from None
    if step < 0:
        raise ReplayError(f"--at {text}: a step is >= 0")
    return step


def rerun_executable() -> Path:
    """The ``rerun`` installed beside this interpreter (the one matching rerun-sdk), else on PATH."""
    here = Path(sys.executable).parent / "rerun"
    if here.is_file():
        return here
    found = shutil.which("rerun")
    if found is None:
        raise ReplayError("the rerun executable was not found: install rerun-sdk 0.41 (pip install rerun-sdk~=0.41.0)")
    return Path(found)


def check_graphics() -> None:
    """ReplayError naming the Debian packages when no Vulkan loader or driver is installed."""
    if ctypes.util.find_library("vulkan") is None:
        raise ReplayError(f"snapshot needs a Vulkan loader and driver, and none is installed: {INSTALL_HINT}")
    if not any(glob.glob(os.path.join(d, "*.json")) for d in VULKAN_ICD_DIRS) and "VK_ICD_FILENAMES" not in os.environ:
        raise ReplayError(f"snapshot needs a Vulkan driver, and none is installed: {INSTALL_HINT}")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def headless_viewer(size: tuple[int, int], timeout_s: float = 30.0) -> Iterator[Any]:
    """A headless Rerun viewer of ``size`` pixels and a client connected to it; stopped on exit."""
    try:
        from rerun.experimental import ViewerClient
    except ImportError:
        raise ReplayError("snapshot drives the viewer through rerun-sdk 0.41's ViewerClient, which this "
                          "install lacks (rerun-sdk 0.39 on Python 3.10): run it from Python 3.11+") from None
    check_graphics()
    port = _free_port()
    cmd = [str(rerun_executable()), "--headless", "--port", str(port), "--window-size", f"{size[0]}x{size[1]}",
           "--hide-welcome-screen", "--memory-limit", "4GB"]
    # Its own session: the `rerun` entry point starts the viewer binary as a child, and both must go at the end.
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    started = time.monotonic()
    try:
        client = None
        while client is None:
            if proc.poll() is not None:
                err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
                panic = next((ln for ln in err.splitlines() if "adapter" in ln.lower() or "panic" in ln.lower()), "")
                raise ReplayError(f"the headless Rerun viewer exited at start ({panic.strip() or 'no message'}); "
                                  f"a software Vulkan driver may be missing: {INSTALL_HINT}")
            try:
                candidate = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
                candidate.get_state()
                client = candidate
            except Exception:  # noqa: BLE001 -- not listening yet; the loop's deadline bounds the wait
                if time.monotonic() - started > timeout_s:
                    raise ReplayError(f"the headless Rerun viewer did not answer within {timeout_s:.0f} s") from None
                time.sleep(0.1)
        yield client
    finally:
        _stop_group(proc)


def _stop_group(proc: subprocess.Popen[bytes]) -> None:
    """Terminate the viewer's whole process group; SIGKILL what is left after 10 s."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    deadline = time.monotonic() + 10.0
    while _group_alive(proc.pid) and time.monotonic() < deadline:
        proc.poll()  # reaps the leader: the group lives on while the viewer binary does
        time.sleep(0.05)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    if proc.stderr is not None:
        proc.stderr.close()


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _tabs(bp: dict[str, Any]) -> tuple[str | None, list[tuple[str, str]]]:
    """(key of the root Tabs container, [(child id, display name)]) of a viewer blueprint (JSON form)."""
    root = bp.get("/viewport", {}).get("ViewportBlueprint", {}).get("root_container")
    key = f"/container/{root}"
    container = bp.get(key, {}).get("ContainerBlueprint", {})
    if container.get("container_kind") != "Tabs":
        return None, [("", "layout")]
    out = []
    for child in _as_list(container.get("contents", [])):
        kind = "ContainerBlueprint" if child.startswith("container/") else "ViewBlueprint"
        name = bp.get(f"/{child}", {}).get(kind, {}).get("display_name") or child.split("/")[-1][:8]
        out.append((child, str(name)))
    return key, out


def _views_in(bp: dict[str, Any], child: str) -> list[tuple[str, str]]:
    """(view id, display name) of every view inside a blueprint node (``view/<id>`` or ``container/<id>``)."""
    if child.startswith("view/"):
        name = bp.get(f"/{child}", {}).get("ViewBlueprint", {}).get("display_name", "")
        return [(child.removeprefix("view/"), str(name))]
    kids = _as_list(bp.get(f"/{child}", {}).get("ContainerBlueprint", {}).get("contents", []))
    return [v for k in kids for v in _views_in(bp, k)]


def _as_list(value: Any) -> list[str]:
    """A blueprint's list field (the viewer writes a one-element list as a bare string)."""
    return [value] if isinstance(value, str) else list(value)


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "tab"


def snapshot(source: Path, out_dir: Path, *, size: tuple[int, int] = (1600, 900), at: str | int = "end",
             timeline: str = STEP, per_view: bool = False) -> list[Shot]:
    """Render every tab of a run's layout to ``out_dir/NN-<tab>.png``; the shots, in tab order.

    With ``per_view`` each view of each tab is saved too, as ``NN-<tab>--MM-<view>.png``.
    """
    rrd = resolve_rrd(source)
    out_dir.mkdir(parents=True, exist_ok=True)
    shots: list[Shot] = []
    started = time.monotonic()
    with headless_viewer(size) as viewer:
        viewer.open([str(rrd.resolve())])
        recording = _wait_loaded(viewer, timeline)
        line = next(t for t in recording.timelines if t.name == timeline)
        cursor = line.end if at == "end" else line.start if at == "start" else int(at)
        if not line.start <= cursor <= line.end:
            raise ReplayError(f"--at {at}: the run's steps are {line.start} to {line.end}")
        bp = viewer.get_blueprint().blueprint
        bp["/top_panel"] = {"PanelBlueprint": {"state": "Hidden"}}
        bp.setdefault("/time_panel", {}).setdefault("TimePanelBlueprint", {})["state"] = "Collapsed"
        key, tabs = _tabs(bp)
        time.sleep(max(0.0, TOAST_S - (time.monotonic() - started)))
        for i, (child, name) in enumerate(tabs):
            if key is not None:
                bp[key]["ContainerBlueprint"]["active_tab"] = child
            viewer.set_blueprint(bp, "recording")
            viewer.set_time(timeline, sequence=cursor, play_state="paused")
            path = out_dir / f"{i + 1:02d}-{_slug(name)}.png"
            atomic_write(path, _settled_screenshot(viewer))
            shots.append(Shot(name, path))
            if per_view and key is not None:
                for j, (view_id, view_name) in enumerate(_views_in(bp, child)):
                    vpath = out_dir / f"{i + 1:02d}-{_slug(name)}--{j + 1:02d}-{_slug(view_name)}.png"
                    atomic_write(vpath, bytes(viewer.take_screenshot(view_id)))
                    shots.append(Shot(f"{name} / {view_name}", vpath))
    return shots


def _settled_screenshot(viewer: Any, timeout_s: float = 20.0, pause_s: float = 0.5) -> bytes:
    """A PNG of the viewer once two frames in a row are the same: plots animate to their bounds."""
    deadline = time.monotonic() + timeout_s
    last = viewer.take_screenshot()
    while time.monotonic() < deadline:
        time.sleep(pause_s)
        shot = viewer.take_screenshot()
        if shot == last:
            break
        last = shot
    return bytes(last)


def _wait_loaded(viewer: Any, timeline: str, timeout_s: float = 60.0) -> Any:
    """The recording once the viewer has loaded it and knows ``timeline``."""
    deadline = time.monotonic() + timeout_s
    while True:
        state = viewer.get_state()
        rec = next((r for r in state.recordings if r.store_id == state.active_recording), None)
        if rec is not None and not state.loading and any(t.name == timeline for t in rec.timelines):
            return rec
        if time.monotonic() > deadline:
            raise ReplayError(f"the viewer did not load the recording within {timeout_s:.0f} s "
                              f"(or it has no {timeline!r} timeline)")
        time.sleep(0.2)
