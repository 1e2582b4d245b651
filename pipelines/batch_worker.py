"""One recording of a local `papl-map batch` in its own process:

    python -m papl_mapper.pipelines.batch_worker OUT/.batch/<name>/job.json

Runs `pipelines.batch.run_job` (which writes result.json beside job.json) and exits 0 when the
recording mapped, 1 when it failed, 130 when interrupted. The first SIGINT interrupts the run at
its next stage boundary (run() keeps the checkpoints); later ones are ignored, so Ctrl-C on the
terminal and the batch forwarding it do not interrupt twice.
"""

from __future__ import annotations

import json
import signal
import sys
from pathlib import Path


def _interrupt_once(signum: int, frame: object) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    signal.signal(signal.SIGINT, _interrupt_once)
    args = sys.argv[1:] if argv is None else argv
    try:
        from papl_mapper.pipelines.batch import run_job

        row = run_job(json.loads(Path(args[0]).read_text()))
    except KeyboardInterrupt:
        return 130
    return {"ok": 0, "interrupted": 130}.get(row["status"], 1)


if __name__ == "__main__":
    sys.exit(main())
