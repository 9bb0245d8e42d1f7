"""The ``victoria-park`` importer (``slamreplay record victoria-park``): in replay/ because the reference it
records, the batch least-squares optimum of the measurements, is computed by
``slamreplay.replay.evaluation.landmark_reference``.

It implements ``slamreplay.recorder.sources.Importer`` and is found through the entry-point group
``slamreplay.importers``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from slamreplay.recorder.sources import OUT_HELP, Progress


class VictoriaPark:
    name = "victoria-park"
    help = "import Victoria Park (iSAM graph form, trees)"
    description = ("Import Victoria Park's iSAM/GTSAM file: odometry composed into poses, tree sightings as "
                   "range-bearing scans with their landmark ids. The file has no ground truth: the batch least-squares "
                   "optimum of the same measurements is recorded as the reference runs are scored against.")
    progress_label = "importing Victoria Park"

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("dir", help="the folder holding victoria_park.txt (or the file)")
        parser.add_argument("--out", required=True, help=OUT_HELP)
        parser.add_argument("--no-reference", action="store_true",
                            help="skip the batch optimum (no /ground_truth topics; runs are not scored)")
        parser.add_argument("--merge-window-m", type=float, default=0.0, metavar="M",
                            help="gather the sightings of consecutive poses over M metres of odometry into one scan "
                                 "(default 0: one scan per pose, as in the file; D-SLAM needs scans seeing two trees)")

    def record(self, options: Mapping[str, Any], progress: Progress, log: Callable[[str], None]) -> str:
        from slamreplay.recorder.importers.victoria_park import read_victoria_park, write_victoria_park

        data = read_victoria_park(Path(options["dir"]))
        reference, note, measured = None, "", None
        if not options["no_reference"]:
            from slamreplay.replay.evaluation.landmark_reference import recording_reference

            log("computing the reference: the batch least-squares optimum of the measurements (under a minute)")
            poses, landmarks, measured, note = recording_reference(data)
            reference = (poses, landmarks)
        s = write_victoria_park(data, Path(options["out"]), reference=reference, reference_note=note,
                                measured_model=measured, merge_window_m=options["merge_window_m"], progress=progress)
        return (f"{s.poses:,} poses, {s.scans:,} scans with {s.observations:,} observations of {s.landmarks} "
                f"landmarks, {s.path_length_m / 1000:.2f} km driven"
                + (f"; ground truth = {note}" if reference is not None else "; no reference (--no-reference)"))
