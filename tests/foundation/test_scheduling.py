"""An agent process's CPU policy: every thread under SCHED_BATCH, the later ones too."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.agents.scheduling import use_batch_scheduling

# Run in a process of its own: the policy must not leak into the test runner's threads.
CHILD = """
import json, os, threading
from hilswarm.agents.scheduling import use_batch_scheduling

started, done = threading.Barrier(3), threading.Event()

def idle():
    started.wait(10)
    done.wait(10)

threads = [threading.Thread(target=idle) for _ in range(2)]
for thread in threads:
    thread.start()
started.wait(10)
nice = os.nice(0)
switched = use_batch_scheduling()
policies = sorted({os.sched_getscheduler(int(t)) for t in os.listdir("/proc/self/task")})
later = []
thread = threading.Thread(target=lambda: later.append(os.sched_getscheduler(0)))
thread.start()
thread.join(10)
done.set()
for thread in threads:
    thread.join(10)
print(json.dumps({"switched": switched, "policies": policies, "later": later,
                  "nice": [nice, os.nice(0)]}))
"""


@pytest.mark.skipif(not hasattr(os, "SCHED_BATCH"), reason="Linux scheduling policies")
def test_every_thread_goes_under_sched_batch_and_later_threads_inherit_it() -> None:
    result = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60, check=False
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["switched"] == 3  # the main thread and both others
    assert report["policies"] == [os.SCHED_BATCH]
    assert report["later"] == [os.SCHED_BATCH]
    assert report["nice"][0] == report["nice"][1]  # the niceness is left as it was


def test_nothing_is_switched_where_the_threads_cannot_be_listed(tmp_path: Path) -> None:
    assert use_batch_scheduling(tmp_path / "no-such-task-folder") == 0
