"""Keys: admins create device, viewer and admin keys."""

from __future__ import annotations

from fastapi import APIRouter

from app.keys import service
from app.keys.deps import AdminDep, PrincipalDep
from app.keys.schemas import KeyCreate, KeyCreated, KeyRead
from app.sites.service import require_site
from app.state import SessionDep

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
