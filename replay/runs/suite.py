"""Suite files: recordings x pipelines x config variants x seeds, read from TOML.

A suite names its recordings (a file ``path``, a ``url`` that fsspec opens, or a simulator
``sim`` with its CLI options in ``args`` and one recording per simulator seed), pipelines with
named config variants, and the run seeds. ``load_suite`` validates all of it against the
simulators' and pipelines' own config classes, so a typo fails before anything runs, and each
error names the file, the line and the key::

    seeds = [1]                                   # run seeds (default [0])
    [recordings.landmarks]
    sim = "sim-landmarks"                         # or: path = "recordings/robot1.mcap" / url = "s3://..."
    args = { duration-s = 120 }                   # the simulator's CLI options (`slamreplay record sim-landmarks -h`)
    seeds = [1, 2, 3]                             # one recording per simulator seed (default [0])
    [pipelines.odometry]                          # no variants: one variant named "default"
    [pipelines.dslam.variants]
    default = {}
    tight = { range_sigma_m = 0.05 }              # config keys as `slamreplay pipelines` lists them
    paper = { preset = "paper" }                  # a preset of the pipeline's, its keys overridable beside it

``preset`` names one of the pipeline's presets (``slamreplay pipelines`` lists them) for a variant,
or for all of them beside ``variants`` (a variant's own ``preset`` wins). It is written out into
the variant's config values, under the keys the variant sets itself, as ``slamreplay run
--preset`` layers it: the cell's config (and so its cache key) holds every value the preset set.

A *cell* is one run: (recording, recording seed, pipeline, variant, run seed). Cells that
differ only by their seeds form a *group*, which ``compare`` matches across two results.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the same parser, as the tomli package
    import tomli as tomllib

from slamreplay.recorder.options import did_you_mean, typed_fields
from slamreplay.replay.engine.declared import use_declarations
from slamreplay.replay.engine.pipeline import get_pipeline, resolve_config
from slamreplay.replay.errors import ReplayError

SIMULATORS = ("sim-landmarks", "sim-seabed", "sim-corridor")
TOP_KEYS = {"seeds", "recordings", "pipelines", "name", "declarations"}
RECORDING_KEYS = {"path", "url", "sim", "args", "seeds", "topic_map"}
ID_RECORDING_KEYS = {"id"}  # a suite sent to the service names uploaded recordings by id, nothing else
PIPELINE_KEYS = {"variants", "config", "preset"}
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


@dataclass(frozen=True, slots=True)
class RecordingSpec:
    """One named recording source; ``seeds`` only for a simulator (one recording each)."""

    name: str
    path: Path | None = None
    url: str | None = None
    sim: str | None = None
    args: dict[str, Any] = field(default_factory=dict)
    seeds: tuple[int, ...] = (0,)
    topic_map: dict[str, str] = field(default_factory=dict)
    id: str | None = None  # the service's recording id (sha256), for a suite sent to the service


@dataclass(frozen=True, slots=True)
class Cell:
    """One run of a suite; ``recording_seed`` is None unless the recording is simulated."""

    recording: str
    recording_seed: int | None
    pipeline: str
    variant: str
    seed: int
    config: dict[str, Any]

    @property
    def group(self) -> tuple[str, str, str]:
        """What ``compare`` matches across results: (recording, pipeline, variant)."""
        return (self.recording, self.pipeline, self.variant)

    @property
    def replicate(self) -> tuple[int, int]:
        """The seeds that tell runs of one group apart, for pairing A with B."""
        return (-1 if self.recording_seed is None else self.recording_seed, self.seed)

    @property
    def label(self) -> str:
        rs = "" if self.recording_seed is None else f"-r{self.recording_seed}"
        return f"{self.recording}{rs}-{self.pipeline}-{self.variant}-s{self.seed}"

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True, slots=True)
class Suite:
    path: Path
    name: str
    seeds: tuple[int, ...]
    recordings: dict[str, RecordingSpec]
    pipelines: dict[str, dict[str, dict[str, Any]]]  # pipeline -> variant -> config values
    text: str

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.text.encode()).hexdigest()

    def cells(self) -> list[Cell]:
        """Every run, in a stable order: recording, recording seed, pipeline, variant, seed."""
        out = []
        for rec in self.recordings.values():
            rseeds: Sequence[int | None] = rec.seeds if rec.sim else (None,)
            for rseed in rseeds:
                for pipeline, variants in self.pipelines.items():
                    for variant, config in variants.items():
                        for seed in self.seeds:
                            out.append(Cell(rec.name, rseed, pipeline, variant, seed, dict(config)))
        return out


# ---------------------------------------------------------------------------------------
# Where a key is in the text: tomllib keeps no positions.


def _split_dotted(key: str) -> list[str]:
    parts = re.findall(r'"((?:[^"\\]|\\.)*)"|\'([^\']*)\'|([^.\s]+)', key)
    return [a or b or c for a, b, c in parts]


_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
_ASSIGN = re.compile(r"""^\s*((?:"[^"]*"|'[^']*'|[A-Za-z0-9_-]+)(?:\s*\.\s*(?:"[^"]*"|'[^']*'|[A-Za-z0-9_-]+))*)\s*=""")


def key_line(text: str, path: Sequence[str]) -> int | None:
    """1-based line of the key at ``path`` (a table header, a ``key =`` or a key in an inline table)."""
    path = list(path)
    header: list[str] = []
    best: tuple[int, int] | None = None  # (how many parts matched, line)
    for lineno, line in enumerate(text.splitlines(), 1):
        m = _HEADER.match(line)
        if m and "=" not in line.split("#")[0].split("]")[0]:
            header = _split_dotted(m.group(1))
            if header == path:
                return lineno
            if header[: len(path)] == path and (best is None or best[0] < len(path)):
                best = (len(path), lineno)
            continue
        m = _ASSIGN.match(line)
        if not m:
            continue
        full = header + _split_dotted(m.group(1))
        if full == path:
            return lineno
        if path[: len(full)] == full:  # an inline table holding the rest of the path?
            rest = line[m.end():]
            found = len(full)
            for part in path[len(full):]:
                if re.search(rf'(^|[{{,\s]){re.escape(part)}\s*=|"{re.escape(part)}"\s*=', rest):
                    found += 1
                else:
                    break
            if found == len(path):
                return lineno
            if best is None or best[0] < found:
                best = (found, lineno)
    return None if best is None else best[1]


def _printable(text: str) -> str:
    """``text`` with line breaks and other control characters escaped, so that an error stays one line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class _Checker:
    def __init__(self, path: Path, text: str) -> None:
        self.path, self.text = path, text

    def fail(self, keys: Sequence[str], what: str) -> ReplayError:
        line = key_line(self.text, keys)
        where = f"{self.path}:{line}" if line else str(self.path)
        # keys and values come from the file, where a quoted key or a string may hold a line break
        return ReplayError(_printable(f"{where}: {'.'.join(keys) or 'suite'}: {what}"))

    def table(self, value: Any, keys: Sequence[str]) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise self.fail(keys, f"must be a table, got {type(value).__name__} {value!r}")
        return value

    def seeds(self, value: Any, keys: Sequence[str]) -> tuple[int, ...]:
        if (not isinstance(value, list) or not value
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in value)):
            raise self.fail(keys, f"must be a non-empty list of integers >= 0, got {value!r}")
        if len(set(value)) != len(value):
            raise self.fail(keys, f"lists a seed twice: {value!r}")
        return tuple(value)

    def unknown(self, doc: Mapping[str, Any], allowed: set[str], keys: Sequence[str]) -> None:
        for key in doc:
            if key not in allowed:
                raise self.fail([*keys, key], f"unknown key; allowed here: {', '.join(sorted(allowed))}")

    def name(self, name: str, keys: Sequence[str]) -> None:
        if not NAME.fullmatch(name):
            raise self.fail(keys, "names must be letters, digits, '_', '-' or '.' (up to 64)")


def sim_config_class(sim: str) -> type:
    """The config dataclass of a simulator (the fields its CLI options set)."""
    if sim == "sim-landmarks":
        from slamreplay.recorder.sim.landmarks import LandmarkSimConfig
        return LandmarkSimConfig
    if sim == "sim-seabed":
        from slamreplay.recorder.sim.seabed import SeabedSimConfig
        return SeabedSimConfig
    if sim == "sim-corridor":
        from slamreplay.recorder.sim.corridor import CorridorConfig
        return CorridorConfig
    raise ReplayError(f"unknown simulator {sim!r}; known: {', '.join(SIMULATORS)}")


def sim_kwargs(sim: str, args: Mapping[str, Any]) -> dict[str, Any]:
    """CLI option names (``duration-s``) -> config field names (``duration_s``), each value converted to its
    field's type as ``slamreplay record`` converts it (``slamreplay.recorder.options``); ValueError if one is not."""
    return typed_fields(sim_config_class(sim), {k.replace("-", "_"): v for k, v in args.items()})


def _recording_by_id(chk: _Checker, name: str, doc: dict[str, Any], ids: Callable[[str], Path]) -> RecordingSpec:
    keys = ["recordings", name]
    for key in doc:
        if key in RECORDING_KEYS:
            raise chk.fail([*keys, key], 'the service runs uploaded recordings only: name one by id = "SHA256" '
                                         "(upload it with POST /recordings first)")
    chk.unknown(doc, ID_RECORDING_KEYS, keys)
    rid = doc.get("id")
    if not isinstance(rid, str) or not rid:
        raise chk.fail(keys, 'needs id = "SHA256" (the id POST /recordings answered)')
    try:
        path = ids(rid)
    except ReplayError as err:
        raise chk.fail([*keys, "id"], str(err)) from None
    return RecordingSpec(name, path=path, id=rid)


def _recording(chk: _Checker, name: str, doc: Any, base: Path,
               ids: Callable[[str], Path] | None = None) -> RecordingSpec:
    keys = ["recordings", name]
    chk.name(name, keys)
    doc = chk.table(doc, keys)
    if ids is not None:
        return _recording_by_id(chk, name, doc, ids)
    chk.unknown(doc, RECORDING_KEYS, keys)
    sources = [k for k in ("path", "url", "sim") if k in doc]
    if len(sources) != 1:
        raise chk.fail(keys, "needs exactly one of path = \"FILE\", url = \"URL\" or sim = \"sim-landmarks\""
                             f" (got {', '.join(sources) or 'none'})")
    source = sources[0]
    if not isinstance(doc[source], str) or not doc[source]:
        raise chk.fail([*keys, source], f"must be a non-empty string, got {doc[source]!r}")
    topic_map = chk.table(doc.get("topic_map", {}), [*keys, "topic_map"])
    if not all(isinstance(v, str) for v in topic_map.values()):
        raise chk.fail([*keys, "topic_map"], "maps file topics to slamreplay topics: strings only")
    if source != "sim":
        for key in ("args", "seeds"):
            if key in doc:
                raise chk.fail([*keys, key], f"only applies to a simulated recording (sim = ...), not to {source}")
    if source == "path":
        try:
            p = Path(doc["path"]).expanduser()
        except RuntimeError as err:  # "~name" of a user this machine does not know
            raise chk.fail([*keys, "path"], f"cannot expand {doc['path']!r}: {err}") from None
        p = p if p.is_absolute() else (base / p)
        if not p.exists():
            raise chk.fail([*keys, "path"], f"{p} does not exist")
        return RecordingSpec(name, path=p, topic_map=topic_map)
    if source == "url":
        return RecordingSpec(name, url=doc["url"], topic_map=topic_map)
    sim = doc["sim"]
    if sim not in SIMULATORS:
        raise chk.fail([*keys, "sim"], f"unknown simulator {sim!r}; known: {', '.join(SIMULATORS)}")
    args = chk.table(doc.get("args", {}), [*keys, "args"])
    cls = sim_config_class(sim)
    fields = {f.name for f in dataclasses.fields(cls)}
    for key in args:
        if key.replace("-", "_") not in fields:
            opts = ", ".join(sorted(f.replace("_", "-") for f in fields))
            raise chk.fail([*keys, "args", key], f"{sim} has no option --{key}; its options: {opts}")
    try:
        cls(**sim_kwargs(sim, args))
    except (TypeError, ValueError) as err:
        raise chk.fail([*keys, "args"], f"invalid {sim} options: {err}") from None
    seeds = chk.seeds(doc.get("seeds", [0]), [*keys, "seeds"])
    return RecordingSpec(name, sim=sim, args=dict(args), seeds=seeds, topic_map=topic_map)


def _pipeline(chk: _Checker, name: str, doc: Any) -> dict[str, dict[str, Any]]:
    keys = ["pipelines", name]
    doc = chk.table(doc, keys)
    chk.unknown(doc, PIPELINE_KEYS, keys)
    try:
        cls = get_pipeline(name)
    except ReplayError as err:
        raise chk.fail(keys, str(err)) from None
    base = chk.table(doc.get("config", {}), [*keys, "config"])
    raw = chk.table(doc.get("variants", {"default": {}}), [*keys, "variants"])
    if not raw:
        raise chk.fail([*keys, "variants"], "is empty: name at least one variant, e.g. default = {}")
    variants = {}
    for variant, values in raw.items():
        vkeys = [*keys, "variants", variant]
        chk.name(variant, vkeys)
        values = {**base, **chk.table(values, vkeys)}
        if "preset" in values:
            preset, at = values.pop("preset"), [*vkeys, "preset"]
        else:
            preset, at = doc.get("preset"), [*keys, "preset"]
        if preset is not None:
            if not isinstance(preset, str) or preset not in cls.presets:
                have = ", ".join(sorted(cls.presets)) or "(none)"
                near = did_you_mean(preset, cls.presets, quote=True) if isinstance(preset, str) else ""
                raise chk.fail(at, f"pipeline {name} has no preset {preset!r}{near}; its presets: {have} "
                                   f"(see `slamreplay pipelines {name}`)")
            values = {**cls.presets[preset], **values}
        try:
            resolve_config(cls, values)
        except ReplayError as err:
            bad = re.search(r"config key '([^']+)'", str(err))
            at = [*vkeys, bad.group(1)] if bad and bad.group(1) in raw[variant] else vkeys
            raise chk.fail(at, str(err)) from None
        variants[variant] = values
    return variants


def _declarations(chk: _Checker, value: Any, base: Path) -> None:
    """``declarations = ["file.toml", ...]``: pipeline declaration files, used from here on (and by workers)."""
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise chk.fail(["declarations"], f"must be a list of declaration file paths, got {value!r}")
    files = [base / v for v in value]
    for v, f in zip(value, files, strict=True):
        if not f.is_file():
            raise chk.fail(["declarations"], f"{v}: no such file (paths are relative to the suite file)")
    use_declarations(files)


def parse_suite(text: str, path: Path, *, ids: Callable[[str], Path] | None = None, fmt: str = "toml") -> Suite:
    """Validate a suite's TOML ``text`` (from ``path``, the base of relative recording paths).

    With ``ids`` (the service), recordings are named only by ``id``, which ``ids`` turns into
    a local file (or raises ReplayError saying why not); ``fmt="json"`` reads the same
    structure as JSON (errors then name the key but no line).
    """
    chk = _Checker(path, text if fmt == "toml" else "")
    if fmt == "json":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as err:
            raise ReplayError(f"{path}: not valid JSON: {err}") from None
        if not isinstance(doc, dict):
            raise ReplayError(f"{path}: a suite must be a JSON object, got {type(doc).__name__}")
    elif fmt == "toml":
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ReplayError(f"{path}: not valid TOML: {err}") from None
    else:
        raise ReplayError(f"unknown suite format {fmt!r}: toml or json")
    chk.unknown(doc, TOP_KEYS, [])
    seeds = chk.seeds(doc.get("seeds", [0]), ["seeds"])
    recs = chk.table(doc.get("recordings"), ["recordings"]) if "recordings" in doc else {}
    pipes = chk.table(doc.get("pipelines"), ["pipelines"]) if "pipelines" in doc else {}
    if not recs:
        raise chk.fail([], "names no recordings: add a [recordings.NAME] table with path, url or sim")
    if not pipes:
        raise chk.fail([], "names no pipelines: add a [pipelines.NAME] table (see `slamreplay pipelines`)")
    base = path.resolve().parent
    if "declarations" in doc:  # files declaring external pipelines (docs/external.md), relative to the suite file
        if ids is not None:
            raise chk.fail(["declarations"], "a suite sent to the service cannot declare pipelines: its operator "
                                             "declares them (SLAMREPLAY_PIPELINES, docs/external.md)")
        _declarations(chk, doc["declarations"], base)
    recordings = {name: _recording(chk, name, d, base, ids) for name, d in recs.items()}
    pipelines = {name: _pipeline(chk, name, d) for name, d in pipes.items()}
    name = doc.get("name", path.stem)
    if not isinstance(name, str):
        raise chk.fail(["name"], f"must be a string, got {name!r}")
    return Suite(path, name, seeds, recordings, pipelines, text)


def load_suite(path: str | Path) -> Suite:
    """Read and validate the suite file at ``path``; ReplayError naming file, line and key."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ReplayError(f"suite file {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ReplayError(f"cannot read suite file {path}: {err}") from None
    return parse_suite(text, path)


def canonical(values: Mapping[str, Any]) -> str:
    """Canonical JSON of config or option values (sorted keys), for hashing."""
    return json.dumps(values, sort_keys=True, separators=(",", ":"), default=str)
