"""Sites: PUT to create or rename, GET to read and list, DELETE to remove."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.core.errors import Forbidden
from app.core.schemas import LimitQuery, OffsetQuery, Page, SiteIdPath
from app.keys.deps import AdminDep, PrincipalDep, SiteReaderDep
from app.sites import service
from app.sites.deps import SiteDep
from app.sites.schemas import SiteRead, SiteUpsert
from app.state import SessionDep, StateDep

router = APIRouter(prefix="/v1/sites", tags=["sites"])


@router.put("/{site_id}", response_model=SiteRead)
def put_site(
    _: AdminDep,
    site_id: SiteIdPath,
    body: SiteUpsert,
    db: SessionDep,
    state: StateDep,
    response: Response,
) -> SiteRead:
    """Create the site or update its name and engine (``pf`` or ``hmm``)."""
    site, created = service.upsert_site(db=db, site_id=site_id, body=body)
    db.commit()
    # ingest on this node tags batches with the new version at once, so workers reload
    state.sites.invalidate(site_id)
    response.status_code = 201 if created else 200
    return SiteRead.model_validate(site)


@router.get("", response_model=Page[SiteRead])
def list_sites(
    principal: PrincipalDep, db: SessionDep, limit: LimitQuery = 100, offset: OffsetQuery = 0
) -> Page[SiteRead]:
    """List the sites this key may see."""
    if principal.role == "admin":
        only = None
    elif principal.role == "viewer":
        only = principal.site_id
    else:
        raise Forbidden("device keys may not list sites")
    rows, total = service.list_sites(db=db, only=only, limit=limit, offset=offset)
    items = [SiteRead.model_validate(r) for r in rows]
    return Page[SiteRead](items=items, total=total, limit=limit, offset=offset)


@router.get("/{site_id}", response_model=SiteRead)
def get_site(_: SiteReaderDep, site: SiteDep) -> SiteRead:
    """Return one site."""
    return SiteRead.model_validate(site)


@router.delete("/{site_id}", status_code=204)
def delete_site(_: AdminDep, site: SiteDep, db: SessionDep, state: StateDep) -> Response:
    """Delete the site and everything recorded for it."""
    site_id = site.id
    service.delete_site(db=db, site=site)
    db.commit()
    # ingest on this node refuses the site at once
    state.sites.invalidate(site_id)
    return Response(status_code=204)
