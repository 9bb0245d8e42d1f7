"""Recorder -> reader round trip (Hypothesis): any messages, any times, come back in replay order."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from slamreplay.recorder import GroundTruthPose, OdometryPose, RangeBearingScan, Recorder, assert_msg_equal
from slamreplay.replay.engine.reader import RecordingReader

coord = st.floats(-1e3, 1e3, allow_nan=False)
message = st.one_of(
    st.builds(lambda t, x, y: ("/odom", OdometryPose(t, x, y, 0.25)), st.integers(0, 10**12), coord, coord),
    st.builds(lambda t, x, y: ("/ground_truth/pose", GroundTruthPose(t, x, y, -0.5)), st.integers(0, 10**12), coord,
              coord),
    st.builds(lambda t, r: ("/landmarks/range_bearing", RangeBearingScan(t, [abs(r)], [0.1], [3])),
              st.integers(0, 10**12), coord),
)


@settings(max_examples=30, deadline=None)
@given(st.lists(message, max_size=40))
def test_roundtrip_in_replay_order(messages: list[tuple[str, object]]) -> None:
    """Every message comes back equal, ordered by (log_time, write order)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "r.mcap"
        with Recorder(path, source={}) as rec:
            for topic, msg in messages:
                rec.write(topic, msg)  # type: ignore[arg-type]
        got = list(RecordingReader(path).messages())
    order = sorted(range(len(messages)), key=lambda i: (messages[i][1].stamp_ns, i))  # type: ignore[attr-defined]
    assert [e.topic for e in got] == [messages[i][0] for i in order]
    for env, i in zip(got, order, strict=True):
        assert_msg_equal(env.msg, messages[i][1])  # type: ignore[arg-type]
        assert env.log_time_ns == env.publish_time_ns == messages[i][1].stamp_ns  # type: ignore[attr-defined]
    assert [e.index for e in got] == list(range(len(got)))
