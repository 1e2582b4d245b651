"""The log.txt of a run: a file handler on the papl_mapper logger that keeps the whole story (INFO and
above) even when the terminal is quiet. `papl-map run` and every batch job write it the same way."""

from __future__ import annotations

import logging
from pathlib import Path

_LOG = logging.getLogger("papl_mapper")


class _RunLog(logging.FileHandler):
    """A FileHandler that stops writing once its disk refuses (full, removed) instead of printing a
    traceback per record or failing the run on close: the terminal still shows the run's errors."""

    failed = False

    def handleError(self, record: logging.LogRecord) -> None:
        self.failed = True

    def emit(self, record: logging.LogRecord) -> None:
        if not self.failed:
            super().emit(record)

    def flush(self) -> None:
        try:
            super().flush()
        except OSError:
            self.failed = True

    def close(self) -> None:
        try:
            super().close()
        except OSError:
            self.failed = True


def file_log(path: Path, mode: str) -> logging.Handler:
    """Attach a log file (mode "w" or "a") to the papl_mapper logger; INFO reaches it even under -q."""
    handler = _RunLog(path, mode=mode)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.setLevel(min(_LOG.getEffectiveLevel(), logging.INFO))
    _LOG.setLevel(handler.level)
    _LOG.addHandler(handler)
    return handler


def close_log(handler: logging.Handler) -> None:
    """Detach and close a handler from `file_log`."""
    _LOG.removeHandler(handler)
    handler.close()
