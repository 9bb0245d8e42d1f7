"""Whether two runs' ``run.rrd`` files hold the same content: ``rerun rrd compare``, said in the user's terms.

The verdict is ``rerun rrd compare``'s, ordered (DESIGN.md: the same chunks, in the same order). When it
finds a difference its message is an assertion from inside Rerun (``: Condition failed:
`lhs.num_rows() == rhs.num_rows()` (601 vs 1)``), so both files are then read with Rerun's Python API
(`rerun.chunk.RrdReader`) and the first difference is named: the application, an entity present on one
side only, an entity's row count on a timeline, a component present on one side only, the first step
at which a component's values differ, or, when every entity holds the same rows, the first place where
the rows are cut into chunks or ordered differently. Without the CLI, the Python comparison gives the
verdict on its own.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

STATIC = "static"  # the timeline key of static rows


def rerun_cli() -> str | None:
    """The ``rerun`` executable that ships with rerun-sdk (beside this Python, or on PATH)."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.exists() else shutil.which("rerun")


def rrd_content_equal(a: Path, b: Path) -> tuple[bool | None, str]:
    """``rerun rrd compare``: (True, "") when equal, (False, the first difference), (None, why) if unknown."""
    exe = rerun_cli()
    if exe is None:
        try:
            where = first_difference(a, b)
        except Exception as err:  # noqa: BLE001 - any failure to read means "not checked", never a verdict
            return None, f"the rerun CLI was not found and the files could not be read: {err}"
        return (True, "") if where is None else (False, where)
    try:
        proc = subprocess.run([exe, "rrd", "compare", str(a), str(b)], capture_output=True, text=True, timeout=600)
    except (OSError, subprocess.TimeoutExpired) as err:
        return None, f"rerun rrd compare could not run: {err}"
    if proc.returncode == 0:
        return True, ""
    try:
        where = first_difference(a, b)
    except Exception as err:  # noqa: BLE001 - the CLI's verdict stands; only the explanation is missing
        return False, f"rerun rrd compare finds them different; reading the files to say where failed: {err}"
    if where is None:
        return False, ("rerun rrd compare finds them different, but every entity holds the same rows and "
                       "components in the same chunks: the difference is in chunk metadata "
                       f"(`rerun rrd compare {a} {b}` prints it)")
    return False, where


@dataclass
class _Content:
    """One recording of an ``.rrd``: its chunks in ``rerun rrd compare``'s order and its rows per entity."""

    app_id: str
    chunks: list[tuple[str, str, int]] = field(default_factory=list)  # (entity, timelines, rows) per chunk
    rows: dict[tuple[str, str], int] = field(default_factory=lambda: defaultdict(int))  # (entity, timelines)
    columns: dict[tuple[str, str, str], list[Any]] = field(default_factory=lambda: defaultdict(list))


def _load(path: Path) -> _Content:
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    stores = reader.recordings()
    if len(stores) != 1:
        raise ValueError(f"{path} holds {len(stores)} recordings, not one")
    content = _Content(stores[0].application_id)
    # rrd compare reads the chunks back from a store that orders them by chunk id
    for ch in sorted(reader.stream(), key=lambda c: c.id):
        rb = ch.to_record_batch()
        kinds = {f.name: (f.metadata or {}).get(b"rerun:kind", b"").decode() for f in rb.schema}
        index = sorted((n for n, k in kinds.items() if k == "index"), key=lambda n: (n != "step", n))  # step first
        timelines = STATIC if ch.is_static else ", ".join(index)
        entity = str(ch.entity_path)
        content.chunks.append((entity, timelines, rb.num_rows))
        content.rows[entity, timelines] += rb.num_rows
        for name, kind in kinds.items():
            if kind == "data":
                content.columns[entity, timelines, name].append((rb.select(index), rb.column(name)))
    return content


def _rows(parts: list[Any]) -> tuple[Any, Any]:
    """(index table, values) of one component over its chunks, rows sorted by their time (stably)."""
    import pyarrow as pa
    import pyarrow.compute as pc

    index = pa.concat_tables([pa.Table.from_batches([i]) for i, _ in parts])
    values = pa.chunked_array([v for _, v in parts]).combine_chunks()
    if index.num_columns:
        order = pc.sort_indices(index, sort_keys=[(n, "ascending") for n in index.column_names])
        index, values = index.take(order), values.take(order)
    return index, values


def _when(index: Any, i: int) -> str:
    """A row's time in words: ``step 17, sensor_time 1.7 s``."""
    out = []
    for name in index.column_names:
        v = index.column(name)[i].as_py()
        out.append(f"{name} {v.total_seconds():g} s" if isinstance(v, timedelta) else f"{name} {v}")
    return ", ".join(out) or "the static row"


def _first_row_differing(ia: Any, va: Any, ib: Any, vb: Any) -> int:
    """Index of the first row whose time or value differs (rows of equal count), found block by block."""
    n, block = len(va), 256
    for lo in range(0, n, block):
        hi = min(n, lo + block)
        if not (ia.slice(lo, hi - lo).equals(ib.slice(lo, hi - lo))
                and va.slice(lo, hi - lo).equals(vb.slice(lo, hi - lo))):
            for i in range(lo, hi):
                if not (ia.slice(i, 1).equals(ib.slice(i, 1)) and va.slice(i, 1).equals(vb.slice(i, 1))):
                    return i
    return n


def _listing(names: list[str], limit: int = 3) -> str:
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def first_difference(a: Path, b: Path) -> str | None:
    """The first difference between two ``.rrd`` files in the user's terms; None when their content is the same.

    Entities, timelines and components are compared in sorted order, rows by their time; then the chunks in
    the order ``rerun rrd compare`` pairs them.
    """
    ca, cb = _load(a), _load(b)
    if ca.app_id != cb.app_id:
        return f"different applications: {ca.app_id!r} in A, {cb.app_id!r} in B"
    ents_a, ents_b = {e for e, _ in ca.rows}, {e for e, _ in cb.rows}
    for side, only in (("A", ents_a - ents_b), ("B", ents_b - ents_a)):
        if only:
            return f"entit{'y' if len(only) == 1 else 'ies'} only in {side}: {_listing(sorted(only))}"
    for key in sorted(set(ca.rows) | set(cb.rows)):
        na, nb = ca.rows.get(key, 0), cb.rows.get(key, 0)
        if na != nb:
            entity, timelines = key
            on = "static" if timelines == STATIC else f"on timelines {timelines}"
            return f"entity {entity}, {on}: {na} rows in A, {nb} in B"
    for side, keys in (("A", set(ca.columns) - set(cb.columns)), ("B", set(cb.columns) - set(ca.columns))):
        if keys:
            entity, timelines, name = min(keys)
            return f"entity {entity}: component {name} ({timelines}) only in {side}"
    for column in sorted(ca.columns):
        (ia, va), (ib, vb) = _rows(ca.columns[column]), _rows(cb.columns[column])
        entity, _, name = column
        if va.type != vb.type:
            return f"entity {entity}, component {name}: type {va.type} in A, {vb.type} in B"
        if not (ia.equals(ib) and va.equals(vb)):
            when = _when(ia, _first_row_differing(ia, va, ib, vb))
            return f"entity {entity}, component {name}: values differ from {when} on"
    for i, (x, y) in enumerate(zip(ca.chunks, cb.chunks, strict=False)):
        if x != y:
            return (f"the same rows per entity and component, but cut into chunks or ordered differently: "
                    f"chunk {i + 1} holds {_chunk_words(x)} in A, {_chunk_words(y)} in B")
    if len(ca.chunks) != len(cb.chunks):
        return (f"the same rows per entity and component, but cut into {len(ca.chunks)} chunks in A, "
                f"{len(cb.chunks)} in B")
    return None


def _chunk_words(chunk: tuple[str, str, int]) -> str:
    entity, timelines, rows = chunk
    what = "static " if timelines == STATIC else ""
    on = "" if timelines == STATIC else f" on {timelines}"
    return f"{rows} {what}row{'s' if rows != 1 else ''} of {entity}{on}"
