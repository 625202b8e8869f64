"""Load-or-404 for sites."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends

from app.core.deps import SessionDep
from app.core.errors import ApiError
from app.core.schemas import SiteIdPath
from app.sites.models import Site
from app.sites.service import get_site


def load_site(site_id: SiteIdPath, db: SessionDep) -> Site:
    """Return the path's site or answer 404."""
    site = get_site(db=db, site_id=site_id)
    if site is None:
        raise ApiError(404, f"site '{site_id}' not found")
    return site


SiteDep = Annotated[Site, Depends(load_site)]
