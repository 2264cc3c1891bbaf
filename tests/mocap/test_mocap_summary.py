"""The run's last line about the mocap process (orchestrator/mocap_runner.py: describe_frames)."""

from __future__ import annotations

from hilswarm.orchestrator.mocap_runner import describe_frames


def test_frames_skipped_and_published_are_said_only_when_they_matter() -> None:
    assert describe_frames({}) is None  # no counts yet (the process never streamed)
    assert describe_frames({"frames": 400, "frames_skipped": 0, "frames_published": 400}) == (
        "mocap: 400 frames"
    )
    assert describe_frames({"frames": 400, "frames_skipped": 3, "frames_published": 160}) == (
        "mocap: 400 frames, 3 skipped (the mocap process fell behind); "
        "poses published for 160 of them (tick_frames_only)"
    )
