"""The error answers of every operation in the OpenAPI document.

FastAPI documents only a 422 with its own ``HTTPValidationError`` body as
``application/json``; the service answers every error as RFC 9457
``application/problem+json`` and with more statuses than that. Clients
generated from the document, and response conformance checks, need the truth,
so :func:`document_problems` adds to each operation the problem answers it can
give:

* every operation: 400 (malformed query or body), 401 (a token is missing or
  wrong: writes, and reads when ``LANEMAP_READ_TOKEN_REQUIRED=1``), 404
  (unknown map, feature, changeset...), 422 (invalid values) and 503 (the
  database is busy or unreachable);
* operations with a request body: 413 (too large) and 415 (wrong content type);
* writes (POST, PUT, PATCH, DELETE): 409 (conflict with the stored state);
* operations that need a write token (security scheme ``WriteToken``): 403
  (a read token, ``LANEMAP_READ_TOKENS``, which may not change data);
* operations taking ``If-Match``: 412 (stale version);
* imagery uploads: 500 (the imagery folder is not writable) and 507 (the disk
  is full).
"""

from __future__ import annotations

from http import HTTPStatus
from typing import Any

from fastapi import FastAPI

PROBLEM_JSON = "application/problem+json"

PROBLEM_SCHEMA: dict[str, Any] = {
    "title": "Problem",
    "description": "RFC 9457 problem details; some problems add members (errors, conflicting_ids...).",
    "type": "object",
    "required": ["type", "title", "status", "detail"],
    "properties": {
        "type": {"type": "string", "description": "URI of the problem type (urn:lanemap:problem:...)"},
        "title": {"type": "string"},
        "status": {"type": "integer", "minimum": 400, "maximum": 599},
        "detail": {"type": "string", "description": "Names the field and what is wrong with it"},
        "instance": {"type": "string"},
        "errors": {
            "type": "array",
            "items": {"type": "object", "properties": {"field": {"type": "string"}, "message": {"type": "string"},
                                                        "type": {"type": ["string", "null"]}}},
        },  # fmt: skip
        "conflicting_ids": {"type": "array", "items": {"type": "string"}},
    },
    "additionalProperties": True,
}

_WRITES = {"post", "put", "patch", "delete"}


def _needs_write_token(operation: dict[str, Any]) -> bool:
    return any("WriteToken" in req for req in operation.get("security", []))


def problem_statuses(method: str, operation: dict[str, Any]) -> set[int]:
    """The error statuses an operation can answer (see the module docstring)."""
    codes = {400, 401, 404, 422, 503}
    if "requestBody" in operation:
        codes |= {413, 415}
    if method in _WRITES:
        codes.add(409)
    if _needs_write_token(operation):
        codes.add(403)
    if any(p.get("in") == "header" and p.get("name", "").lower() == "if-match"
           for p in operation.get("parameters", [])):  # fmt: skip
        codes.add(412)
    if method == "post" and "Imagery" in operation.get("tags", []):
        codes |= {500, 507}  # the imagery folder is unwritable / the disk is full
    return codes


def add_problem_responses(schema: dict[str, Any]) -> dict[str, Any]:
    """Document the problem answers of every operation of an OpenAPI document, in place."""
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    components["Problem"] = PROBLEM_SCHEMA
    ref = {"$ref": "#/components/schemas/Problem"}
    for ops in schema.get("paths", {}).values():
        for method, op in ops.items():
            if method not in {"get", "head", "post", "put", "patch", "delete", "options"}:
                continue
            if _needs_write_token(op):
                # The routers' read check runs on writes too; only a write token gets past both.
                op["security"] = [{"WriteToken": []}]
            responses = op.setdefault("responses", {})
            declared = {int(c) for c in responses if c.isdigit() and int(c) >= 400}
            for code in sorted(problem_statuses(method, op) | declared):
                resp = responses.setdefault(str(code), {})
                resp.setdefault("description", HTTPStatus(code).phrase)
                resp["content"] = {PROBLEM_JSON: {"schema": ref}}
    # FastAPI's own validation-error schemas are no longer referenced.
    for name in ("HTTPValidationError", "ValidationError"):
        components.pop(name, None)
    return schema


def document_problems(app: FastAPI) -> None:
    """Make ``app.openapi()`` document the problem answers of every operation."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = add_problem_responses(generate())
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
