"""Per-sample validation: an impossible value drops its sample (or only its optional field).

The structure of a body (JSON, types, required fields, sizes) is all-or-nothing:
such errors still reject the request. A *value* that no radio or sensor can
produce (an RSSI above 0 dBm, a transmit power of +86 dBm, a NaN sent as the
string ``"NaN"``) is a fault of one sample, not of the batch: that sample is
left out, or only its optional field where the rest is sound, and the drop is
reported to the client and counted in metrics by reason.
"""

from __future__ import annotations

import json
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

VALUE_ERRORS = frozenset(
    {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"}
)
"""Pydantic error types that judge a well-typed value impossible, not a malformed body."""

MAX_REPORTED = 100
"""At most this many drops are listed in an answer; ``dropped_total`` gives the count."""

Drop = dict[str, Any]
M = TypeVar("M", bound=BaseModel)


def _reason(error: ErrorDetails) -> tuple[str, str]:
    """Return a value error's code (``finite_number``, ``less_than_equal``) and message."""
    return error["type"], error["msg"]


def screen_samples(data: Any, kinds: dict[str, type[BaseModel]]) -> tuple[Any, list[Drop]]:
    """Return ``data`` with impossible samples or optional fields removed, and what went.

    ``kinds`` maps each sample list's key to the model of its items. Items with
    a structural error are left as they are, so the body's own validation
    rejects them with its usual message.
    """
    if not isinstance(data, dict):
        return data, []
    out = dict(data)
    drops: list[Drop] = []
    for kind, model in kinds.items():
        items = data.get(kind)
        if not isinstance(items, list):
            continue
        kept: list[Any] = []
        for index, item in enumerate(items):
            screened, item_drops = _screen_one(item, model, kind, index)
            drops.extend(item_drops)
            if screened is not None:
                kept.append(screened)
        out[kind] = kept
    return out, drops


def _screen_one(
    item: Any, model: type[BaseModel], kind: str, index: int
) -> tuple[Any | None, list[Drop]]:
    """Return the item (trimmed of impossible optional fields) or None, and its drops."""
    if not isinstance(item, dict):
        return item, []
    drops: list[Drop] = []
    current = dict(item)
    while True:
        try:
            model.model_validate(current)
            return current, drops
        except ValidationError as exc:
            errors = exc.errors(include_url=False)
        if any(e["type"] not in VALUE_ERRORS for e in errors):
            # a structural fault: leave the item for the body's validation to reject
            return item, []
        fields = {str(e["loc"][0]) for e in errors if e["loc"]}
        optional = {f for f in fields if f in model.model_fields and not _required(model, f)}
        if optional != fields:
            # a required value is impossible: the whole sample goes
            field = min(fields - optional)
            reason = _reason(next(e for e in errors if e["loc"] and str(e["loc"][0]) == field))
            return None, [*drops, _drop(kind, index, field, reason, "sample")]
        removed = False
        for e in errors:
            field = str(e["loc"][0])
            if field in current:
                drops.append(_drop(kind, index, field, _reason(e), "field"))
                del current[field]
                removed = True
        if not removed:
            return None, [*drops, _drop(kind, index, "", _reason(errors[0]), "sample")]


def _required(model: type[BaseModel], field: str) -> bool:
    return model.model_fields[field].is_required()


def _drop(kind: str, index: int, field: str, reason: tuple[str, str], what: str) -> Drop:
    code, message = reason
    return {
        "kind": kind,
        "index": index,
        "field": field,
        "code": code,
        "reason": message,
        "dropped": what,
    }


def validate_screened(
    model: type[M], raw: bytes | str, kinds: dict[str, type[BaseModel]]
) -> tuple[M, list[Drop]]:
    """Validate a JSON body, dropping impossible samples; raise ValidationError otherwise.

    The common case, a body with nothing to drop, takes pydantic's JSON fast path.
    """
    try:
        return model.model_validate_json(raw), []
    except ValidationError as exc:
        if any(e["type"] not in VALUE_ERRORS for e in exc.errors()):
            raise
    data, drops = screen_samples(json.loads(raw), kinds)
    return model.model_validate(data), drops


def report(drops: list[Drop]) -> dict[str, Any]:
    """Return the answer's part about drops: nothing when none, else the list (capped)."""
    if not drops:
        return {}
    return {"dropped": drops[:MAX_REPORTED], "dropped_total": len(drops)}
