"""Streaming a mocap client in a test: on a thread, bounded, until enough frames or an error."""

from __future__ import annotations

import threading

from hilswarm.agents.mocap.clients import Frame, MotionCaptureClient


def stream(
    client: MotionCaptureClient, frames_wanted: int, bound_s: float = 20.0
) -> tuple[list[Frame], BaseException | None]:
    """Run ``client`` on a thread until it gave ``frames_wanted`` frames (then stop) or raised;
    bounded by ``bound_s``."""
    frames: list[Frame] = []
    errors: list[BaseException] = []
    enough = threading.Event()

    def on_frame(frame: Frame) -> None:
        frames.append(frame)
        if len(frames) >= frames_wanted:
            enough.set()
            client.stop()

    def target() -> None:
        try:
            client.run(on_frame, lambda: None)
        except BaseException as exc:
            errors.append(exc)
        finally:
            enough.set()

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    assert enough.wait(bound_s), "no frames and no error within the bound"
    client.stop()
    thread.join(10.0)
    assert not thread.is_alive()
    return frames, (errors[0] if errors else None)
