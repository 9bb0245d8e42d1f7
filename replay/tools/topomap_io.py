"""Topo-metric map files: ``np.savez`` of the :class:`~slamreplay.algorithms.topometric.TopoMap` arrays, no pickle.

A file holds one array per TopoMap array field plus ``header``, a uint8 array of UTF-8 JSON:
``{"format": "slamreplay.topomap", "version": 2, "config": <MapperConfig as a dict>}``. The mapping
pipeline writes it as ``map.npz`` in its run directory; a navigation run loads it with
:func:`load_map`.

Versions: 2 adds the optional evaluation-only array ``truth_poses`` (the ground-truth pose of each
location's reference image, NaN where unknown; absent when mapping had no ground truth). Version 1
files (no ``truth_poses``) still load, with ``truth_poses`` None.
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from slamreplay.algorithms.topometric import TopoMap, mapper_config_from_dict
from slamreplay.replay.errors import ReplayError

FORMAT = "slamreplay.topomap"
VERSION = 2
READS = (1, 2)  # version 1: the same arrays without truth_poses
OPTIONAL = ("truth_poses",)  # evaluation only, may be absent (always absent in version 1)
ARRAYS = tuple(f.name for f in dataclasses.fields(TopoMap) if f.name != "config" and f.name not in OPTIONAL)


def save_map(topomap: TopoMap) -> bytes:
    """The map as the bytes of an ``.npz`` file (compressed)."""
    header = {"format": FORMAT, "version": VERSION, "config": dataclasses.asdict(topomap.config)}
    buf = io.BytesIO()
    arrays: dict[str, Any] = {name: getattr(topomap, name) for name in ARRAYS}
    arrays.update({name: getattr(topomap, name) for name in OPTIONAL if getattr(topomap, name) is not None})
    arrays["header"] = np.frombuffer(json.dumps(header, sort_keys=True).encode(), np.uint8)
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def load_map(source: str | Path | bytes) -> TopoMap:
    """Read a map written by :func:`save_map` (a path or the bytes).

    Raises
    ------
    ReplayError
        The file is missing, not an ``.npz`` map, of another format version, or its arrays are
        inconsistent; the message says which.
    """
    name = "<bytes>" if isinstance(source, bytes) else str(source)
    try:
        raw = source if isinstance(source, bytes) else Path(source).read_bytes()
    except OSError as err:
        msg = f"cannot read topo-metric map {name}: {err.strerror or err}"
        raise ReplayError(msg) from err
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as npz:
            files = {k: npz[k] for k in npz.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as err:
        msg = f"{name} is not a topo-metric map (.npz written by slamreplay): {err}"
        raise ReplayError(msg) from err
    if "header" not in files:
        raise ReplayError(f"{name} is not a topo-metric map: no header array")
    try:
        header = json.loads(files["header"].tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        msg = f"{name}: the map header is not JSON: {err}"
        raise ReplayError(msg) from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        found = header.get("format") if isinstance(header, dict) else None
        raise ReplayError(f"{name} is not a topo-metric map: header format {found!r}, expected {FORMAT!r}")
    version = header.get("version")
    if version not in READS:
        raise ReplayError(f"{name}: map format version {version!r} is not supported (this slamreplay reads "
                          f"versions {', '.join(map(str, READS))}); rebuild the map with the topometric pipeline")
    missing = [k for k in ARRAYS if k not in files]
    if missing:
        raise ReplayError(f"{name}: the map lacks the arrays {', '.join(missing)}")
    try:
        config = mapper_config_from_dict(header.get("config", {}))
        optional = {k: files[k] for k in OPTIONAL if k in files and version >= 2}
        return TopoMap(config, **{k: files[k] for k in ARRAYS}, **optional)
    except (TypeError, ValueError) as err:
        msg = f"{name}: inconsistent topo-metric map: {err}"
        raise ReplayError(msg) from err
