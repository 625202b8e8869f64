"""The site named by a request's path, or 404."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends

from app.core.schemas import SiteIdPath
from app.sites.models import Site
from app.sites.service import require_site
from app.state import SessionDep


def site_or_404(site_id: SiteIdPath, db: SessionDep) -> Site:
    """Return the path's site or answer 404."""
    return require_site(db=db, site_id=site_id)


SiteDep = Annotated[Site, Depends(site_or_404)]
