"""Split a bulk ingest body into its batches, each as its own JSON, checking only the envelope.

Each batch of ``POST /v1/ingest/bulk`` is validated as the single ingest
validates its body: from JSON, on pydantic's fast path. The envelope is cut
with msgspec, which hands back every batch as the bytes the client sent
(``msgspec.Raw``) and counts their samples without building them, where
decoding the whole body with the json module and encoding each batch back
would cost as much again as validating the batches (``bench/load.py``'s
``bulk`` mode measures it). A body msgspec cannot read but the json module
can (``NaN`` literals, lone surrogate escapes), and every body refused as
a whole, takes that slower road, so both roads accept and refuse the same
bodies with the same errors.
"""

from __future__ import annotations

import json
from typing import Any

import msgspec

from app.core.config import Settings
from app.core.errors import Invalid, TooLarge, not_json
from app.ingest.schemas import SAMPLE_KINDS


class _SampleLists(msgspec.Struct):
    """A batch's sample lists, decoded only to be counted (every other field is skipped)."""

    wifi: list[msgspec.Raw] = []
    ble: list[msgspec.Raw] = []
    imu: list[msgspec.Raw] = []
    uwb: list[msgspec.Raw] = []
    uwb_fix: list[msgspec.Raw] = []
    baro: list[msgspec.Raw] = []


_ENVELOPE = msgspec.json.Decoder(dict[str, msgspec.Raw])
_RAW_LIST = msgspec.json.Decoder(list[msgspec.Raw])
_SAMPLE_LISTS = msgspec.json.Decoder(_SampleLists)


def _not_an_envelope() -> Invalid:
    return Invalid(
        'the body must be an object {"batches": [<ingest body>, ...]}',
        details=[{"loc": ["body", "batches"], "type": "missing_list"}],
    )


def bulk_items(raw: bytes, settings: Settings) -> list[bytes | str]:
    """Return each batch of a bulk body as its own JSON, still unchecked; refuse the body whole
    when its own structure is wrong (not JSON, no ``batches`` list, other keys) or it is too
    large."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise not_json(str(exc)) from exc
    try:
        envelope = _ENVELOPE.decode(text)
    except msgspec.DecodeError:
        # not an object, not JSON, or JSON only the json module reads: its road says which
        return _decoded_items(text, settings)
    if "batches" not in envelope:
        raise _not_an_envelope()
    try:
        batches = _RAW_LIST.decode(envelope["batches"])
    except msgspec.ValidationError:
        raise _not_an_envelope() from None
    _check_envelope(set(envelope), len(batches), settings)
    _check_samples(sum(_sample_count(b) for b in batches), settings)
    return [bytes(b) for b in batches]


def _sample_count(batch: msgspec.Raw) -> int:
    """Return the samples a batch lists (none counted in a list that is not one)."""
    try:
        lists = _SAMPLE_LISTS.decode(batch)
    except msgspec.ValidationError:
        return _count_decoded(msgspec.json.decode(batch))
    return sum(len(getattr(lists, kind)) for kind in SAMPLE_KINDS)


def _count_decoded(batch: Any) -> int:
    """Return the samples a decoded batch lists (none counted in a list that is not one)."""
    if not isinstance(batch, dict):
        return 0
    return sum(len(v) for kind in SAMPLE_KINDS if isinstance(v := batch.get(kind), list))


def _decoded_items(text: str, settings: Settings) -> list[bytes | str]:
    """Split a body through the json module: the road of what msgspec cannot read."""
    try:
        body = json.loads(text)
    except json.JSONDecodeError as exc:
        raise not_json(str(exc)) from exc
    if not isinstance(body, dict) or not isinstance(body.get("batches"), list):
        raise _not_an_envelope()
    batches: list[Any] = body["batches"]
    _check_envelope(set(body), len(batches), settings)
    _check_samples(sum(_count_decoded(b) for b in batches), settings)
    return [json.dumps(b, separators=(",", ":")) for b in batches]


def _check_envelope(keys: set[str], n_batches: int, settings: Settings) -> None:
    """Refuse other fields beside ``batches``, no batch, or more batches than allowed."""
    extra = sorted(keys - {"batches"})
    if extra:
        raise Invalid(
            f"unknown fields in the body: {', '.join(extra)}",
            details=[{"loc": ["body", k], "type": "extra_forbidden"} for k in extra],
        )
    if not n_batches:
        raise Invalid("batches is empty; send at least one ingest body")
    if n_batches > settings.bulk_max_batches:
        raise TooLarge(f"{n_batches} batches in one body; the limit is {settings.bulk_max_batches}")


def _check_samples(samples: int, settings: Settings) -> None:
    """Refuse a body with more samples than allowed."""
    if samples > settings.bulk_max_samples:
        raise TooLarge(
            f"{samples} samples in one bulk body; the limit is {settings.bulk_max_samples}"
        )
