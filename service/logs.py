"""The server's log: uvicorn's logging configuration, as text lines or as JSON lines.

``LANEMAP_LOG_FORMAT=text`` (the default) gives uvicorn's lines with the
request ID (``INFO:     [3f2c…] 127.0.0.1:50412 - "GET / HTTP/1.1" 200``);
``json`` gives one JSON object per line, for a log collector: ``time`` (UTC,
ISO 8601), ``level``, ``logger``, ``pid`` (the server process), ``request_id``, ``token`` (the
name of the token the request came with, ``-`` without one), ``message``, an access
line's ``client``, ``method``, ``path``, ``http_version`` and ``status``, and
an error's ``exception`` (its traceback as text).
"""

from __future__ import annotations

import copy
import json
import logging
from datetime import datetime, timezone
from typing import Literal

from .request_id import RequestIdFilter

LogFormat = Literal["text", "json"]

#: uvicorn's access lines: ``'%s - "%s %s HTTP/%s" %d'`` with these arguments.
_ACCESS_FIELDS = ("client", "method", "path", "http_version", "status")


class JsonFormatter(logging.Formatter):
    """One JSON object per record (see the module's docstring for its keys)."""

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "time": datetime.fromtimestamp(record.created, timezone.utc).isoformat(timespec="milliseconds")
            .replace("+00:00", "Z"),
            "level": record.levelname,
            "logger": record.name,
            "pid": record.process,
            "request_id": getattr(record, "request_id", "-"),
            "token": getattr(record, "client_name", "-"),
            "message": record.getMessage(),
        }
        if record.name == "uvicorn.access" and isinstance(record.args, tuple) \
                and len(record.args) == len(_ACCESS_FIELDS):
            out.update(zip(_ACCESS_FIELDS, record.args))
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exception"] = record.exc_text
        return json.dumps(out, ensure_ascii=False, default=str)


def log_config(fmt: LogFormat = "text") -> dict:
    """uvicorn's logging configuration with the request ID in every record.

    The service's own loggers (``service.*``) log at INFO through the same
    handler as uvicorn's, in every server process. With ``fmt="json"`` every
    handler writes :class:`JsonFormatter` lines.
    """
    from uvicorn.config import LOGGING_CONFIG

    config = copy.deepcopy(LOGGING_CONFIG)
    config["filters"] = {"request_id": {"()": RequestIdFilter}}
    for handler in config["handlers"].values():
        handler.setdefault("filters", []).append("request_id")
    if fmt == "json":
        config["formatters"] = {name: {"()": JsonFormatter} for name in config["formatters"]}
    else:
        config["formatters"]["default"]["fmt"] = "%(levelprefix)s [%(request_id)s] %(message)s"
        config["formatters"]["access"]["fmt"] = (
            '%(levelprefix)s [%(request_id)s] %(client_addr)s - "%(request_line)s" %(status_code)s'
        )
    config["loggers"]["service"] = {"handlers": ["default"], "level": "INFO", "propagate": False}
    return config
