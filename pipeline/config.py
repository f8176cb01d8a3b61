"""The replay configuration: pydantic models mirroring the frontends' frozen dataclasses, and its TOML file.

    [input]                 scan_topic, odom_topic, base_frame, repair_information
    [optimizer]             method, iterations, robust
    [slam2d.matching] [slam2d.odometry] [slam2d.keyframes] [slam2d.loop_closure]
                            the fields of `frontends.slam2d.Slam2DConfig` (logs of laser scans)
    [slam3d.odometry] [slam3d.keyframes] [slam3d.loop_closure]
                            the fields of `frontends.slam3d.Slam3DConfig` (logs of point clouds)

The frontend sections are built from the dataclasses' fields (same section and key names, same defaults),
so a setting added there appears here without touching this module. Units are the dataclasses' except
angles: an angle field (its name mentions an angle, see `is_angle_field`) is in degrees here and in the
file, and converted to radians by `ReplayConfig.to_slam2d()` / `to_slam3d()`. A setting whose default is
"none" (e.g. `slam3d.odometry.voxel_size`) is left out of the file to keep it.

Every key is optional; unknown keys and bad values are errors naming the file, line and key
(`ConfigError`). Numbers must be finite and positive unless listed in `_BOUNDS`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import operator
import re
import tomllib
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import tomli_w
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    create_model,
    field_validator,
    model_validator,
)

from frontends.slam2d import RETIRED_SETTINGS as SLAM2D_RETIRED_SETTINGS
from frontends.slam2d import Slam2DConfig
from frontends.slam3d import Slam3DConfig
from optimizer.file_input import read_bytes_bounded
from optimizer.robust import KERNELS
from optimizer.solve import (
    DEFAULT_ITERATIONS,
    DEFAULT_METHOD,
    DEFAULT_POLISH_ITERATIONS,
    LARGEST_FOR_EXTRA_STAGES,
    MAX_ITERATIONS,
    METHODS,
    ROBUST_METHODS,
)
from pipeline.errors import PipelineError

_ANGLE_NAME = re.compile(r"angle|angular|turn_rate")
_DEGREE_DIGITS = 9
"""Degrees converted from the dataclasses' radians are rounded to this many decimals, so that the default
6° is written as 6.0 rather than 5.999999999999999 (and converts back to the very same radians)."""


class ConfigError(PipelineError):
    """A configuration file (or mapping) that cannot be used. `str()` is ``"path:line: key: message"``, the
    parts that are known."""

    def __init__(self, path: str | Path | None, message: str, *, line: int | None = None,
                 key: str | None = None) -> None:
        self.line = line
        where = "configuration" if path is None else str(path)
        if line is not None:
            where += f":{line}"
        super().__init__(f"{where}: {key}: {message}" if key else f"{where}: {message}")


def is_angle_field(name: str) -> bool:
    """Whether a frontend setting is an angle (or an angular rate): degrees in the file, radians inside."""
    return _ANGLE_NAME.search(name) is not None


# ------------------------------------------------------------------------------------------ the sections

_NON_NEGATIVE: dict[str, float] = {"ge": 0}
"""Zero is meaningful: no growth with distance / turn, no tolerance, no context around a match."""
_FRACTION: dict[str, float] = {"ge": 0, "le": 1}
_POSITIVE_FRACTION: dict[str, float] = {"gt": 0, "le": 1}
_STEP_FLOOR: dict[str, float] = {"ge": 0.01}
"""Steps and cells finer than this (m, degrees) multiply the work and memory of a search or a grid far
beyond any use."""
_RANGE_CEILING: dict[str, float] = {"gt": 0, "le": 1000}

_BOUNDS: dict[str, dict[str, dict[str, float]]] = {
    "slam2d.matching": {"resolution": {"ge": 0.005}, "max_range": _RANGE_CEILING,
                        "min_match_interval": {"ge": 0, "le": 1}},
    "slam2d.odometry": {"odometry_sigma_per_metre": _NON_NEGATIVE, "odometry_sigma_per_radian": _NON_NEGATIVE,
                        "min_inlier_fraction": _FRACTION, "angular_step": _STEP_FLOOR},
    "slam2d.keyframes": {"max_turn_rate": {"gt": 0, "le": 3600}},
    "slam2d.loop_closure": {"search_radius_per_metre": _NON_NEGATIVE, "submap_keyframes": _NON_NEGATIVE,
                            "travel_between_closures": _NON_NEGATIVE,
                            "min_score": _FRACTION, "ambiguity_ratio": _POSITIVE_FRACTION,
                            "min_inlier_fraction": _FRACTION, "angular_step": _STEP_FLOOR},
    "slam3d.odometry": {"min_range": {"ge": 0, "le": 1000}, "max_range": _RANGE_CEILING,
                        "max_threads": _NON_NEGATIVE,  # 0: all cores
                        "sweep_start_angle": _NON_NEGATIVE, "voxel_size": _STEP_FLOOR},
    "slam3d.keyframes": {"odometry_sigma_per_metre": _NON_NEGATIVE, "cloud_voxel": _STEP_FLOOR,
                         "odometry_sigma_per_radian": _NON_NEGATIVE,
                         "odometry_sigma_per_metre_angular": _NON_NEGATIVE},
    "slam3d.loop_closure": {"min_travel": _NON_NEGATIVE, "travel_between_closures": _NON_NEGATIVE,
                            "search_radius_per_metre": _NON_NEGATIVE,
                            "submap_keyframes": _NON_NEGATIVE, "small_correction_linear": _NON_NEGATIVE,
                            "small_correction_angular": _NON_NEGATIVE, "min_inlier_fraction": _FRACTION,
                            "ambiguity_ratio": _POSITIVE_FRACTION, "registration_voxel": _STEP_FLOOR,
                            "threads": _NON_NEGATIVE},  # 0: all cores
    "slam3d.se3_polish": {"max_iterations": {"gt": 0, "le": 1000}},
}
"""Section → key → bounds of the numbers that differ from the rule: greater than 0, at most `_MAX_ANGLE`
for an angle, else `_MAX_NUMBER`."""
_MAX_NUMBER = 10_000.0
"""Every other number's upper bound (metres, counts, scales): far above any use, and low enough that no
value in range can overflow a computation or size an allocation beyond the memory bound."""
_MAX_ANGLE = 360.0
"""Upper bound of an angle (degrees)."""


def _bounds(section: str, name: str) -> dict[str, Any]:
    ceiling = _MAX_ANGLE if is_angle_field(name) else _MAX_NUMBER
    return {"le": ceiling, **_BOUNDS.get(section, {}).get(name, {"gt": 0})}


_AT_LEAST: dict[tuple[str, str], str] = {
    ("slam2d.loop_closure", "max_search_radius"): "search_radius",
    ("slam3d.loop_closure", "max_search_radius"): "search_radius",
}
"""A key that must be at least another key of its section; left out, it defaults to the larger of its
dataclass default and that key (so raising `search_radius` alone is never an error)."""

_AT_MOST: dict[tuple[str, str], str] = {
    ("slam2d.odometry", "angular_step"): "window_angular",
    ("slam2d.loop_closure", "angular_step"): "angular_window",
}
"""A search step must not exceed the window it steps through."""

_BELOW: dict[tuple[str, str], str] = {
    ("slam3d.odometry", "min_range"): "max_range",
}
"""A key that must be less than another of its section (declared before it): a range that keeps nothing."""

_ORDERS: tuple[tuple[dict[tuple[str, str], str], str, Callable[[float, float], bool]], ...] = (
    (_AT_LEAST, "at least", operator.ge),
    (_AT_MOST, "at most", operator.le),
    (_BELOW, "less than", operator.lt),
)
"""Each table of keys in order, the relation in words (for the error), and its test."""


class _Section(BaseModel):
    # Strict: a string or boolean is not a number and a number is not a boolean (an int is a fine float).
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _section_model(section: str, dataclass_type: type) -> type[_Section]:
    """A frozen pydantic model with the dataclass's fields (angles in degrees) and their bounds."""
    hints = typing.get_type_hints(dataclass_type)
    defaults = dataclass_type()
    fields: dict[str, Any] = {}
    for item in dataclasses.fields(dataclass_type):
        annotation = hints[item.name]
        default = getattr(defaults, item.name)
        if annotation not in (bool, int, float, float | None):
            raise TypeError(f"{dataclass_type.__name__}.{item.name}: no TOML form for {annotation!r}")
        if default is not None and annotation in (float, float | None) and is_angle_field(item.name):
            default = round(math.degrees(default), _DEGREE_DIGITS)
        bounds = {} if annotation is bool else _bounds(section, item.name)
        fields[item.name] = (annotation, Field(default, **bounds))

    validators: dict[str, Any] = {}
    for rules, relation, holds in _ORDERS:
        for (rule_section, key), other in rules.items():
            if rule_section == section:
                validators[f"_{key}_against_{other}"] = _order_check(key, other, relation, holds)
    derived = {key: (other, getattr(defaults, key)) for (s, key), other in _AT_LEAST.items() if s == section}
    if derived:
        validators["_derived_defaults"] = model_validator(mode="before")(_derive_at_least(derived))

    name = section.title().replace(".", "").replace("_", "") + "Section"
    model = create_model(name, __base__=_Section, __module__=__name__, __validators__=validators, **fields)
    model.__doc__ = f"The [{section}] section: `{dataclass_type.__module__}.{dataclass_type.__name__}`."
    return model


def _order_check(key: str, other: str, relation: str, holds: Callable[[float, float], bool]) -> Any:
    """A validator of `key`: in `relation` to `other` (`holds` tells), when that passed its own validation."""
    def check(cls: type, value: float, info: ValidationInfo) -> float:
        bound = info.data.get(other)  # absent when it failed its own validation: reported there
        if bound is not None and not holds(value, bound):
            raise ValueError(f"must be {relation} {other} ({bound:g})")
        return value

    return field_validator(key)(check)


def _derive_at_least(derived: dict[str, tuple[str, float]]) -> Callable[[type, Any], Any]:
    def derive(cls: type, data: Any) -> Any:
        if isinstance(data, Mapping):
            data = dict(data)
            for key, (other, default) in derived.items():
                bound = data.get(other)
                if key not in data and isinstance(bound, int | float) and not isinstance(bound, bool):
                    data[key] = max(default, bound)
        return data

    return derive


def _frontend_sections(name: str, config_type: type) -> tuple[dict[str, type[_Section]], type[_Section]]:
    """One section model per field of a frontend's config dataclass (`[name.field]`), and the model of
    `[name]` holding them."""
    hints = typing.get_type_hints(config_type)
    sections: dict[str, type[_Section]] = {}
    for item in dataclasses.fields(config_type):
        model = _section_model(f"{name}.{item.name}", hints[item.name])
        sections[item.name] = model
        globals()[model.__name__] = model  # importable by name, so that configurations pickle
    holder = create_model(  # type: ignore[call-overload]
        f"{name.title()}Sections", __base__=_Section, __module__=__name__,
        **{key: (model, Field(default_factory=model)) for key, model in sections.items()},
    )
    holder.__doc__ = f"The [{name}.*] sections: `{config_type.__module__}.{config_type.__name__}`."
    globals()[holder.__name__] = holder
    return sections, holder


SLAM2D_SECTIONS, Slam2DSections = _frontend_sections("slam2d", Slam2DConfig)
"""Section name → model, one per field of `Slam2DConfig`, in its order."""
SLAM3D_SECTIONS, Slam3DSections = _frontend_sections("slam3d", Slam3DConfig)
"""Section name → model, one per field of `Slam3DConfig`, in its order."""


def _to_dataclass(sections: _Section, config_type: type) -> Any:
    """A frontend's frozen config dataclass from its sections (angles back to radians)."""
    hints = typing.get_type_hints(config_type)
    values: dict[str, Any] = {}
    for name, section in sections:
        fields = {key: math.radians(value) if isinstance(value, float) and is_angle_field(key) else value
                  for key, value in section.model_dump().items()}
        values[name] = hints[name](**fields)
    return config_type(**values)


class OptimizerSection(_Section):
    """The [optimizer] section. `iterations`: SGD (or Gauss–Seidel) iterations; with method "gn", the cap on
    Gauss–Newton iterations. Left out (None), the optimizer's default: 100 iterations, except that on a
    graph of more than 200 000 poses the default method's SGD hands over to the polish once it stalls
    (`optimizer.solve.until_stalled`, at most 100), and the polish cap (5000) for "gn"."""

    method: Literal[METHODS] = DEFAULT_METHOD  # type: ignore[valid-type]
    iterations: int | None = Field(None, ge=0, le=MAX_ITERATIONS)
    robust: Literal["none", *KERNELS] = "none"  # type: ignore[valid-type]
    """A robust kernel against false loop closures: "cauchy" or "dcs" (methods sgd+gn and sgd)."""

    @property
    def robust_kernel(self) -> str | None:
        return None if self.robust == "none" else self.robust

    @model_validator(mode="after")
    def _robust_with_its_methods(self) -> OptimizerSection:
        # Here, not only in the optimizer: a log whose graph has no loop closure is never optimized, and
        # whether a setting is refused must not depend on what the data turns out to hold.
        if self.robust != "none" and self.method not in ROBUST_METHODS:
            raise ValueError(f"robust = {self.robust!r} works with the methods {', '.join(ROBUST_METHODS)}, "
                             f"not {self.method!r}")
        return self

    @model_validator(mode="before")
    @classmethod
    def _derive_iterations(cls, data: Any) -> Any:
        if isinstance(data, Mapping) and "iterations" not in data and data.get("method") == "gn":
            return {**data, "iterations": DEFAULT_POLISH_ITERATIONS}
        return data


class InputSection(_Section):
    """The [input] section. Topics left out are found by message type (an error lists the candidates when
    a log has several); `repair_information` applies to pose-graph files."""

    scan_topic: str | None = Field(None, min_length=1)
    """The sensor topic: laser scans or point clouds."""
    odom_topic: str | None = Field(None, min_length=1)
    base_frame: str | None = Field(None, min_length=1)
    """The vehicle frame poses are of; left out: the frame tf mounts the sensor on, else base_link."""
    repair_information: bool = False


class ReplayConfig(_Section):
    """Everything a replay can be told: `ReplayConfig(optimizer={"method": "sgd"})`, or `load_config(path)`.
    Frozen; `model_copy(update=...)` does not validate: build a changed one with `config_from_mapping`."""

    input: InputSection = Field(default_factory=InputSection)
    optimizer: OptimizerSection = Field(default_factory=OptimizerSection)
    slam2d: Slam2DSections = Field(default_factory=Slam2DSections)  # type: ignore[valid-type]
    slam3d: Slam3DSections = Field(default_factory=Slam3DSections)  # type: ignore[valid-type]

    def to_slam2d(self) -> Slam2DConfig:
        """The 2D frontend's frozen dataclass (angles in radians)."""
        return _to_dataclass(self.slam2d, Slam2DConfig)

    def to_slam3d(self) -> Slam3DConfig:
        """The 3D frontend's frozen dataclass (angles in radians)."""
        return _to_dataclass(self.slam3d, Slam3DConfig)

    def to_toml(self) -> str:
        """This configuration as a TOML document that `load_config` reads back to an equal one (sections in
        file order, in its units, unset values left out)."""
        parts = [_TOML_HEADER]
        for name in type(self).model_fields:
            text = tomli_w.dumps({name: getattr(self, name).model_dump(exclude_none=True)})
            if name in ("input", "optimizer"):  # comments under the header, before the keys
                header, _, body = text.partition("\n")
                parts.append(f"{header}\n{_SECTION_COMMENTS[name]}{body}")
            else:
                parts.append(_SECTION_COMMENTS[name] + text)
        return "\n".join(parts)


_TOML_HEADER = """\
# sgdslam replay configuration: replay LOG --config FILE (command-line options override it).
# Every key is optional; left out, it takes the default written here. Lengths in metres, times in
# seconds, angles in degrees (angular rates in degrees per second).
"""

_SECTION_COMMENTS = {
    "input": '# scan_topic = "/scan"    # default: the log\'s only LaserScan or PointCloud2 topic\n'
             '# odom_topic = "/odom"    # default: the log\'s only odometry topic, if any\n'
             '# base_frame = "base_link"  # default: the frame tf mounts the sensor on, else base_link\n',
    "optimizer": f"# method: one of {', '.join(METHODS)}\n"
                 f"# iterations: SGD (or Gauss-Seidel) iterations (left out: {DEFAULT_ITERATIONS}; on "
                 f"graphs over {LARGEST_FOR_EXTRA_STAGES:_} poses\n#   a cap: the default method's SGD "
                 f"hands over to the polish once it stalls); with gn, the Gauss-Newton cap\n#   (left out: "
                 f"{DEFAULT_POLISH_ITERATIONS})\n"
                 f"# robust: none, {' or '.join(KERNELS)}: a robust kernel against false loop closures\n",
    "slam2d": "# The 2D laser SLAM (logs of LaserScan messages): frontends.slam2d.Slam2DConfig\n",
    "slam3d": "# The 3D LiDAR SLAM (logs of PointCloud2 messages): frontends.slam3d.Slam3DConfig.\n"
              "# Left out: voxel_size (max_range / 100, KISS-ICP's rule), fixed_threshold (adaptive).\n",
}


# ------------------------------------------------------------------------------------------------ loading


MAX_CONFIG_BYTES = 1 << 20
"""A settings file is a few kilobytes; anything past this is not one (e.g. /dev/zero)."""


def load_config(path: str | Path, overrides: Mapping[str, Mapping[str, Any]] | None = None) -> ReplayConfig:
    """Read a TOML configuration; `overrides` (section → key → value, e.g. from command-line options)
    replace the file's values before validation, so values derived from them follow too.

    Raises `ConfigError` naming the file, the line and the key.
    """
    path = Path(path)
    try:
        text = read_bytes_bounded(path, MAX_CONFIG_BYTES).decode("utf-8")
    except FileNotFoundError:
        raise ConfigError(path, "no such file") from None
    except (OSError, UnicodeDecodeError) as error:
        reason = error.strerror if isinstance(error, OSError) and error.strerror else str(error)
        raise ConfigError(path, f"cannot read the file: {reason}") from error
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        message, line = _decode_error_position(str(error))
        raise ConfigError(path, f"not valid TOML: {message}", line=line) from None
    return config_from_mapping(_merge(data, overrides or {}), path=path, text=text)


def config_from_mapping(data: Mapping[str, Any], *, path: str | Path | None = None,
                        text: str | None = None) -> ReplayConfig:
    """Validate a section → key → value mapping (file units); `path` and `text` name where it came from in
    the error."""
    try:
        return ReplayConfig.model_validate(data)
    except ValidationError as error:
        raise _config_error(error, path, text) from None


def _merge(base: Mapping[str, Any], updates: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    merged = dict(base)
    for section, values in updates.items():
        current = merged.get(section)
        merged[section] = {**current, **values} if isinstance(current, Mapping) else dict(values)
    return merged


def _decode_error_position(message: str) -> tuple[str, int | None]:
    # Python 3.11's TOMLDecodeError has no line attribute: the position is at the end of its message.
    found = re.fullmatch(r"(.*?)\s*\(at line (\d+), column \d+\)", message, re.DOTALL)
    return (found.group(1), int(found.group(2))) if found else (message, None)


def _config_error(error: ValidationError, path: str | Path | None, text: str | None) -> ConfigError:
    first = error.errors()[0]
    loc = tuple(str(part) for part in first["loc"])
    line = _line_of(text, loc) if text is not None and loc else None
    if first["type"] == "extra_forbidden":
        message = _unknown_key_message(loc)
    else:
        message = first["msg"][:1].lower() + first["msg"][1:]
        message = message.removeprefix("value error, ")
        if first["type"] != "missing" and not isinstance(first["input"], Mapping):  # (a whole section's)
            message += f", got {first['input']!r}"
    more = error.error_count() - 1
    if more:
        message += f" (and {more} more error{'s' if more > 1 else ''})"
    return ConfigError(path, message, line=line, key=".".join(loc))  # "": the whole configuration


def _unknown_key_message(loc: tuple[str, ...]) -> str:
    if len(loc) == 3 and loc[0] == "slam2d" and (loc[1], loc[2]) in SLAM2D_RETIRED_SETTINGS:
        fixed = SLAM2D_RETIRED_SETTINGS[loc[1], loc[2]]
        return (f"{loc[2]} is no longer a setting (fixed at {fixed}, which served every log tried); "
                "remove it from the file")
    model: Any = ReplayConfig
    for part in loc[:-1]:  # the sections holding the key: models all the way, as only a model forbids extras
        model = model.model_fields[part].annotation
    known = list(model.model_fields)
    what = "unknown section" if len(loc) == 1 else f"unknown key in [{'.'.join(loc[:-1])}]"
    close = difflib.get_close_matches(loc[-1], known, n=1)
    return what + (f"; did you mean {close[0]}?" if close else f"; known: {', '.join(known)}")


_TABLE = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\- ]+?)\s*\]\s*(#.*)?$")
_KEY = re.compile(r"^\s*([A-Za-z0-9_.\-]+)\s*=")


def _line_of(text: str, loc: tuple[str, ...]) -> int | None:
    """The 1-based line of the table `[a.b]` that `loc` names, or of `key = …` under its table (or as a
    dotted key `a.b.key = …`), or of the first table or key inside what it names."""
    whole = ".".join(loc)
    table = ""
    for number, line in enumerate(text.splitlines(), start=1):
        if header := _TABLE.match(line):
            table = name = header.group(1).replace(" ", "")
        elif assignment := _KEY.match(line):
            name = f"{table}.{assignment.group(1)}" if table else assignment.group(1)
        else:
            continue
        if name == whole or name.startswith(whole + "."):
            return number
    return None
