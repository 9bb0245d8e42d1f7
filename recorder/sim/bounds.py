"""What one simulation may ask for, said once for the three simulators (their configs check it).

A simulation runs where it is asked: on a user's machine, and in the service's request thread
(``POST /recordings/record/NAME``), where a JSON body of ``{"landmarks": 8371841}`` took 24 GB and
``{"image_height": 127058998962946049}`` as much before these bounds (the schemathesis pass). Each bound
is far beyond what the simulators are used for, and its error says what to do instead.
"""

from __future__ import annotations

from typing import Final

MAX_LANDMARKS: Final = 100_000  # sim-landmarks: 6x the 16,000 features of the scaling benchmarks
MAX_SAMPLES: Final = 2_000_000  # odometry/ground-truth samples or scans: 2.3 days at 10 Hz (1.1 GB, 2.5 min)
MAX_IMAGE_SIDE_PX: Final = 4096  # a camera image's side
MAX_IMAGES: Final = 100_000  # images of one recording (the corridor's default route: about 1,200)
MAX_SEABED_PX: Final = 256_000_000  # sim-seabed's rendered seabed, pixels (16,000 x 16,000)


def too_many(what: str, count: float, bound: int, advice: str) -> str | None:
    """The error when ``count`` of ``what`` passes ``bound``, else None."""
    if count <= bound:
        return None
    return f"{what}: {count:,.0f}, more than {bound:,}: {advice}"
