"""The replay configuration: pydantic models mirroring the frontends' frozen dataclasses, and its TOML file.

    [input]                 scan_topic, odom_topic, repair_information
    [optimizer]             method, iterations
    [matching] [odometry] [keyframes] [loop_closure]    the fields of `frontends.slam2d.config`

The frontend sections are built from the dataclasses' fields (same section and key names, same defaults),
so a setting added there appears here without touching this module. Units are the dataclasses' except
angles: an angle field (its name mentions an angle, see `is_angle_field`) is in degrees here and in the
file, and converted to radians by `ReplayConfig.to_slam2d()`.

Every key is optional; unknown keys and bad values are errors naming the file, line and key
(`ConfigError`). Numbers must be finite and positive unless listed in `_BOUNDS`.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
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

from frontends.slam2d import Slam2DConfig
from optimizer.file_input import read_bytes_bounded
from optimizer.robust import KERNELS
from optimizer.solve import (
    DEFAULT_ITERATIONS,
    DEFAULT_METHOD,
    DEFAULT_POLISH_ITERATIONS,
    MAX_ITERATIONS,
    METHODS,
)
from pipeline.errors import PipelineError

__all__ = [
    "SLAM2D_SECTIONS",
    "ConfigError",
    "InputSection",
    "OptimizerSection",
    "ReplayConfig",
    "default_config_toml",
    "is_angle_field",
    "load_config",
]

_ANGLE_NAME = re.compile(r"angle|angular|turn_rate")
_DEGREE_DIGITS = 9
"""Degrees converted from the dataclasses' radians are rounded to this many decimals, so that the default
6° is written as 6.0 rather than 5.999999999999999 (and converts back to the very same radians)."""


class ConfigError(PipelineError):
    """A configuration file (or mapping) that cannot be used. `str()` is ``"path:line: key: message"``, the
    parts that are known."""

    def __init__(self, path: str | Path | None, message: str, *, line: int | None = None,
                 key: str | None = None) -> None:
        self.path = None if path is None else Path(path)
        self.line = line
        self.key = key
        self.reason = message
        where = "configuration" if self.path is None else str(self.path)
        if line is not None:
            where += f":{line}"
        super().__init__(f"{where}: {key}: {message}" if key else f"{where}: {message}")


def is_angle_field(name: str) -> bool:
    """Whether a frontend setting is an angle (or an angular rate): degrees in the file, radians inside."""
    return _ANGLE_NAME.search(name) is not None


# ------------------------------------------------------------------------------------------ the sections

_POSITIVE: dict[str, float] = {"gt": 0}
_NON_NEGATIVE: dict[str, float] = {"ge": 0}
_FRACTION: dict[str, float] = {"ge": 0, "le": 1}
_POSITIVE_FRACTION: dict[str, float] = {"gt": 0, "le": 1}

_BOUNDS: dict[tuple[str, str], dict[str, float]] = {
    # zero is meaningful: no growth with distance / turn, no tolerance, no context around a match
    ("odometry", "odometry_sigma_per_metre"): _NON_NEGATIVE,
    ("odometry", "odometry_sigma_per_radian"): _NON_NEGATIVE,
    ("odometry", "min_inlier_fraction"): _FRACTION,
    ("loop_closure", "search_radius_per_metre"): _NON_NEGATIVE,
    ("loop_closure", "submap_keyframes"): _NON_NEGATIVE,
    ("loop_closure", "query_keyframes"): _NON_NEGATIVE,
    ("loop_closure", "small_correction_linear"): _NON_NEGATIVE,
    ("loop_closure", "small_correction_angular"): _NON_NEGATIVE,
    ("loop_closure", "min_score"): _FRACTION,
    ("loop_closure", "ambiguity_ratio"): _POSITIVE_FRACTION,
    ("loop_closure", "min_inlier_fraction"): _FRACTION,
}
"""Bounds of the numbers that need not be strictly positive (every other number must be)."""

_FLOORS: dict[tuple[str, str], float] = {
    ("matching", "resolution"): 0.005,
    ("loop_closure", "query_thinning"): 0.005,
    ("odometry", "angular_step"): 0.01,
    ("loop_closure", "angular_step"): 0.01,
}
"""Steps and cells finer than these (m, degrees) multiply the work and memory of a search or a grid far
beyond any use."""

_CEILINGS: dict[tuple[str, str], float] = {
    ("matching", "max_range"): 1000.0,
    ("keyframes", "max_turn_rate"): 3600.0,
}
_MAX_NUMBER = 10_000.0
"""Every other number's upper bound (metres, counts, scales): far above any use, and low enough that no
value in range can overflow a computation or size an allocation beyond the memory bound."""
_MAX_ANGLE = 360.0
"""Upper bound of an angle (degrees)."""


def _bounds(section: str, name: str) -> dict[str, float]:
    bounds = dict(_BOUNDS.get((section, name), _POSITIVE))
    if (section, name) in _FLOORS:
        bounds.pop("gt", None)
        bounds["ge"] = _FLOORS[section, name]
    ceiling = _CEILINGS.get((section, name), _MAX_ANGLE if is_angle_field(name) else _MAX_NUMBER)
    bounds["le"] = min(bounds.get("le", ceiling), ceiling)
    return bounds

_AT_LEAST: dict[tuple[str, str], str] = {
    ("loop_closure", "max_search_radius"): "search_radius",
}
"""A key that must be at least another key of its section; left out, it defaults to the larger of its
dataclass default and that key (so raising `search_radius` alone is never an error)."""

_AT_MOST: dict[tuple[str, str], str] = {
    ("odometry", "angular_step"): "window_angular",
    ("loop_closure", "angular_step"): "angular_window",
}
"""A search step must not exceed the window it steps through."""

_MODEL_CONFIG = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)
"""Strict: a string or boolean is not a number and a number is not a boolean (an int is a fine float)."""


class _Section(BaseModel):
    model_config = _MODEL_CONFIG


def _section_model(section: str, dataclass_type: type) -> type[_Section]:
    """A frozen pydantic model with the dataclass's fields (angles in degrees) and their bounds."""
    hints = typing.get_type_hints(dataclass_type)
    defaults = dataclass_type()
    fields: dict[str, Any] = {}
    for item in dataclasses.fields(dataclass_type):
        annotation = hints[item.name]
        default = getattr(defaults, item.name)
        if annotation is bool:
            fields[item.name] = (bool, default)
            continue
        if annotation not in (int, float):
            raise TypeError(f"{dataclass_type.__name__}.{item.name}: no TOML form for {annotation!r}")
        if annotation is float and is_angle_field(item.name):
            default = round(math.degrees(default), _DEGREE_DIGITS)
        fields[item.name] = (annotation, Field(default, **_bounds(section, item.name)))

    validators: dict[str, Any] = {}
    for (rule_section, key), other in _AT_LEAST.items():
        if rule_section == section:
            validators[f"_at_least_{key}"] = field_validator(key)(_order_check(other, at_least=True))
    for (rule_section, key), other in _AT_MOST.items():
        if rule_section == section:
            validators[f"_at_most_{key}"] = field_validator(key)(_order_check(other, at_least=False))
    derived = {key: (other, getattr(defaults, key)) for (s, key), other in _AT_LEAST.items() if s == section}
    if derived:
        validators["_derived_defaults"] = model_validator(mode="before")(_derive_at_least(derived))

    name = dataclass_type.__name__.removesuffix("Config") + "Section"
    model = create_model(name, __base__=_Section, __module__=__name__, __validators__=validators, **fields)
    model.__doc__ = f"The [{section}] section: `{dataclass_type.__module__}.{dataclass_type.__name__}`."
    return model


def _order_check(other: str, *, at_least: bool) -> Callable[[type, float, ValidationInfo], float]:
    def check(cls: type, value: float, info: ValidationInfo) -> float:
        bound = info.data.get(other)  # absent when it failed its own validation: reported there
        if bound is not None and (value < bound if at_least else value > bound):
            relation = "at least" if at_least else "at most"
            raise ValueError(f"must be {relation} {other} ({bound:g})")
        return value

    return check


def _derive_at_least(derived: dict[str, tuple[str, float]]) -> Callable[[type, Any], Any]:
    def derive(cls: type, data: Any) -> Any:
        if not isinstance(data, Mapping):
            return data
        data = dict(data)
        for key, (other, default) in derived.items():
            bound = data.get(other)
            if key not in data and isinstance(bound, int | float) and not isinstance(bound, bool):
                data[key] = max(default, bound)
        return data

    return derive


SLAM2D_SECTIONS: dict[str, type[_Section]] = {}
"""Section name → model, one per field of `Slam2DConfig`, in its order."""
for _field in dataclasses.fields(Slam2DConfig):
    _model = _section_model(_field.name, typing.get_type_hints(Slam2DConfig)[_field.name])
    SLAM2D_SECTIONS[_field.name] = _model
    globals()[_model.__name__] = _model  # importable by name, so that configurations pickle
del _field, _model

_METHOD_CHOICE = Literal[METHODS]  # type: ignore[valid-type]


class OptimizerSection(_Section):
    """The [optimizer] section. `iterations`: SGD (or Gauss–Seidel) iterations; with method "gn", the cap on
    Gauss–Newton iterations. Left out, it is 100, or the polish cap (5000) for "gn"."""

    method: _METHOD_CHOICE = DEFAULT_METHOD  # type: ignore[valid-type]
    iterations: int = Field(DEFAULT_ITERATIONS, ge=0, le=MAX_ITERATIONS)
    robust: Literal["none", *KERNELS] = "none"  # type: ignore[valid-type]
    """A robust kernel against false loop closures: "cauchy" or "dcs" (methods sgd+gn and sgd)."""

    @property
    def robust_kernel(self) -> str | None:
        return None if self.robust == "none" else self.robust

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
    odom_topic: str | None = Field(None, min_length=1)
    repair_information: bool = False


_Slam2DSections: type[_Section] = create_model(  # type: ignore[call-overload]
    "_Slam2DSections",
    __base__=_Section,
    __module__=__name__,
    **{name: (model, Field(default_factory=model)) for name, model in SLAM2D_SECTIONS.items()},
)


class ReplayConfig(_Slam2DSections):  # type: ignore[misc, valid-type]
    """Everything a replay can be told: `ReplayConfig(optimizer={"method": "sgd"})`, or `load_config(path)`.

    Frozen; `model_copy(update=...)` does not validate, so build a changed one with `with_updates`.
    """

    optimizer: OptimizerSection = Field(default_factory=OptimizerSection)
    input: InputSection = Field(default_factory=InputSection)

    def to_slam2d(self) -> Slam2DConfig:
        """The frontend's frozen dataclass (angles in radians)."""
        sections: dict[str, Any] = {}
        hints = typing.get_type_hints(Slam2DConfig)
        for name in SLAM2D_SECTIONS:
            values = getattr(self, name).model_dump()
            for key, value in values.items():
                if isinstance(value, float) and is_angle_field(key):
                    values[key] = math.radians(value)
            sections[name] = hints[name](**values)
        return Slam2DConfig(**sections)

    def with_updates(self, updates: Mapping[str, Mapping[str, Any]]) -> ReplayConfig:
        """A validated copy with some keys replaced, e.g. `{"optimizer": {"method": "gn"}}`."""
        return config_from_mapping(_merge(self.to_mapping(), updates))

    def to_mapping(self) -> dict[str, dict[str, Any]]:
        """Section → key → value as in the file (degrees), sections in file order, unset topics left out."""
        order = ["input", "optimizer", *SLAM2D_SECTIONS]
        return {name: getattr(self, name).model_dump(exclude_none=True) for name in order}

    def to_toml(self) -> str:
        """This configuration as a TOML document that `load_config` reads back to an equal one."""
        parts = [_TOML_HEADER]
        for name, values in self.to_mapping().items():
            text = tomli_w.dumps({name: values})
            comments = _SECTION_COMMENTS.get(name)
            if comments:
                header, _, body = text.partition("\n")
                text = f"{header}\n{comments}{body}"
            parts.append(text)
        return "\n".join(parts)


_TOML_HEADER = """\
# sgdslam replay configuration: replay LOG --config FILE (command-line options override it).
# Every key is optional; left out, it takes the default written here. Lengths in metres, times in
# seconds, angles in degrees (angular rates in degrees per second).
"""

_SECTION_COMMENTS = {
    "input": '# scan_topic = "/scan"    # default: the log\'s only LaserScan topic\n'
             '# odom_topic = "/odom"    # default: the log\'s only odometry topic, if any\n',
    "optimizer": f"# method: one of {', '.join(METHODS)}\n"
                 f"# iterations: SGD (or Gauss-Seidel) iterations; with gn, the Gauss-Newton cap "
                 f"(left out: {DEFAULT_POLISH_ITERATIONS})\n"
                 f"# robust: none, {' or '.join(KERNELS)}: a robust kernel against false loop closures\n",
}


def default_config_toml() -> str:
    """The defaults as TOML (what `replay --dump-config` prints)."""
    return ReplayConfig().to_toml()


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
    found = re.search(r"\s*\(at line (\d+), column \d+\)$", message)
    if found is None:
        return message, None
    return message[: found.start()], int(found.group(1))


def _config_error(error: ValidationError, path: str | Path | None, text: str | None) -> ConfigError:
    first = error.errors()[0]
    loc = tuple(str(part) for part in first["loc"])
    line = _line_of(text, loc) if text is not None else None
    key = ".".join(loc) if loc else None
    if first["type"] == "extra_forbidden":
        message = _unknown_key_message(loc)
    else:
        message = first["msg"][:1].lower() + first["msg"][1:]
        message = message.removeprefix("value error, ")
        if first["type"] != "missing":
            message += f", got {first['input']!r}"
    more = error.error_count() - 1
    if more:
        message += f" (and {more} more error{'s' if more > 1 else ''})"
    return ConfigError(path, message, line=line, key=key)


def _unknown_key_message(loc: tuple[str, ...]) -> str:
    if len(loc) == 1:
        known = list(ReplayConfig.model_fields)
        what = "unknown section"
    else:
        model = _section_models().get(loc[0])
        known = list(model.model_fields) if model is not None else []
        what = f"unknown key in [{loc[0]}]"
    close = difflib.get_close_matches(loc[-1], known, n=1)
    return what + (f"; did you mean {close[0]}?" if close else f"; known: {', '.join(known)}")


def _section_models() -> dict[str, type[BaseModel]]:
    return {name: field.annotation for name, field in ReplayConfig.model_fields.items()}  # type: ignore[misc]


_TABLE = re.compile(r"^\s*\[\s*([A-Za-z0-9_.\- ]+?)\s*\]\s*(#.*)?$")
_KEY = re.compile(r"^\s*([A-Za-z0-9_.\-]+)\s*=")


def _line_of(text: str, loc: tuple[str, ...]) -> int | None:
    """The 1-based line of `[section]` or of `key = …` under it (or `section.key = …` before any table)."""
    if not loc:
        return None
    section, key = loc[0], (loc[1] if len(loc) > 1 else None)
    table = ""
    for number, line in enumerate(text.splitlines(), start=1):
        header = _TABLE.match(line)
        if header:
            table = header.group(1).replace(" ", "")
            if key is None and table == section:
                return number
            continue
        assignment = _KEY.match(line)
        if assignment is None:
            continue
        name = assignment.group(1)
        at_key = (table == section and name == key) or (not table and name == f"{section}.{key}")
        if key is not None and at_key:
            return number
        if key is None and not table and name.split(".")[0] == section:
            return number
    return None
