"""Profile aliases: list, set or move (`champion` = activate), delete. Every write is audited."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Path

from app.http.deps import AdminIdDep, StoreDep
from app.http.errors import RequestError
from app.http.json_body import body_doc, json_body
from app.schemas.aliases import AliasIn, AliasList, AliasOut
from app.schemas.types import AliasName, ErrorResponse, ProfileName
from app.store import CHAMPION, AliasRecord, AuditEntry

router = APIRouter(prefix="/v1/profiles", tags=["profiles"])
ADMIN_ERRORS = {code: {"model": ErrorResponse} for code in (401, 403, 404)}

AliasPath = Annotated[AliasName, Path(description="`champion` (the active version), "
                                                  "`challenger` or any alias name")]


def _out(r: AliasRecord) -> AliasOut:
    return AliasOut(name=r.name, alias=r.alias, version=r.version, id=f"{r.name}@{r.version}",
                    updated_at=r.updated_at)


@router.get("/{name}/aliases", responses={404: {"model": ErrorResponse}})
def list_aliases(name: ProfileName, store: StoreDep) -> AliasList:
    """Every alias of a profile name and the version it points at, `champion` first."""
    store.versions(name)   # 404 for an unknown name
    return AliasList(name=name, aliases=[_out(a) for a in store.aliases(name)])


@router.put("/{name}/aliases/{alias}", openapi_extra=body_doc(AliasIn),
            responses={**ADMIN_ERRORS, 415: {"model": ErrorResponse}})
def set_alias(name: ProfileName, alias: AliasPath,
              body: Annotated[AliasIn, Depends(json_body(AliasIn))], store: StoreDep,
              token: AdminIdDep) -> AliasOut:
    """Point an alias at a version (create or move it); `champion` activates the version."""
    # the store adds `previous`, read in the write's own transaction
    audit = AuditEntry("activate" if alias == CHAMPION else "alias", f"{name}@{alias}", token,
                       {"version": body.version})
    return _out(store.set_alias(name, alias, body.version, audit))


@router.delete("/{name}/aliases/{alias}", responses={**ADMIN_ERRORS,
                                                     409: {"model": ErrorResponse},
                                                     422: {"model": ErrorResponse}})
def delete_alias(name: ProfileName, alias: AliasPath, store: StoreDep, token: AdminIdDep
                 ) -> AliasOut:
    """Remove an alias; the removed one (409 for `champion`: activate another version)."""
    if alias == CHAMPION:
        raise RequestError(["path", "alias"], "champion is the active version and cannot be "
                                              "deleted; activate another version instead",
                           status=409)
    audit = AuditEntry("alias.delete", f"{name}@{alias}", token)   # the store adds `previous`
    return _out(store.delete_alias(name, alias, audit))
