"""Whether two runs' ``run.rrd`` files hold the same content: ``rerun rrd compare``, said in the user's terms."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path


def rerun_cli() -> str | None:
    """The ``rerun`` executable that ships with rerun-sdk (beside this Python, or on PATH)."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def rrd_content_equal(a: Path, b: Path) -> tuple[bool | None, str]:
    """``rerun rrd compare``: (True, "") when equal, (False, first lines of the diff), (None, why) if unknown."""
    exe = rerun_cli()
    if exe is None:
        return None, "the rerun CLI was not found; content equality not checked"
    try:
        proc = subprocess.run([exe, "rrd", "compare", str(a), str(b)], capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as err:
        return None, f"rerun rrd compare could not run: {err}"
    if proc.returncode == 0:
        return True, ""
    text = (proc.stderr or proc.stdout).strip()
    last = text.splitlines()[-1] if text else f"exit code {proc.returncode}"
    return False, last[:500]
