"""Keys: admins create, list and revoke device, viewer and admin keys."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from app.core.schemas import ID_PATTERN, LimitQuery, OffsetQuery, Page
from app.keys import service
from app.keys.deps import AdminDep, PrincipalDep
from app.keys.schemas import KeyCreate, KeyCreated, KeyInfo, KeyRead
from app.sites.service import require_site
from app.state import SessionDep, StateDep

router = APIRouter(prefix="/v1/keys", tags=["keys"])


@router.get("/self", response_model=KeyRead)
async def who_am_i(principal: PrincipalDep) -> KeyRead:
    """Return the calling key's role and site (dashboards decide what to show by it)."""
    return KeyRead(role=principal.role, site_id=principal.site_id)


@router.post("", response_model=KeyCreated, status_code=201)
def create_key(_: AdminDep, body: KeyCreate, db: SessionDep) -> KeyCreated:
    """Create a key; the key itself is returned only in this answer."""
    if body.site_id is not None:
        require_site(db=db, site_id=body.site_id)
    key = service.create_key(db=db, role=body.role, site_id=body.site_id, label=body.label)
    db.commit()
    return KeyCreated(key=key, role=body.role, site_id=body.site_id, label=body.label)


@router.get("", response_model=Page[KeyInfo])
def list_keys(
    _: AdminDep,
    db: SessionDep,
    site_id: Annotated[str | None, Query(pattern=ID_PATTERN)] = None,
    limit: LimitQuery = 100,
    offset: OffsetQuery = 0,
) -> Page[KeyInfo]:
    """List keys (admin), revoked ones with their revocation time; never the keys themselves."""
    rows, total = service.list_keys(db=db, site_id=site_id, limit=limit, offset=offset)
    items = [KeyInfo.model_validate(r) for r in rows]
    return Page[KeyInfo](items=items, total=total, limit=limit, offset=offset)


@router.delete("/{key_id}", status_code=204)
def revoke_key(_: AdminDep, key_id: int, db: SessionDep, state: StateDep) -> Response:
    """Revoke a key (admin): it stops working at once on this node and within a second on
    every node, open WebSockets included. 409 for the last working admin key."""
    row = service.revoke_key(db=db, key_id=key_id)
    db.commit()
    state.revocations.revoked([(row.id, row.key_hash)])
    return Response(status_code=204)
