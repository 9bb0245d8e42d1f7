"""The pipeline interface, configuration handling, and the registry of pipelines.

A pipeline adapts recorded messages to one algorithm: it names the topics it needs, has a
frozen-dataclass ``Config`` with defaults and validation, processes one message per
``step`` and returns its metrics from ``finish``. It draws through the observer handed in
and never reads the wall clock: its results depend on the recording, config and seed only.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import typing
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np
import rerun.blueprint as rrb

from slamreplay.algorithms.observe import Observation
from slamreplay.recorder.codec.bounds import MAX_JSON_DEPTH, json_depth
from slamreplay.recorder.errors import RecorderError
from slamreplay.recorder.options import did_you_mean, parse_value, type_name
from slamreplay.recorder.plugins import Plugin, discover, missing_builtins_hint
from slamreplay.recorder.sensor_model import SensorModel
from slamreplay.recorder.writer import GROUND_TRUTH_IS_ESTIMATE, METADATA_NAME
from slamreplay.replay.engine import views
from slamreplay.replay.engine.declared import DECLARED, DeclaredPlugin, declared_pipelines
from slamreplay.replay.engine.reader import ROBOT_NAMESPACE, Envelope, RecordingInfo, topic_type
from slamreplay.replay.errors import ReplayError
from slamreplay.replay.metric_registry import (  # noqa: F401  (MetricSpec's import path for plugins)
    MEASURED_ABS_TOLERANCE,
    MEASURED_REL_TOLERANCE,
    MetricSpec,
)


class ReplayObserver(Protocol):
    """What a pipeline may draw with: an algorithm Observer plus time and bulk series."""

    step: int
    sensor_time_ns: int

    def set_time(self, step: int, sensor_time_ns: int) -> None: ...
    def log(self, path: str, item: Observation) -> None: ...
    def log_static(self, path: str, item: Observation) -> None: ...
    def send_series(self, path: str, steps: np.ndarray, times_ns: np.ndarray, values: np.ndarray) -> None: ...


@dataclass
class ReplayContext:
    """What a pipeline gets besides its config.

    ``T_world_start`` is the ground-truth pose at the first message of the pipeline's
    ``start_topic`` (None without ground truth): the frame in which the estimate starts,
    used to draw and score estimates in the world frame, as with a known initial pose.
    """

    info: RecordingInfo
    seed: int
    rng: np.random.Generator
    observer: ReplayObserver
    T_world_start: np.ndarray | None
    start_ns: int
    log: Callable[[str], None]
    # where each config value came from (`resolve_layers`): "default", "recording", "preset NAME" or "user"
    config_sources: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def user_set(self, key: str) -> bool:
        """Whether the user gave ``key`` (``--set``/``--config``): such a value wins over what messages state."""
        return self.config_sources.get(key) == "user"


class Pipeline(ABC):
    """Base class of every pipeline; found through an entry point in group ``slamreplay.pipelines`` named ``name``."""

    name: ClassVar[str]
    summary: ClassVar[str]
    required_topics: ClassVar[tuple[str, ...]]
    optional_topics: ClassVar[tuple[str, ...]] = ()
    start_topic: ClassVar[str]
    Config: ClassVar[type]
    metrics: ClassVar[dict[str, MetricSpec]]
    # Whether the engine scores a trajectory this pipeline exports (``trajectory()``) with the trajectory
    # metrics (ape_*, rpe_*: replay.evaluate); False where it exports none (several robots, mosaic pixels).
    trajectory_metrics: ClassVar[bool] = True
    summary_skip: ClassVar[tuple[str, ...]] = views.SUMMARY_SKIP  # map entities left out of the static summary
    # Named sets of config values (`--preset NAME`). ``paper`` turns off every extra over the paper the
    # pipeline implements (each such key's help says what it adds); empty when the defaults are the paper's.
    presets: ClassVar[Mapping[str, Mapping[str, Any]]] = {"paper": {}}
    # True: the pipeline replays every robot of a multi-robot recording at once, each robot's topics read under
    # its namespace (``/robot2/odom``: `all_robots_topic_map`), all in one replay order; its topics name them so.
    multi_robot: ClassVar[bool] = False

    @classmethod
    def config_from_sensor_model(cls, model: SensorModel) -> dict[str, Any]:
        """The config values a recording's sensor model implies: by default its figures whose names are config keys."""
        keys = {f.name for f in dataclasses.fields(cls.Config)}
        return {k: v for k, v in model.values().items() if k in keys}

    def __init__(self, config: Any, ctx: ReplayContext) -> None:
        self.config = config
        self.ctx = ctx

    @abstractmethod
    def step(self, env: Envelope) -> None:
        """Process one message (the observer's time is already set to it)."""

    @abstractmethod
    def finish(self) -> dict[str, float]:
        """End of the recording: final logging, and the metrics (keys of ``metrics``; absent when not applicable)."""

    def timings(self) -> dict[str, float]:
        """Wall-clock timings of the pipeline's own (seconds), for manifest.json only; none by default."""
        return {}

    def provenance(self) -> dict[str, Any]:
        """What this replay did besides its config, for manifest.json under ``pipeline_run`` (called after
        ``finish``; none by default): an external program's command, version and determinism check."""
        return {}

    def artifacts(self) -> dict[str, bytes]:
        """Extra files for the run directory, by file name (called after ``finish``; none by default).

        Names are plain file names (``[A-Za-z0-9._-]``, not one of the run's own files); each is
        written atomically and listed with its sha256 in ``manifest.json`` under ``artifacts``.
        """
        return {}

    def trajectory(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The estimated trajectory, (t_ns (n,) int64, poses (n, 3) x y yaw in the world frame), or None.

        Written to the run as ``trajectory.tum``. By default it is read from the ``t_est`` and
        ``est`` lists that trajectory pipelines keep; a pipeline holding it elsewhere overrides this.
        """
        t_est, est = getattr(self, "t_est", None), getattr(self, "est", None)
        if t_est is None or est is None or len(t_est) != len(est):
            return None
        return np.asarray(t_est, np.int64), np.asarray(est, np.float64).reshape(-1, 3)

    @classmethod
    def blueprint(cls, bounds: views.Bounds | None = None) -> rrb.Blueprint:
        """The Rerun layout a run of this pipeline opens into (`slamreplay.replay.engine.views`): the summary first.

        ``bounds``: the world box the map views show (the run's final map), None to let Rerun fit.
        """
        return views.layout(
            views.summary_tab(bounds, ("metrics/**",), "Metrics over time"),
            views.tab("Map over time", views.map_view("Map", "world", bounds),
                      rrb.Vertical(views.series_view("Metrics", "metrics/**"), views.log_view()), columns=[3, 2]),
            views.tab("Data", views.data_view()),
        )


PIPELINE_GROUP = "slamreplay.pipelines"


def _check_pipeline(name: str, obj: Any) -> str | None:
    """What is wrong with an entry point's object as a pipeline (None: nothing)."""
    if not (isinstance(obj, type) and issubclass(obj, Pipeline)):
        return f"is not a Pipeline subclass (it is {type(obj).__name__} {getattr(obj, '__name__', obj)!r})"
    missing = sorted(getattr(obj, "__abstractmethods__", ()))
    if missing:
        return f"does not implement {', '.join(missing)}"
    declared = getattr(obj, "name", None)
    if declared != name:
        return f"is registered as {name!r} but its class says name = {declared!r}: make the two agree"
    for attr in ("summary", "required_topics", "start_topic", "Config", "metrics"):
        if not hasattr(obj, attr):
            return f"has no {attr} (docs/pipelines.md lists what a pipeline declares)"
    if not dataclasses.is_dataclass(obj.Config):
        return "has a Config that is not a dataclass"
    return None


def pipeline_plugins() -> dict[str, Plugin]:
    """Every pipeline entry point (group ``slamreplay.pipelines``), built-in or a user's, working or broken, and
    every pipeline declared in a TOML file (`declared_pipelines`: external programs)."""
    found = discover(PIPELINE_GROUP, _check_pipeline)
    declared = declared_pipelines(PIPELINE_GROUP, _check_pipeline)
    if not declared:
        return found
    for name, plugin in declared.items():
        if name in found and isinstance(plugin, DeclaredPlugin) and plugin.error is None:
            plugin.refuse(f"has the name of an installed pipeline ({found[name].origin}): rename it")
    return {**found, **declared}


def get_pipeline(name: str) -> type[Pipeline]:
    """The pipeline class called ``name``; ReplayError naming the known ones, or why a plugin is broken."""
    plugins = pipeline_plugins()
    if name not in plugins:
        if not plugins:
            raise ReplayError(missing_builtins_hint(PIPELINE_GROUP))
        raise ReplayError(f"unknown pipeline {name!r}{did_you_mean(name, plugins, quote=True)}; known pipelines: "
                          f"{', '.join(plugins)} (see `slamreplay pipelines`)") from None
    try:
        cls: type[Pipeline] = plugins[name].load()
    except RecorderError as err:
        raise ReplayError(str(err)) from None
    return cls


def pipeline_origin(name: str) -> dict[str, str]:
    """Where pipeline ``name`` comes from: its distribution, version and entry point (for run manifests)."""
    p = pipeline_plugins()[name]
    if isinstance(p, DeclaredPlugin):
        return dict(getattr(p.load(), "declared_origin", {})) or {"distribution": DECLARED, "version": "",
                                                                  "entry_point": f"{p.path}:{name}"}
    return {"distribution": p.distribution, "version": p.version, "entry_point": p.value}


def all_pipelines() -> dict[str, type[Pipeline]]:
    """The pipelines that load, by name (a broken plugin is left out: `slamreplay pipelines` reports it)."""
    return {name: p.load() for name, p in pipeline_plugins().items() if p.error is None}


def pipelines_fitting(message_counts: Mapping[str, int]) -> list[str]:
    """The pipelines whose required topics a recording has, with messages (``message_counts``: logical topic ->
    count): what an error about a missing topic offers instead."""
    return [name for name, cls in all_pipelines().items()
            if all(message_counts.get(t, 0) > 0 for t in cls.required_topics)]


# ---------------------------------------------------------------------------------------
# Configuration


def config_schema(config_cls: type) -> list[dict[str, Any]]:
    """Keys, types, defaults and help of a config dataclass (for `slamreplay pipelines`)."""
    hints = typing.get_type_hints(config_cls)
    rows = []
    for f in dataclasses.fields(config_cls):
        default = f.default if f.default is not dataclasses.MISSING else None
        rows.append({"key": f.name, "type": type_name(hints[f.name]), "default": default,
                     "help": f.metadata.get("help", "")})
    return rows


def _parse(key: str, tp: Any, value: Any) -> Any:
    """Convert a CLI string or JSON value to the field's type (:func:`slamreplay.recorder.options.parse_value`)."""
    try:
        return parse_value(tp, value)
    except ValueError as err:
        raise ReplayError(f"config key {key!r} {err}") from None


def parse_assignments(items: list[str]) -> dict[str, str]:
    """``["a=1", "b=x"]`` -> ``{"a": "1", "b": "x"}``; ReplayError for an item without ``=``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ReplayError(f"--set expects key=value, got {item!r}")
        out[key.strip()] = value.strip()
    return out


def parse_values(pipeline: type[Pipeline], values: Mapping[str, Any] | None) -> dict[str, Any]:
    """``values`` converted to the types of the pipeline's config keys; ReplayError naming a bad key."""
    config_cls = pipeline.Config
    hints = typing.get_type_hints(config_cls)
    known = {f.name for f in dataclasses.fields(config_cls)}
    kwargs = {}
    for key, value in (values or {}).items():
        if key not in known:
            raise ReplayError(f"unknown config key {key!r} for pipeline {pipeline.name}"
                              f"{did_you_mean(key, known, quote=True)}; its keys are: "
                              f"{', '.join(sorted(known)) or '(none)'} (see `slamreplay pipelines {pipeline.name}`)")
        kwargs[key] = _parse(key, hints[key], value)
    return kwargs


def resolve_config(pipeline: type[Pipeline], values: Mapping[str, Any] | None = None) -> Any:
    """Build the pipeline's config from defaults and ``values``; ReplayError naming a bad key."""
    kwargs = parse_values(pipeline, values)
    try:
        return pipeline.Config(**kwargs)
    except ValueError as err:
        raise ReplayError(f"invalid config for pipeline {pipeline.name}: {err}") from err


def recording_sensor_model(info: RecordingInfo, robot: str | None = None) -> SensorModel | None:
    """The sensor model a recording carries for its one robot or for ``robot`` of several (None when it
    carries none); ReplayError when it is damaged."""
    try:
        return SensorModel.from_record(info.metadata.get(METADATA_NAME, {}), "" if robot is None else f"/robot{robot}")
    except RecorderError as err:
        raise ReplayError(str(err)) from err


def ground_truth_is_estimate(info: RecordingInfo) -> bool:
    """Whether the recording says its /ground_truth topics hold an estimate from its own measurements (a batch
    optimum), not the truth (``recorder.writer.GROUND_TRUTH_IS_ESTIMATE``); False when it does not say, or its
    source record cannot be read."""
    text = info.metadata.get(METADATA_NAME, {}).get("source", "")
    if not text or json_depth(text) > MAX_JSON_DEPTH:
        return False
    try:
        source = json.loads(text)
    except ValueError:
        return False
    return isinstance(source, dict) and source.get(GROUND_TRUTH_IS_ESTIMATE) is True


def robots_in(info: RecordingInfo) -> list[str]:
    """The robots of a multi-robot recording: N of each topic namespace ``/robotN/`` (``record mrclam --robot all``)."""
    found = {t.file_topic.split("/")[1][len("robot"):] for t in info.topics
             if t.file_topic.startswith("/robot") and t.file_topic.count("/") >= 2}
    return sorted(r for r in found if r)


def robot_topic_map(info: RecordingInfo, robot: str) -> dict[str, str]:
    """Topic map replaying robot ``robot`` of a multi-robot recording: ``/robotN/odom`` read as ``/odom`` ..."""
    robots = robots_in(info)
    if robot not in robots:
        have = f"its robots: {', '.join(robots)}" if robots else "it holds one robot's topics: drop --robot"
        raise ReplayError(f"{info.path.name} has no robot {robot!r} (no topics under /robot{robot}/); {have}")
    prefix = f"/robot{robot}"
    return {t.file_topic: t.file_topic[len(prefix):] for t in info.topics if t.file_topic.startswith(prefix + "/")}


def all_robots_topic_map(info: RecordingInfo) -> dict[str, str]:
    """Topic map replaying every robot of a multi-robot recording at once: each robot's topics read under its
    namespace (``/robot2/odom`` as ``/robot2/odom``, a robot's odometry); ReplayError when there is no robot."""
    if not robots_in(info):
        raise ReplayError(f"{info.path.name} holds no multi-robot topics (none under /robotN/); record one with "
                          f"e.g. `slamreplay record mrclam DATASET --robot all`")
    return {t.file_topic: t.file_topic for t in info.topics
            if ROBOT_NAMESPACE.match(t.file_topic) and topic_type(t.file_topic) is not None}


@dataclass(frozen=True, slots=True)
class ResolvedConfig:
    """A pipeline's config and where each value came from (``sources``: key -> origin)."""

    config: Any
    sources: dict[str, str]
    preset: str | None = None


def resolve_layers(pipeline: type[Pipeline], user: Mapping[str, Any] | None = None, *,
                   sensor_model: SensorModel | None = None, preset: str | None = None) -> ResolvedConfig:
    """Build a pipeline's config from its layers, the first that gives a key winning:

    1. ``user``: what the user set (``--config`` file, then ``--set``);
    2. ``preset``: a named set of the pipeline's (``Pipeline.presets``, e.g. ``paper``);
    3. ``sensor_model``: what the recording says of its sensors (``Pipeline.config_from_sensor_model``);
    4. the pipeline's defaults.

    ReplayError for an unknown preset, an unknown key or a bad value (naming the layer it came from).
    """
    sources = {f.name: "default" for f in dataclasses.fields(pipeline.Config)}
    values: dict[str, Any] = {}
    if sensor_model is not None:
        from_model = pipeline.config_from_sensor_model(sensor_model)
        values.update(from_model)
        sources.update(dict.fromkeys(from_model, "recording"))
    if preset is not None:
        if preset not in pipeline.presets:
            raise ReplayError(f"pipeline {pipeline.name} has no preset {preset!r}"
                              f"{did_you_mean(preset, pipeline.presets, quote=True)}; its presets: "
                              f"{', '.join(sorted(pipeline.presets)) or '(none)'} (see `slamreplay pipelines`)")
        values.update(pipeline.presets[preset])
        sources.update(dict.fromkeys(pipeline.presets[preset], f"preset {preset}"))
    values.update(parse_values(pipeline, user))  # the user's keys checked alone first: an error names them
    sources.update(dict.fromkeys(user or {}, "user"))
    return ResolvedConfig(resolve_config(pipeline, values), sources, preset)


def config_dict(config: Any) -> dict[str, Any]:
    return dataclasses.asdict(config)


def config_hash(config: Any) -> str:
    """sha256 of the canonical JSON of a resolved config."""
    return hashlib.sha256(json.dumps(config_dict(config), sort_keys=True).encode()).hexdigest()
