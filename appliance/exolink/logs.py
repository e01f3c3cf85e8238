"""Structured logging: JSON lines off a terminal (journald, supervisor capture), readable on one.

Every line carries the node name so the supervisor's merged log stays attributable.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any

import structlog


def setup(node: str, level: str | None = None, json: bool | None = None) -> structlog.BoundLogger:
    """Configure structlog once per process and return a logger bound to ``node``."""
    level_name = (level or os.environ.get("EXOLINK_LOG_LEVEL", "info")).upper()
    if json is None:
        json = not sys.stderr.isatty() or os.environ.get("EXOLINK_LOG_JSON") == "1"
    renderer: Any = (
        structlog.processors.JSONRenderer()
        if json
        else structlog.dev.ConsoleRenderer(colors=sys.stderr.isatty())
    )
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.format_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(
            logging.getLevelNamesMapping().get(level_name, logging.INFO)
        ),
        logger_factory=structlog.PrintLoggerFactory(file=sys.stderr),
        cache_logger_on_first_use=True,
    )
    structlog.contextvars.bind_contextvars(node=node)
    return structlog.get_logger()


def get(**bind: Any) -> structlog.BoundLogger:
    return structlog.get_logger().bind(**bind)


RARELY_EVERY = 1000


def rarely(n: int) -> bool:
    """Whether the ``n``-th of a kind of junk (a malformed frame, an unreadable sample) is
    logged: the first and every RARELY_EVERY-th. Each is counted where it arrives; anyone on
    the network or the bus can send junk, and a flood of it must not flood the journal too."""
    return n == 1 or n % RARELY_EVERY == 0
