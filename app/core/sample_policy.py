"""Per-sample validation: an impossible value drops its sample (or only its optional field).

The structure of a body (JSON, types, required fields, sizes) is all-or-nothing:
such errors still reject the request. A *value* that no radio or sensor can
produce (an RSSI above 0 dBm, a transmit power of +86 dBm, a NaN sent as the
string ``"NaN"``) is a fault of one sample, not of the batch: that sample is
left out, or only its optional field where the rest is sound, and the drop is
reported to the client and counted in metrics by reason.

Times are judged within the body, never against the server's clock, so a
recording from years ago replays: ``t`` is milliseconds since the epoch, and a
body whose median time reads as seconds, microseconds or nanoseconds since the
epoch is refused whole, naming the unit. A sample far from the body's median
time (a clock that jumped) is dropped like an impossible value; an *anchor*
that far (a survey's waypoint, which places every sample around it) refuses
the body.
"""

from __future__ import annotations

import itertools
import json
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails, PydanticCustomError

from app.core.errors import Invalid

VALUE_ERRORS = frozenset(
    {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"}
)
"""Pydantic error types that judge a well-typed value impossible, not a malformed body."""

MIN_T_MS = 946_684_800_000
"""2000-01-01 in ms: anything earlier is a device clock that was never set."""

MAX_T_MS = 10**14
"""Year 5138 in ms: a median time beyond it is in a finer unit."""

OTHER_UNITS = (("seconds", 1e-3), ("microseconds", 1e3), ("nanoseconds", 1e6))
"""Units a device clock is mistakenly sent in, with their count per millisecond."""


def unit_of(t: float) -> str | None:
    """Return the unit ``t`` reads as when it is a time from 2000 to 5138 in another unit
    than milliseconds since the epoch (``"seconds"``, ...), else None."""
    for unit, per_ms in OTHER_UNITS:
        if MIN_T_MS * per_ms <= t < MAX_T_MS * per_ms:
            return unit
    return None


def check_ms(t: int) -> int:
    """Return ``t`` when it is milliseconds since the epoch from 2000 to 5138; else raise a
    value error that says ``t`` is in milliseconds and, when it reads as another unit, which.

    The error keeps pydantic's ``greater_than_equal``/``less_than_equal`` type, so one sample
    with such a time is dropped like any impossible value rather than refusing its batch.
    """
    if MIN_T_MS <= t < MAX_T_MS:
        return t
    unit = unit_of(t)
    if unit is not None:
        message = f"t {t} looks like {unit} since the epoch; t must be milliseconds since the epoch"
    elif t < MIN_T_MS:
        message = (
            f"t {t} is before 2000-01-01 ({MIN_T_MS}); t must be milliseconds since the epoch "
            "from a clock that was set"
        )
    else:
        message = f"t {t} is after the year 5138; t must be milliseconds since the epoch"
    kind = "greater_than_equal" if t < MIN_T_MS else "less_than_equal"
    raise PydanticCustomError(kind, message)


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
        if drops and all(not e["loc"] for e in errors):
            # nothing sound is left (an imu sample whose only sensor read NaN): the sample
            # goes, for its first impossible field, and the body stays
            first = drops[0]
            return None, [
                _drop(kind, index, first["field"], (first["code"], first["reason"]), "sample")
            ]
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


def body_indices(kind: str, count: int, earlier: list[Drop]) -> list[int]:
    """Return the body indices of the ``count`` samples of ``kind`` left after the samples
    dropped ``earlier``, so that every drop names the sample as the client sent it."""
    gone = {d["index"] for d in earlier if d["kind"] == kind and d["dropped"] == "sample"}
    return list(itertools.islice((i for i in itertools.count() if i not in gone), count))


def _median(times: list[float]) -> float:
    """Return the lower median: a time of the body itself, so one sample at least is near it.

    Plain Python: a body holds tens of times, where a numpy call costs more than the sort.
    """
    ordered = sorted(times)
    return float(ordered[(len(ordered) - 1) // 2])


def check_time_units(times: list[float]) -> None:
    """Raise Invalid when the median of ``times`` reads as another unit than milliseconds
    since the epoch (a time from 2000 to 5138 in that unit)."""
    if times:
        _check_unit(_median(times))


def _check_unit(median: float) -> None:
    unit = unit_of(median)
    if unit is not None:
        message = (
            f"sample times look like {unit} since the epoch (median t {median:.0f}); "
            "t must be milliseconds since the epoch"
        )
        raise Invalid(
            message,
            code="timestamp_units",
            details=[{"loc": ["t"], "msg": message, "type": "timestamp_units"}],
        )


def _raw_times(data: Any) -> list[float]:
    """Return every number given as ``t`` in the lists of a JSON body (up to nanoseconds in
    the year 5138: beyond, a float would not hold it)."""
    lists = data.values() if isinstance(data, dict) else ()
    items = (i for v in lists if isinstance(v, list) for i in v if isinstance(i, dict))
    times = (i.get("t") for i in items)
    numbers = (t for t in times if isinstance(t, int | float) and not isinstance(t, bool))
    return [float(t) for t in numbers if abs(t) < MAX_T_MS * 1e6]


def _duration(ms: float) -> str:
    s = ms / 1000
    if s >= 86_400:
        return f"{s / 86_400:.1f} days"
    if s >= 3600:
        return f"{s / 3600:.1f} hours"
    return f"{s:.0f} s"


def _offset(t: int, median: float, max_offset_ms: int) -> str:
    return (
        f"t={t} is {_duration(abs(t - median))} from the median time ({median:.0f}); "
        f"at most {_duration(max_offset_ms)}"
    )


def screen_times(
    body: M,
    kinds: tuple[str, ...],
    anchors: tuple[str, ...],
    *,
    max_offset_ms: int,
    earlier: list[Drop],
) -> tuple[M, list[Drop]]:
    """Return ``body`` without the samples of ``kinds`` more than ``max_offset_ms`` from the
    median time of its samples and ``anchors``, and what went.

    Raise Invalid when the times are in another unit, or an item of ``anchors`` is that far.
    ``earlier`` are the drops before, for the samples' body indices.
    """
    every = [s.t for k in (*anchors, *kinds) for s in getattr(body, k)]
    if not every:
        return body, []
    lo, hi = min(every), max(every)
    if hi - lo <= max_offset_ms and MIN_T_MS <= lo and hi < MAX_T_MS:
        # the usual body: the median lies between the extremes, so nothing is far from it,
        # and it is in milliseconds as they are (a sixth of the time of the full check)
        return body, []
    times = {k: [s.t for s in getattr(body, k)] for k in (*anchors, *kinds)}
    median = _median(every)
    _check_unit(median)
    far = {
        k: [i for i, t in enumerate(ts) if abs(t - median) > max_offset_ms]
        for k, ts in times.items()
    }
    for kind in anchors:
        if far[kind]:
            offsets = {i: _offset(times[kind][i], median, max_offset_ms) for i in far[kind]}
            first = min(offsets)
            raise Invalid(
                f"{kind}[{first}]: {offsets[first]}",
                code="clock_skew",
                details=[
                    {"loc": [kind, i, "t"], "msg": msg, "type": "clock_skew"}
                    for i, msg in offsets.items()
                ],
            )
    update: dict[str, list[Any]] = {}
    drops: list[Drop] = []
    for kind in (k for k in kinds if far[k]):
        index = body_indices(kind, len(times[kind]), earlier)
        for i in far[kind]:
            reason = _offset(times[kind][i], median, max_offset_ms)
            drops.append(_drop(kind, index[i], "t", ("time_outlier", reason), "sample"))
        gone = set(far[kind])
        update[kind] = [s for i, s in enumerate(getattr(body, kind)) if i not in gone]
    return (body.model_copy(update=update) if update else body), drops


def _loads(raw: bytes | str) -> Any:
    try:
        return json.loads(raw)
    except ValueError:
        return None


def validate_screened(
    model: type[M],
    raw: bytes | str,
    kinds: dict[str, type[BaseModel]],
    *,
    max_offset_ms: int,
    anchors: tuple[str, ...] = (),
) -> tuple[M, list[Drop]]:
    """Validate a JSON body, dropping impossible samples and samples far from the body's
    time; raise ValidationError for a structural fault, Invalid for a clock in another unit
    or an anchor far off (see ``screen_times``).

    The common case, a body with nothing to drop, takes pydantic's JSON fast path.
    """
    drops: list[Drop] = []
    try:
        body = model.model_validate_json(raw)
    except ValidationError as exc:
        data = _loads(raw)
        # times in seconds fail as values, from time.time() as types: name the unit first
        check_time_units(_raw_times(data))
        if data is None or any(e["type"] not in VALUE_ERRORS for e in exc.errors()):
            raise
        data, drops = screen_samples(data, kinds)
        if drops and not any(data.get(kind) for kind in kinds):
            # name why nothing is left, not just that nothing is
            raise Invalid(
                f"every sample was dropped ({len(drops)}): none is physically possible",
                details=drops[:MAX_REPORTED],
            ) from exc
        body = model.model_validate(data)
    body, far = screen_times(
        body, tuple(kinds), anchors, max_offset_ms=max_offset_ms, earlier=drops
    )
    return body, drops + far


def report(drops: list[Drop]) -> dict[str, Any]:
    """Return the answer's part about drops: the list (capped, empty when none) and the count."""
    return {"dropped": drops[:MAX_REPORTED], "dropped_total": len(drops)}
