"""Staged outputs: written in a hidden staging folder, published only when all are complete, one run of
an output set at a time, and whatever a killed run left cleaned up by the next."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from pipeline.errors import OutputError
from pipeline.outputs import json_text, prepare_output_dir, staged_outputs


def test_staged_outputs_rename_all_on_success(tmp_path: Path) -> None:
    targets = (tmp_path / "a.g2o", tmp_path / "a.json")
    targets[0].write_text("old")
    with staged_outputs(*targets) as temporaries:
        for temporary, target, text in zip(temporaries, targets, ("new graph", "new summary"), strict=True):
            assert temporary.name == target.name  # writers that look at the suffix see the real one
            assert temporary.parent.parent == target.parent and temporary.parent.name.startswith(".")
            temporary.write_text(text)
        assert targets[0].read_text() == "old"  # nothing replaced before the block ends
        assert not targets[1].exists()
    assert [target.read_text() for target in targets] == ["new graph", "new summary"]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a.g2o", "a.json"]


@pytest.mark.parametrize("failure", [ValueError, KeyboardInterrupt])
def test_staged_outputs_keep_old_files_and_remove_temporaries_on_failure(tmp_path: Path,
                                                                        failure: type[BaseException]) -> None:
    target = tmp_path / "a.rrd"
    target.write_text("good")
    with pytest.raises(failure), staged_outputs(target, tmp_path / "b.json") as (first, second):
        first.write_text("partial")
        second.write_text("partial")
        raise failure("interrupted")
    assert target.read_text() == "good"
    assert [path.name for path in tmp_path.iterdir()] == ["a.rrd"]


def test_a_rename_failing_while_publishing_puts_every_earlier_output_back(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    targets = (tmp_path / "a.g2o", tmp_path / "a.json", tmp_path / "a.session", tmp_path / "a.tum")
    for target in targets[:3]:
        target.write_text(f"old {target.suffix}")  # a.tum is new in this run
    real_replace = os.replace

    def failing_on_the_session(source: str | os.PathLike[str], destination: str | os.PathLike[str]) -> None:
        if Path(destination) == targets[2] and Path(source).parent.name.startswith(".a.staging-"):
            raise PermissionError(1, "Operation not permitted", str(destination))
        real_replace(source, destination)

    monkeypatch.setattr(os, "replace", failing_on_the_session)
    with (pytest.raises(OutputError, match=r"a\.session: cannot write the file: Operation not permitted"),
          staged_outputs(targets[3], *targets[:3]) as temporaries):
        for temporary in temporaries:
            temporary.write_text("new")
    # The new a.tum and a.g2o, a.json published before the failure are gone, the old files back.
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a.g2o", "a.json", "a.session"]
    assert [target.read_text() for target in targets[:3]] == ["old .g2o", "old .json", "old .session"]


def test_a_folder_where_an_output_would_go_is_refused_before_the_run(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_text("old")
    (tmp_path / "a.session").mkdir()
    ran = False
    with (pytest.raises(OutputError, match=r"a\.session: is a folder"),
          staged_outputs(tmp_path / "a.json", tmp_path / "a.session")):
        ran = True
    assert not ran
    assert (tmp_path / "a.json").read_text() == "old" and (tmp_path / "a.session").is_dir()


@pytest.mark.parametrize("during", ["staging folder", "lock file"])
@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM", "SIGALRM"])
def test_a_stop_signal_during_the_clean_up_is_held_until_it_is_done(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, during: str, signal_name: str) -> None:
    """Ctrl-C pressed again, SIGTERM, or the alarm retrying a lost interrupt (`install_stop_signals`), while
    an interrupted run removes its staging folder or its lock file: the signal waits for the clean-up,
    then stops the run."""
    import shutil
    import signal

    from pipeline import outputs

    number = getattr(signal, signal_name)
    removed: list[str] = []

    def interrupted(remove: Callable[..., None]) -> Callable[..., None]:
        def remove_with_a_signal(*args: object, **kwargs: object) -> None:
            signal.raise_signal(number)  # lands as the clean-up starts
            remove(*args, **kwargs)
            removed.append(during)
        return remove_with_a_signal

    def stop(_signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    if during == "staging folder":
        monkeypatch.setattr(outputs.shutil, "rmtree", interrupted(shutil.rmtree))
    else:
        monkeypatch.setattr(outputs.Path, "unlink", interrupted(Path.unlink))
    previous = signal.signal(number, stop)
    try:
        with pytest.raises(KeyboardInterrupt), staged_outputs(tmp_path / "a.g2o") as (temporary,):
            temporary.write_text("half")
            raise KeyboardInterrupt  # the first Ctrl-C
    finally:
        signal.signal(number, previous)
    assert removed == [during]
    assert list(tmp_path.iterdir()) == []


def test_a_second_run_of_the_same_outputs_fails_clearly_while_the_first_writes(tmp_path: Path) -> None:
    with staged_outputs(tmp_path / "a.g2o", tmp_path / "a.json") as (first, second):
        with pytest.raises(OutputError, match="another replay is writing the a outputs"), \
                staged_outputs(tmp_path / "a.g2o"):
            pass
        with staged_outputs(tmp_path / "b.g2o") as (other,):  # other outputs in the same folder: fine
            other.write_text("b")
        first.write_text("g2o")
        second.write_text("json")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a.g2o", "a.json", "b.g2o"]


def test_the_next_run_cleans_up_after_a_killed_one(tmp_path: Path) -> None:
    (tmp_path / "a.json").write_text("old")
    # Killed while writing: an incomplete staging folder and the lock file remain.
    incomplete = tmp_path / ".a.staging-123-abcd"
    incomplete.mkdir()
    (incomplete / "a.json").write_text("half")
    (tmp_path / ".a.lock").write_text("")
    # Killed while publishing: the staged set was whole, one file was already renamed.
    publishing = tmp_path / ".b.staging-124-abcd"
    publishing.mkdir()
    (publishing / "b.json").write_text("new json")
    (publishing / ".complete").write_text("")
    (tmp_path / "b.g2o").write_text("new g2o")
    (publishing / ".replaced").mkdir()  # the previous b.g2o, moved aside for the new one
    (publishing / ".replaced" / "b.g2o").write_text("old g2o")
    with staged_outputs(tmp_path / "a.g2o") as (temporary,):
        temporary.write_text("a")
    with staged_outputs(tmp_path / "b.rrd") as (temporary,):
        temporary.write_text("b")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["a.g2o", "a.json", "b.g2o", "b.json", "b.rrd"]
    assert (tmp_path / "a.json").read_text() == "old" and (tmp_path / "b.json").read_text() == "new json"
    assert (tmp_path / "b.g2o").read_text() == "new g2o"


def test_a_run_killed_while_undoing_a_failed_publication_is_undone_by_the_next(tmp_path: Path) -> None:
    # The set no longer complete (its marker removed first), c.g2o already back, c.json not yet.
    (tmp_path / "c.g2o").write_text("old g2o")
    (tmp_path / "c.json").write_text("new json")
    undoing = tmp_path / ".c.staging-125-abcd"
    (undoing / ".replaced").mkdir(parents=True)
    (undoing / ".replaced" / "c.json").write_text("old json")
    (undoing / "c.rrd").write_text("new rrd, never published")
    with staged_outputs(tmp_path / "c.tum") as (temporary,):
        temporary.write_text("c")
    assert sorted(path.name for path in tmp_path.iterdir()) == ["c.g2o", "c.json", "c.tum"]
    assert (tmp_path / "c.json").read_text() == "old json"


def test_errors_name_the_output_not_the_hidden_copy(tmp_path: Path) -> None:
    from pipeline.outputs import write_text

    with pytest.raises(OutputError) as caught, staged_outputs(tmp_path / "a.json") as (temporary,):
        temporary.mkdir()  # writing a file there now fails
        write_text(temporary, "x")
    assert str(caught.value).startswith(f"{tmp_path / 'a.json'}: cannot write the file")


def test_an_image_or_a_session_that_cannot_be_written_is_an_output_error_naming_it(tmp_path: Path) -> None:
    import numpy as np

    from pipeline.outputs import write_png
    from pipeline.session_file import write_session_file

    missing = tmp_path / "no such folder"
    with pytest.raises(OutputError, match=f"^{missing / 'map.png'}: cannot write the image: "):
        write_png(missing / "map.png", np.zeros((4, 4), dtype=np.uint8))
    with pytest.raises(OutputError, match=f"^{missing / 'run.session'}: cannot write the session: "):
        write_session_file(missing / "run.session", {}, {}, [])
    assert not missing.exists()


def test_staged_outputs_require_every_file(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match="was not written"), \
            staged_outputs(tmp_path / "a.txt", tmp_path / "b.txt") as (first, _):
        first.write_text("only one")
    assert list(tmp_path.iterdir()) == []


def test_prepare_output_dir(tmp_path: Path) -> None:
    assert prepare_output_dir(tmp_path / "x" / "y") is True
    assert prepare_output_dir(tmp_path / "x" / "y") is False
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputError, match="not a folder"):
        prepare_output_dir(tmp_path / "file")


def test_json_text_writes_non_finite_numbers_as_null() -> None:
    data = json.loads(json_text({"chi2": [1.5, float("nan"), float("inf")], "n": 3}))
    assert data == {"chi2": [1.5, None, None], "n": 3}
