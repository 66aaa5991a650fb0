"""Virtual objects for AR: upload a GLB / OBJ / PLY mesh, get an id to use in ``/ar`` requests."""

from __future__ import annotations

from fastapi import APIRouter, Depends, File, HTTPException, Response, UploadFile, status
from starlette.concurrency import run_in_threadpool

from ar import AssetError
from ar.assets import MAX_ASSET_BYTES
from server.assets import AssetsFull, AssetStore
from server.deps import get_assets, require_token
from server.helper_pool import PoolBusy
from server.schemas import AssetOut, ErrorOut

router = APIRouter(prefix="/api/assets", tags=["ar"], dependencies=[Depends(require_token)],
                   responses={401: {"model": ErrorOut}})


@router.post("", status_code=status.HTTP_201_CREATED, response_model=AssetOut,
             responses={413: {"model": ErrorOut}, 422: {"model": ErrorOut}, 409: {"model": ErrorOut},
                        503: {"model": ErrorOut}},
             summary="Upload a virtual object (GLB, OBJ or PLY)")
async def upload_asset(file: UploadFile = File(description="a .glb, .obj or .ply mesh"),
                       assets: AssetStore = Depends(get_assets)) -> AssetOut:
    """The file is parsed (in the decode helper, within the asset limits) before it is stored;
    its name is used only for the extension. 422 names the limit a file is over; 503 with
    ``Retry-After`` when the helper stays busy with other work."""
    data = await file.read(MAX_ASSET_BYTES + 1)
    if len(data) > MAX_ASSET_BYTES:
        raise HTTPException(413,
                            f"asset larger than {MAX_ASSET_BYTES // (1024 * 1024)} MiB")
    try:
        asset_id, vertices, faces = await run_in_threadpool(assets.add, data, file.filename or "")
    except AssetError as error:
        raise HTTPException(422, str(error)) from None
    except AssetsFull as error:
        raise HTTPException(409, str(error)) from None
    except PoolBusy as error:
        raise HTTPException(503, str(error), headers={"Retry-After": str(error.retry_after_s)}) from None
    return AssetOut(id=asset_id, vertices=vertices, faces=faces)


@router.delete("/{asset_id}", status_code=status.HTTP_204_NO_CONTENT, responses={404: {"model": ErrorOut}},
               summary="Delete an uploaded virtual object")
def delete_asset(asset_id: str, assets: AssetStore = Depends(get_assets)) -> Response:
    try:
        assets.delete(asset_id)
    except KeyError:
        raise HTTPException(404, f"no asset {asset_id!r}") from None
    return Response(status_code=status.HTTP_204_NO_CONTENT)
