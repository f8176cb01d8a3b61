"""Property-based fuzzing of the config loader: whatever the file holds, `load_config` returns a
configuration or raises our `ConfigError` with one line naming the file; nothing else escapes."""

from __future__ import annotations

import tempfile
from pathlib import Path

import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.config import ConfigError, ReplayConfig, load_config

FUZZ_SETTINGS = settings(max_examples=60, deadline=None,
                         suppress_health_check=[HealthCheck.function_scoped_fixture])

SECTIONS = [name for name in ReplayConfig.model_fields] + ["slam2d", "slam3d", "nonsense"]
DEFAULT_KEYS = {line.split("=")[0].strip() for line in ReplayConfig().to_toml().splitlines()
                if "=" in line and not line.lstrip().startswith("#")}
KEYS = [*sorted(DEFAULT_KEYS), "bogus", ""]
VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
    st.lists(st.integers(), max_size=3),
)


def load_text(text: str | bytes) -> ReplayConfig | None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "replay.toml"
        path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
        try:
            return load_config(path)
        except ConfigError as error:
            message = str(error)
            assert message.startswith(str(path)) and "\n" not in message, message
            return None


@FUZZ_SETTINGS
@given(st.binary(max_size=400))
def test_any_bytes(data: bytes) -> None:
    load_text(data)


@FUZZ_SETTINGS
@given(st.dictionaries(st.sampled_from(SECTIONS),
                       st.one_of(VALUES, st.dictionaries(st.sampled_from(KEYS), VALUES, max_size=4),
                                 st.dictionaries(st.sampled_from(["matching", "odometry", "keyframes",
                                                                  "loop_closure", "se3_polish"]),
                                                 st.dictionaries(st.sampled_from(KEYS), VALUES, max_size=3),
                                                 max_size=2)),
                       max_size=4))
def test_any_well_formed_toml(data: dict) -> None:
    try:
        text = tomli_w.dumps(data)
    except (TypeError, ValueError):  # None and some values have no TOML form
        return
    load_text(text)


@FUZZ_SETTINGS
@given(st.integers(min_value=0, max_value=2000), st.integers(min_value=0, max_value=255))
def test_one_byte_changed_in_the_defaults(position: int, value: int) -> None:
    text = bytearray(ReplayConfig().to_toml().encode())
    text[position % len(text)] = value
    load_text(bytes(text))
