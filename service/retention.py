"""Forgetting old deletions from the maps' change feeds, in the background of the server.

Every deletion is kept for the change feed (``GET /collections/{id}/changes``)
until pruned: a map rebuilt often grows a row for each detection a rebuild
replaces. With ``LANEMAP_FEED_RETENTION_DAYS`` set, each server process prunes
every map's feed once at start and then every ``LANEMAP_FEED_PRUNE_INTERVAL_S``
seconds, as ``lanemap maps prune-feed --all`` does. Pruning is idempotent and
each map is pruned in a transaction of its own, so several server processes
pruning at once only repeat each other's work.
"""

from __future__ import annotations

import logging
import threading
from datetime import datetime, timedelta, timezone

from mapbuilder.store import Store

log = logging.getLogger(__name__)


class FeedPruner:
    """A daemon thread that prunes every map's change feed of deletions older than ``retention_days``.

    Parameters
    ----------
    store : Store
    retention_days : float
        Deletions recorded more than this many days ago are forgotten, days.
    interval_s : float
        Time between two prunings, seconds.
    """

    def __init__(self, store: Store, retention_days: float, interval_s: float) -> None:
        self.store = store
        self.retention = timedelta(days=retention_days)
        self.interval_s = interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="feed-pruner", daemon=True)
        self._thread.start()
        log.info("change feeds keep deletions for %g days; pruned every %g s",
                 self.retention.total_seconds() / 86400, self.interval_s)  # fmt: skip

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None

    def prune_once(self) -> dict[str, tuple[int, int]]:
        """Prune every map now; ``{map id: (deletions forgotten, revision the feed answers from)}``."""
        pruned = self.store.prune_all_removed(datetime.now(timezone.utc) - self.retention)
        n = sum(v[0] for v in pruned.values())
        if n:
            log.info("change feeds: %d deletions older than %g days forgotten in %d maps",
                     n, self.retention.total_seconds() / 86400, len(pruned))  # fmt: skip
        return pruned

    def _run(self) -> None:
        while True:
            try:
                self.prune_once()
            except Exception:  # the database away for a while: try again next time
                log.warning("pruning the change feeds failed; trying again in %g s", self.interval_s, exc_info=True)
            if self._stop.wait(self.interval_s):
                return
