"""Starting a recorder process, with nothing heavy imported (``hilswarm run`` starts one first).

The process (:mod:`hilswarm.orchestrator.recorder_process`) imports its modules (~1 s of CPU),
then waits for its set-up message on its standard input, which
:class:`~hilswarm.orchestrator.recorder_process.RecorderProcess` sends. So it can be started
before the run is known: ``hilswarm run`` starts it before its own imports, and the two import
at once.
"""

from __future__ import annotations

import subprocess
import sys


def start_recorder_process(python: str = sys.executable) -> subprocess.Popen[bytes]:
    """Start a recorder process waiting for its set-up. In a session of its own, so a Ctrl-C
    at the terminal reaches only the orchestrator; one never given its set-up is ended with
    SIGTERM (it ignores SIGINT).

    Raises:
        OSError: the interpreter cannot be started.
    """
    return subprocess.Popen(
        [python, "-m", "hilswarm.orchestrator.recorder_process"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        start_new_session=True,
    )
