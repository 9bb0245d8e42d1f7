"""What a live recording left when its process died (``kill -9``, a power cut): salvaged into a recording, or why not.

A live recording writes ``FOLDER/live.mcap.partial`` (:mod:`.foxglove_live`) and renames it ``live.mcap`` at a
clean end. A process killed mid-way leaves the ``.partial``: every chunk flushed before (at most a second old) is
salvaged by :func:`slamreplay.recorder.recover.recover` into ``FOLDER/recovered.mcap``, which is then a
recording like any other. :func:`salvage_live` looks at one such folder; the service calls it for the folders its
live recordings left at start-up, and stores what it gives (or marks the recording failed with the reason).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.recover import RecoveryReport, describe, recover
from slamreplay.recorder.writer import partial_path

LIVE_FILE = "live.mcap"
RECOVERED_FILE = "recovered.mcap"


@dataclass(frozen=True, slots=True)
class Salvaged:
    """One folder's outcome: the recording to keep (``path``; None when nothing could be kept) and why.

    ``how``: ``complete`` (the recording had ended cleanly, its file whole), ``recovered`` (from the
    ``.partial``: ``report`` says what was kept and lost, None when an earlier call salvaged it), or ``failed``
    (``reason``).
    """

    folder: Path
    how: str
    path: Path | None = None
    report: RecoveryReport | None = None
    reason: str = ""

    def line(self) -> str:
        """One line for a log or a status: what was kept, or why nothing was."""
        if self.how == "complete":
            return f"{self.path}: the recording had ended cleanly; kept whole"
        if self.how == "recovered" and self.report is None:
            return f"{self.path}: salvaged before from {LIVE_FILE}.partial; kept"
        if self.how == "recovered":
            assert self.report is not None and self.path is not None
            return "; ".join(line.strip() for line in describe(self.report, self.path).splitlines())
        return f"{self.folder}: nothing salvaged: {self.reason}"


def salvage_live(folder: str | Path) -> Salvaged:
    """Salvage the live recording a dead process left in ``folder``.

    Parameters
    ----------
    folder : the recording's folder, holding ``live.mcap`` (a clean end not yet stored), or
        ``live.mcap.partial`` (the process died while recording), or a ``recovered.mcap`` of an
        earlier call that was not stored

    Returns
    -------
    Salvaged : the file to keep, or ``how == "failed"`` with the reason (no file, or none of its
        messages readable). The ``.partial`` is left as it is; the caller removes the folder once the
        recording is stored.
    """
    folder = Path(folder)
    done, recovered = folder / LIVE_FILE, folder / RECOVERED_FILE
    if done.is_file():
        return Salvaged(folder, "complete", done)
    if recovered.is_file():  # salvaged before, and the process died again before storing it
        return Salvaged(folder, "recovered", recovered)
    partial = partial_path(done)
    if not partial.is_file():
        return Salvaged(folder, "failed", reason="no recording file: the process stopped before it recorded")
    partial_path(recovered).unlink(missing_ok=True)  # an earlier salvage's, cut short with it
    try:
        report = recover(partial, recovered)
    except RecorderError as err:
        return Salvaged(folder, "failed", reason=f"{partial.name} cannot be salvaged: {err}")
    return Salvaged(folder, "recovered", recovered, report)


def live_leftovers(root: str | Path, prefix: str) -> list[Path]:
    """The folders ``root/PREFIX*`` live recordings left, oldest first (by modification time)."""
    root = Path(root)
    if not root.is_dir():
        return []
    found = [p for p in root.iterdir() if p.name.startswith(prefix) and p.is_dir()]
    return sorted(found, key=lambda p: (p.stat().st_mtime, p.name))
