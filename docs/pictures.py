"""The record of every picture in docs/images: what made it, from which commit, and what it shows.

One file, ``docs/images/pictures.json``, maps each picture's file name to::

    {"made_by": "make snapshots (docs/make_snapshots.py)",   # the make target or command that made it
     "commit": "<40 hex digits>",                             # the clean commit it was made from
     "sha256": "<the png's sha256>",
     "source": "demo",                                        # or what else it was made from (named runs)
     "metrics": {"sim-landmarks--dslam/landmark_rmse_m": 0.0439, ...},   # RUN/METRIC: value, as shown
     "note": "..."}                                           # optional: what to know about it

``make snapshots`` writes the records of the pictures it renders (and refuses a dirty tree:
it renders from an export of a commit); ``make test-docs`` checks them all
(tests/test_docs_pictures.py, and against its fresh demo in tests/test_readme.py):

- a picture that README.md or docs/*.md links has a record;
- the png is the one recorded (its sha256: a picture replaced by hand fails);
- the commit is a full commit id, not ``-dirty`` (a picture made from uncommitted code fails);
- every metric a record names is in the metric registry (a picture made before a rename fails);
- with ``source: demo``, every value equals a fresh demo's within the metric's tolerance.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
IMAGES = REPO / "docs" / "images"
RECORDS = IMAGES / "pictures.json"
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"""(?:\]\(|src=["'])(?:\.\./)?(?:docs/)?images/(?P<name>[\w.-]+\.png)""")
COMMIT = re.compile(r"[0-9a-f]{40}")


def sha256(path: Path) -> str:
    """The sha256 of a file, hex."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def linked(files: Iterable[Path] = DOCS) -> dict[str, str]:
    """``{picture name: "FILE:LINE"}`` of every docs/images picture the markdown ``files`` link (first link)."""
    out: dict[str, str] = {}
    for path in files:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for m in LINK.finditer(line):
                out.setdefault(m["name"], f"{path.relative_to(REPO)}:{n}")
    return out


def load(path: Path = RECORDS) -> dict[str, dict[str, Any]]:
    """The records (empty when there is no file yet)."""
    return json.loads(path.read_text()) if path.is_file() else {}


def save(records: Mapping[str, Mapping[str, Any]], path: Path = RECORDS) -> None:
    """Write the records, sorted, one picture per block (a diff shows which changed)."""
    path.write_text(json.dumps(dict(sorted(records.items())), indent=1, sort_keys=True) + "\n")


def record(png: Path, made_by: str, commit: str, source: str, metrics: Mapping[str, float | None],
           note: str = "") -> dict[str, Any]:
    """The record of ``png`` as it is now (its sha256): what made it, from which clean commit, what it shows."""
    if not COMMIT.fullmatch(commit):
        raise ValueError(f"{png.name}: a picture is recorded from a clean commit (40 hex digits), not {commit!r}")
    return {"made_by": made_by, "commit": commit, "sha256": sha256(png), "source": source, "metrics": dict(metrics),
            **({"note": note} if note else {})}


def split(key: str) -> tuple[str, str]:
    """``RUN/METRIC`` -> (RUN, METRIC)."""
    run, _, name = key.rpartition("/")
    return run, name


def problems(records: Mapping[str, Mapping[str, Any]], images: Path, links: Mapping[str, str],
             registered: Callable[[str], bool]) -> list[str]:
    """Every way the records disagree with the pictures, the links and the registry, one line each."""
    out = [f"{where}: links {name}, which has no record in {RECORDS.relative_to(REPO)} "
           f"(make snapshots writes the viewer's pictures' records; docs/pictures.py says what a record holds)"
           for name, where in sorted(links.items()) if name not in records]
    for name, rec in sorted(records.items()):
        png = images / name
        if not png.is_file():
            out.append(f"{name}: recorded, but there is no such picture in {images.name}/")
            continue
        if rec.get("sha256") != sha256(png):
            out.append(f"{name}: the png is not the one recorded (sha256 differs): replaced by hand? "
                       f"Make it with {rec.get('made_by', 'its make target')} so that its record says what it shows")
        commit = str(rec.get("commit", ""))
        if not COMMIT.fullmatch(commit):
            out.append(f"{name}: made from {commit or 'no recorded commit'!r}, not a clean commit: "
                       f"commit the code, then make it again ({rec.get('made_by', '?')})")
        if not rec.get("made_by"):
            out.append(f"{name}: the record does not say what made it (made_by)")
        for key in sorted(rec.get("metrics", {})):
            metric = split(key)[1]
            if not registered(metric):
                out.append(f"{name}: shows metric {metric!r}, which the metric registry does not have "
                           f"(renamed or retired): make the picture again")
    return out


def value_problems(records: Mapping[str, Mapping[str, Any]], demo: Path,
                   tolerance: Callable[[Mapping[str, Any], float], float]) -> list[str]:
    """Every recorded value of a demo picture that a fresh demo in ``demo`` does not give (beyond
    ``tolerance(metrics.json entry, recorded value)``)."""
    out: list[str] = []
    fresh: dict[str, dict[str, Any]] = {}
    for name, rec in sorted(records.items()):
        if rec.get("source") != "demo":
            continue
        for key, shown in sorted(rec.get("metrics", {}).items()):
            run, metric = split(key)
            if run not in fresh:
                doc = demo / run / "metrics.json"
                fresh[run] = json.loads(doc.read_text())["metrics"] if doc.is_file() else {}
            entry = fresh[run].get(metric)
            if entry is None:
                out.append(f"{name}: shows {key} = {shown:.6g}; a fresh demo has no such metric")
            elif abs(float(entry["value"]) - float(shown)) > tolerance(entry, float(shown)):
                out.append(f"{name}: shows {key} = {shown:.6g}; a fresh demo gives {float(entry['value']):.6g}")
    return out
