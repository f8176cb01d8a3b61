"""Logs localized in the maps of other places, and in their own (issue 13: a wrong placement is said).

    OMP_NUM_THREADS=1 python benchmarks/other_place_bench.py --shared ../shared \\
        [--extra /work/extra_logs/fr079.mcap /work/extra_logs/intel.mcap] [--out DIR]

Maps every log (`replay LOG`, its session), then localizes every log in every session (`replay LOG --map
SESSION`) through `pipeline.replay`, and prints per pairing: refused (and why), or placed, with the scans
matched, the scans on the mapping robot's path left unmatched (`counts.scans_on_saved_path_unmatched`),
the wall crossings of the placed path (`counts.saved_map_wall_crossings`) and which warnings were given.
A log in its own map is the correct localization; every other pairing is a log of another building.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import pipeline  # noqa: E402
from frontends.errors import FrontendError  # noqa: E402
from pipeline.errors import PipelineError  # noqa: E402

SHARED_LOGS = {"csail": "data/logs/csail/csail.mcap", "aces": "data/logs/aces/aces.mcap",
               "mumble": "data/logs/mumble/hallway_room_loop"}
WARNINGS = {"on the path": "did not match the saved map", "walls": "cross its walls"}


def pairing_row(log: Path, map_name: str, session: Path, out: Path) -> str:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result = pipeline.replay(log, out_dir=out, map=session)
        except (FrontendError, PipelineError) as error:
            return f"| {log.stem} | {map_name} | refused: {str(error)[:90]} | | | | |"
    counts = json.loads(Path(result.outputs["json"]).read_text())["counts"]
    said = [name for name, text in WARNINGS.items() if any(text in str(w.message) for w in caught)]
    on_path, unmatched = counts["scans_on_saved_path"], counts["scans_on_saved_path_unmatched"]
    return (f"| {log.stem} | {map_name} | placed | {counts['scans_matched']} / {counts['scans']} | "
            f"{unmatched} / {on_path} ({unmatched / max(on_path, 1):.0%}) | "
            f"{counts['saved_map_wall_crossings']} | {', '.join(said) or '-'} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    parser.add_argument("--extra", type=Path, nargs="*", default=[], help="more 2D laser logs")
    parser.add_argument("--out", type=Path, default=None, help="keep the replays here (default: a temp dir)")
    args = parser.parse_args()
    logs = {name: args.shared / relative for name, relative in SHARED_LOGS.items()}
    logs.update({path.stem: path for path in args.extra})
    with tempfile.TemporaryDirectory() as temporary:
        out = args.out or Path(temporary)
        sessions = {name: Path(pipeline.replay(log, out_dir=out / f"map_{name}").outputs["session"])
                    for name, log in logs.items()}
        print("| log | map | result | scans matched | on the saved path unmatched | wall crossings "
              "| warned |")
        print("|---|---|---|---|---|---|---|")
        for map_name, session in sessions.items():
            for name, log in logs.items():
                print(pairing_row(log, map_name, session, out / f"{name}_in_{map_name}"), flush=True)


if __name__ == "__main__":
    main()
