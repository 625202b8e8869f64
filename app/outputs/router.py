"""Outputs: PUT an MQTT broker or a webhook for a site, read them with their status, DELETE."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response

from app.core.schemas import ID_PATTERN, LimitQuery, OffsetQuery, Page
from app.keys.deps import AdminDep, SiteReaderDep
from app.outputs import service
from app.outputs.schemas import OutputRead, OutputUpsert
from app.sites.deps import SiteDep
from app.state import SessionDep

router = APIRouter(prefix="/v1/sites/{site_id}/outputs", tags=["outputs"])

OutputIdPath = Annotated[str, Path(pattern=ID_PATTERN, description="Output identifier")]


@router.put("/{output_id}", response_model=OutputRead)
def put_output(
    _: AdminDep,
    site: SiteDep,
    output_id: OutputIdPath,
    body: OutputUpsert,
    db: SessionDep,
    response: Response,
) -> OutputRead:
    """Create or replace an output; positions and zone events stored from then on go to it."""
    output, created = service.upsert_output(db=db, site_id=site.id, output_id=output_id, body=body)
    db.commit()
    response.status_code = 201 if created else 200
    return service.read_all(db=db, outputs=[output], site_id=site.id)[0]


@router.get("", response_model=Page[OutputRead])
def list_outputs(
    _: SiteReaderDep,
    site: SiteDep,
    db: SessionDep,
    limit: LimitQuery = 100,
    offset: OffsetQuery = 0,
) -> Page[OutputRead]:
    """List the site's outputs with their delivery status (never their secrets)."""
    outputs = service.list_outputs(db=db, site_id=site.id)
    items = service.read_all(db=db, outputs=outputs[offset : offset + limit], site_id=site.id)
    return Page[OutputRead](items=items, total=len(outputs), limit=limit, offset=offset)


@router.get("/{output_id}", response_model=OutputRead)
def get_output(
    _: SiteReaderDep, site: SiteDep, output_id: OutputIdPath, db: SessionDep
) -> OutputRead:
    """Return one output with its delivery status (never its secret)."""
    output = service.get_output(db=db, site_id=site.id, output_id=output_id)
    return service.read_all(db=db, outputs=[output], site_id=site.id)[0]


@router.delete("/{output_id}", status_code=204)
def delete_output(_: AdminDep, site: SiteDep, output_id: OutputIdPath, db: SessionDep) -> Response:
    """Delete the output and the messages still waiting for it."""
    output = service.get_output(db=db, site_id=site.id, output_id=output_id)
    service.delete_output(db=db, output=output)
    db.commit()
    return Response(status_code=204)
