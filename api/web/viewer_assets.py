"""The Rerun web viewer's files, taken from the installed rerun-sdk, for the service to serve itself.

rerun-sdk's wheel embeds the web viewer (``index.html``, ``re_viewer.js``, the ``.wasm``) in its
extension module and serves them with ``rerun.start_web_viewer_server``; some wheels ship them
as ``rerun/web_viewer.zip`` instead. Either way nothing comes from outside the installed
package: the files are copied once per rerun-sdk version into a cache directory (from the zip,
or from the SDK's own server, started for a moment in a child process on a loopback port), and
the service serves that directory under ``/viewer/``. ``index.html`` loses its links to web
fonts (the viewer draws its own text), so opening it fetches nothing from another host, and
gains a script that quietens it (``QUIET``): the viewer logs at debug level, about 11,000
console lines for one run, which hid real errors.
The viewer loads a recording given as ``?url=http://.../run.rrd``; ``&log=debug`` brings its
debug lines back.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
import zipfile
from pathlib import Path

FILES = ("index.html", "re_viewer.js", "re_viewer_bg.wasm", "favicon.ico", "apple-touch-icon.png", "sw.js")
REQUIRED = ("index.html", "re_viewer.js", "re_viewer_bg.wasm")
_FONT_LINKS = re.compile(r'\s*<link[^>]*(fonts\.googleapis\.com|fonts\.gstatic\.com)[^>]*/>', re.S)
_lock = threading.Lock()
# Bumped whenever the rewrite of index.html changes, so that a cached copy made by an older slamreplay is redone.
PATCH = "q1"

# The viewer's Rust logger writes at debug level and cannot be configured from the page; its JavaScript glue looks
# up console.* and fetch at each call, so replacing them before the viewer loads sets its level. Its usage
# statistics and version check go to other hosts: the page's CSP already blocks them, and answering them here,
# without a request, spares a CSP error and a "Failed to fetch" per attempt in the console.
QUIET = """<script>
(() => {
  const levels = ["trace", "debug", "info", "warn", "error"];
  const asked = levels.indexOf(new URLSearchParams(location.search).get("log"));
  const least = asked >= 0 ? asked : levels.indexOf("warn");
  for (const name of levels.slice(0, least)) console[name] = () => {};
  if (least > levels.indexOf("debug")) console.log = () => {};
  const fetchHere = window.fetch.bind(window);
  window.fetch = (input, init) => {
    const url = new URL(input instanceof Request ? input.url : String(input), location.href);
    if (url.origin === location.origin) return fetchHere(input, init);
    return Promise.resolve(new Response("", {status: 403, statusText: "this viewer reaches its own server only"}));
  };
})();
</script>
"""


class ViewerAssetsError(RuntimeError):
    """The installed rerun-sdk did not give its web viewer files."""


def rerun_version() -> str:
    from importlib.metadata import version

    return version("rerun-sdk")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


_SERVE = """
import sys, time
import rerun as rr
rr.start_web_viewer_server(int(sys.argv[1]))
print("ready", flush=True)
time.sleep(float(sys.argv[2]))
"""


def _from_server(out: Path, timeout_s: float = 60.0) -> None:
    """Copy the files the SDK's own web viewer server serves (a child process, loopback only)."""
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-c", _SERVE, str(port), str(timeout_s)], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, env={**os.environ, "RUST_LOG": "error"})
    try:
        assert proc.stdout is not None
        if proc.stdout.readline().strip() != b"ready":
            raise ViewerAssetsError(f"rerun's web viewer server did not start (exit code {proc.wait(5)})")
        deadline = time.monotonic() + timeout_s
        for name in FILES:
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/{name}", timeout=30) as r, \
                            open(out / name, "wb") as f:
                        shutil.copyfileobj(r, f, 1 << 20)
                    break
                except urllib.error.HTTPError as err:
                    if name in REQUIRED:
                        raise ViewerAssetsError(f"rerun's web viewer server has no {name}: {err}") from None
                    break
                except OSError:  # not listening yet
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.1)
    finally:
        proc.kill()
        proc.wait(10)


def _from_zip(archive: Path, out: Path) -> None:
    with zipfile.ZipFile(archive) as z:
        for info in z.infolist():
            name = Path(info.filename).name
            if name in FILES and not info.is_dir():
                (out / name).write_bytes(z.read(info))


def quiet_index(html: str) -> str:
    """The viewer's ``index.html`` with ``QUIET`` run before anything else of the page."""
    head = html.find("</head>")
    if head < 0:
        raise ViewerAssetsError("the installed rerun-sdk's index.html has no </head>")
    return html[:head] + QUIET + html[head:]


def viewer_dir(cache: Path) -> Path:
    """The web viewer's files for the installed rerun-sdk, copied into ``cache/<version>-<PATCH>/`` on first use."""
    target = cache / f"{rerun_version()}-{PATCH}"
    if (target / "index.html").is_file():
        return target
    with _lock:
        if (target / "index.html").is_file():
            return target
        cache.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=cache, prefix=".viewer-"))
        try:
            import rerun

            archive = Path(rerun.__file__).parent / "web_viewer.zip"
            if archive.is_file():
                _from_zip(archive, tmp)
            else:
                _from_server(tmp)
            missing = [n for n in REQUIRED if not (tmp / n).is_file()]
            if missing:
                raise ViewerAssetsError(f"the installed rerun-sdk gave no {', '.join(missing)}")
            index = tmp / "index.html"
            index.write_text(quiet_index(_FONT_LINKS.sub("", index.read_text())))
            if target.exists():
                shutil.rmtree(target)
            os.replace(tmp, target)
            for old in cache.iterdir():  # copies for another rerun-sdk or an older rewrite: 40 MB each, unused
                if old.is_dir() and old != target and not old.name.startswith("."):
                    shutil.rmtree(old, ignore_errors=True)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    return target
