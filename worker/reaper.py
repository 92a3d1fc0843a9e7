"""The reaper's own process: a pass of `worker.tasks.reap_lost_work` at start and every REAPER_INTERVAL after.

It is no task: it runs neither in a scoring consumer nor behind their queue, so a full, slow or wedged pool
never delays it. worker.supervisor runs it (`navsim-lb worker --reaper`, exactly one in a deployment; a second
would only send duplicates, which drop) and starts it again when it dies or when a pass outlasts
PASS_LIMIT_S.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import time

from server.settings import get_settings
from worker.logs import LOG_FORMAT
from worker.supervised import become_supervised, report_busy, report_idle

# A pass is a few queries and sends, in well under a second; the embedded broker's writers wait up to 30 s
# for its file's lock. A pass still running after this long is wedged: its supervisor kills it.
PASS_LIMIT_S = 90.0
PASS = "reaper pass"
log = logging.getLogger("worker.reaper")


def run_reaper(app_module: str) -> None:
    """Reap until SIGTERM or SIGINT, sending with the Celery app of `app_module` (tests inject faults there)."""
    importlib.import_module(app_module)
    from worker import tasks  # after the app module, which may have replaced what a pass calls

    signal.signal(signal.SIGTERM, signal.default_int_handler)  # a pass stopped midway rolls back
    become_supervised()
    interval = get_settings().reaper_interval
    log.info("reaper ready: a pass every %.0f s", interval)
    try:
        while True:
            report_busy(PASS, None, PASS_LIMIT_S)
            try:
                tasks.reap_lost_work()
            except Exception:  # the database or the broker away: the next pass tries again
                log.exception("reaper pass failed; the next one follows in %.0f s", interval)
            report_idle()
            time.sleep(interval)
    except KeyboardInterrupt:
        log.info("reaper stopped")


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m worker.reaper", description=__doc__)
    parser.add_argument("--app", default="worker.app", help="module of the workers' Celery app")
    parser.add_argument("--loglevel", default="info")
    arguments = parser.parse_args()
    logging.basicConfig(level=arguments.loglevel.upper(), format=LOG_FORMAT)
    run_reaper(arguments.app)


if __name__ == "__main__":
    main()
