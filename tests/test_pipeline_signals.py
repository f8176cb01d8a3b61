"""A replay stopped by SIGTERM or SIGKILL at any point leaves the old outputs or the new ones, complete, and
nothing else (after SIGKILL: once the next run into the folder has cleaned up)."""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from optimizer.cost import chi2
from optimizer.graph_files import read_graph, write_g2o
from optimizer.gridworld import generate_grid_world
from pipeline.outputs import install_stop_signals

OUTPUTS = {"city.g2o", "city.json", "city.rrd"}


def _replay(graph: Path, out: Path, iterations: int) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "pipeline.launcher", str(graph), "--out", str(out), "--quiet",
         "--iterations", str(iterations)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
    )


def _state(graph: Path, out: Path) -> str:
    """'old' or 'new' when the folder holds exactly one complete, consistent set of outputs."""
    assert {path.name for path in out.iterdir()} == OUTPUTS
    summary = json.loads((out / "city.json").read_text())
    written = read_graph(out / "city.g2o").graph
    original = read_graph(graph).graph
    assert summary["chi2_final"] == pytest.approx(chi2(original, written.poses), rel=1e-9)
    assert (out / "city.rrd").stat().st_size > 0
    return "old" if summary["iterations"]["sgd"] == 1 else "new"


@pytest.fixture(scope="module")
def city(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("graph") / "city.g2o"
    world = generate_grid_world(4000, seed=3)
    write_g2o(path, world.graph)
    return path


@pytest.mark.parametrize("delay", [0.2, 3.0, 6.0])
@pytest.mark.parametrize("signal_number", [signal.SIGTERM, signal.SIGKILL])
def test_a_stopped_replay_leaves_old_or_new_outputs(city: Path, tmp_path: Path, delay: float,
                                                     signal_number: int) -> None:
    out = tmp_path / "out"
    first = _replay(city, out, iterations=1)
    assert first.wait(timeout=120) == 0, first.stderr.read() if first.stderr else ""
    assert _state(city, out) == "old"

    second = _replay(city, out, iterations=60)
    time.sleep(delay)
    second.send_signal(signal_number)
    code = second.wait(timeout=120)
    stderr = second.stderr.read() if second.stderr else ""
    if signal_number == signal.SIGTERM:
        # 0: it had finished before the signal came; -15: it came before Python ran any of our code.
        assert code in (0, 128 + signal.SIGTERM, -signal.SIGTERM), stderr
        assert "Traceback" not in stderr
    else:
        # Whatever a killed run left (its staging folder, its lock) goes with the next run into the folder.
        third = _replay(city, out, iterations=1)
        assert third.wait(timeout=120) == 0
    assert _state(city, out) in ("old", "new")


def _exit_code_of_main(monkeypatch: pytest.MonkeyPatch) -> int:
    """`replay`'s entry point run here (its exit raised, not made), with the stop signals' handlers it
    installs put back afterwards."""
    import pipeline.cli as cli

    def exit_code(code: int) -> None:
        raise SystemExit(code)

    stop_signals = (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)
    previous = {number: signal.getsignal(number) for number in stop_signals}
    monkeypatch.setattr(cli, "_exit_now", exit_code)
    try:
        with pytest.raises(SystemExit) as stopped:
            cli.main()
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    return int(stopped.value.code)  # type: ignore[arg-type]


@pytest.mark.parametrize("signal_number", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_before_the_command_runs_is_a_quiet_interrupt(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signal_number: int) -> None:
    """The signal lands while the BLAS thread limit is being set, before typer can turn it into Abort."""
    import threadpoolctl


    @contextlib.contextmanager
    def signalled_on_entry(**_limits: object):  # type: ignore[no-untyped-def]
        os.kill(os.getpid(), signal_number)
        yield

    monkeypatch.setattr(threadpoolctl, "threadpool_limits", signalled_on_entry)
    assert _exit_code_of_main(monkeypatch) == 128 + signal_number
    assert "Traceback" not in capsys.readouterr().err


def _interrupt_inside_a_callback_from_c() -> None:
    """What numba's dispatcher raises when a stop signal's KeyboardInterrupt leaves a Python callback it
    made (its `_numba_unpickle`, seen in 3 of 21 Ctrl-Cs of a CSAIL replay)."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as interrupt:
        raise SystemError("<function _numba_unpickle> returned a result with an exception set") from interrupt


@pytest.mark.parametrize("inputs", [1, 2])
def test_an_interrupt_that_a_callback_from_c_wrapped_is_still_a_quiet_interrupt(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path,
        inputs: int) -> None:
    from pipeline import batch

    def replay(*_args: object, **_kwargs: object) -> None:
        _interrupt_inside_a_callback_from_c()

    monkeypatch.setattr(batch, "replay", replay)
    names = ["a.g2o", "b.g2o"][:inputs]
    monkeypatch.setattr(sys, "argv", ["replay", *(str(tmp_path / name) for name in names),
                                      "--out", str(tmp_path / "out")])
    for name in names:
        (tmp_path / name).write_text("VERTEX_SE2 0 0 0 0\n")
    # Not a traceback, nor "a.g2o failed" and a batch going on to b.g2o: the command stops as after Ctrl-C.
    assert _exit_code_of_main(monkeypatch) == 130
    assert "Traceback" not in capsys.readouterr().err


# --- a batch's workers stop with their parent ------------------------------------------------------------

BATCH_STEMS = ("north", "south")


def _descendants(pid: int) -> dict[int, float]:
    """The processes under `pid` (workers, forkserver, resource tracker): pid → start time, which tells a
    reused pid from the same process."""
    try:
        import psutil
    except ImportError:
        found: dict[int, float] = {}
        parents = {pid}
        grew = True
        while grew:
            grew = False
            for entry in Path("/proc").iterdir():
                if entry.name.isdigit() and int(entry.name) not in found | {pid: 0.0}:
                    stat = _proc_stat(int(entry.name))
                    if stat is not None and int(stat[1]) in parents:
                        found[int(entry.name)] = float(stat[19])
                        parents.add(int(entry.name))
                        grew = True
        return found
    with contextlib.suppress(psutil.NoSuchProcess):
        return {child.pid: child.create_time() for child in psutil.Process(pid).children(recursive=True)}
    return {}


def _proc_stat(pid: int) -> list[str] | None:
    """/proc/PID/stat after the command name: state, ppid, …, start time at index 19."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()


def _alive(pid: int, started: float) -> bool:
    """Whether that process still runs (a zombie awaiting its parent's wait does not count)."""
    try:
        import psutil
    except ImportError:
        stat = _proc_stat(pid)
        return stat is not None and float(stat[19]) == started and stat[0] != "Z"
    try:
        process = psutil.Process(pid)
        return process.create_time() == started and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _wait_for(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _batch_state(out: Path) -> dict[str, object]:
    """Per stem: the method and SGD iterations its summary names, after checking the folder holds complete
    sets of outputs and nothing else (no staging folder, no lock); and the batch table's bytes."""
    names = {path.name for path in out.iterdir()}
    outputs = {f"{stem}.{suffix}" for stem in BATCH_STEMS for suffix in ("g2o", "json", "rrd")}
    assert names == outputs | {"batch_summary.parquet"}
    state: dict[str, object] = {"batch_summary": (out / "batch_summary.parquet").read_bytes()}
    for stem in BATCH_STEMS:
        summary = json.loads((out / f"{stem}.json").read_text())
        assert (out / f"{stem}.rrd").stat().st_size > 0 and (out / f"{stem}.g2o").stat().st_size > 0
        state[stem] = (summary["method"], summary["iterations"]["sgd"])
    return state


@pytest.fixture(scope="module")
def batch(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[Path], Path]:
    """Two graphs, and a folder of their outputs from a one-iteration run (the 'old' outputs)."""
    folder = tmp_path_factory.mktemp("batch")
    graphs = []
    for seed, stem in enumerate(BATCH_STEMS):
        graphs.append(folder / f"{stem}.g2o")
        write_g2o(graphs[-1], generate_grid_world(1500, seed=seed).graph)
    old = folder / "old"
    done = subprocess.run(
        [sys.executable, "-m", "pipeline.launcher", *map(str, graphs), "--out", str(old), "--quiet",
         "--method", "sgd", "--iterations", "1", "--allow-unconverged"],
        capture_output=True, text=True, timeout=300, env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    return graphs, old


@pytest.mark.parametrize("whom", ["parent-SIGINT", "parent-SIGTERM", "group-SIGINT", "group-SIGTERM"])
def test_an_interrupted_batch_stops_its_workers_and_publishes_nothing(
        batch: tuple[list[Path], Path], tmp_path: Path, whom: str) -> None:
    graphs, old = batch
    out = tmp_path / "out"
    shutil.copytree(old, out)
    expected = _batch_state(out)
    # Enough iterations that neither input can finish: whatever the folder holds later was there before.
    parent = subprocess.Popen(
        [sys.executable, "-m", "pipeline.launcher", *map(str, graphs), "--jobs", "2", "--out", str(out),
         "--quiet", "--method", "sgd", "--iterations", "1000000", "--allow-unconverged"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"})
    try:
        # Both workers replaying: each input's staging folder exists.
        _wait_for(lambda: all(any(out.glob(f".{stem}.staging-*")) for stem in BATCH_STEMS), 180,
                  "both workers to start replaying")
        helpers = _descendants(parent.pid)
        assert len(helpers) >= 3  # two workers and the forkserver (and the resource tracker)
        number = signal.SIGTERM if whom.endswith("SIGTERM") else signal.SIGINT
        if whom.startswith("group"):  # as `timeout` and service managers do: the forkserver gets it too
            os.killpg(parent.pid, number)
        else:
            parent.send_signal(number)
        code = parent.wait(timeout=60)
        stderr = parent.stderr.read() if parent.stderr else ""
        assert code == 128 + number, stderr
        assert "Traceback" not in stderr
        assert _batch_state(out) == expected  # already when the command has ended, not some time later
        _wait_for(lambda: not any(_alive(pid, started) for pid, started in helpers.items()), 20,
                  f"the workers, the forkserver and the resource tracker to exit ({sorted(helpers)})")
        assert _batch_state(out) == expected
    finally:
        with contextlib.suppress(ProcessLookupError):  # whatever a failure left running
            os.killpg(parent.pid, signal.SIGKILL)


def test_a_stopped_pool_waits_for_workers_its_forkserver_no_longer_reports(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A signal to the whole process group ends the forkserver too, after which the pool's process objects
    say every worker has ended (exit code 255) while a worker may still be cleaning up its outputs (a kernel
    runs a while before Python sees the signal): the command must not end before that worker."""
    from pipeline import batch

    cleaning_up = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(1.0)"])

    class ReportedEnded:
        pid = cleaning_up.pid

        def terminate(self) -> None:
            pass

        def join(self, timeout: float | None = None) -> None:
            pass

        def is_alive(self) -> bool:
            return False

    class Pool:
        def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
            pass

    monkeypatch.setattr(batch, "_pool_processes", lambda pool: [ReportedEnded()])
    try:
        started = time.monotonic()
        batch._stop_pool(Pool(), [], tmp_path)  # type: ignore[arg-type]
        assert cleaning_up.poll() is not None or _proc_stat(cleaning_up.pid)[0] == "Z"  # type: ignore[index]
        assert time.monotonic() - started < batch.STOP_GRACE_S
    finally:
        cleaning_up.kill()
        cleaning_up.wait()


def test_an_interrupt_raised_where_python_cannot_propagate_it_is_retried_silently(
        capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C landing in a callback from C (numba's LLVM object cache while a kernel compiles): Python
    prints the KeyboardInterrupt as an ignored exception with its traceback and drops it. It must instead
    reach the run a moment later, and print nothing."""
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # restored after the test
    stop_signals = (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)
    previous = {number: signal.getsignal(number) for number in stop_signals}
    handled: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        handled.append(signum)
        raise KeyboardInterrupt

    @ctypes.CFUNCTYPE(None)
    def called_from_c() -> None:
        signal.raise_signal(signal.SIGINT)

    try:
        install_stop_signals(on_signal)
        with pytest.raises(KeyboardInterrupt):
            called_from_c()
            time.sleep(2.0)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        for number, handler in previous.items():
            signal.signal(number, handler)
    assert handled == [signal.SIGINT, signal.SIGALRM]
    assert "Traceback" not in capfd.readouterr().err
